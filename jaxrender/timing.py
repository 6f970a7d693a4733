"""Timing of jitted work, the one loop every `--time` flag, gallery entry and benchmark uses:
the first call (compilation included) apart from the calls after it, each waited for with
`jax.block_until_ready` so that asynchronous dispatch is not mistaken for speed."""

from __future__ import annotations

import dataclasses
import math
import statistics
import time
from collections.abc import Callable
from typing import Any

import jax


@dataclasses.dataclass(frozen=True)
class Timing:
    compile_s: float                 # the first call, tracing and compilation included
    runs_s: tuple[float, ...]        # each later call

    @property
    def median_s(self) -> float:
        return statistics.median(self.runs_s) if self.runs_s else math.nan


def timed_call(fn: Callable[[], Any]) -> tuple[Any, float]:
    """(fn()'s result, waited for; the seconds it took)."""
    start = time.perf_counter()
    result = jax.block_until_ready(fn())
    return result, time.perf_counter() - start


def time_calls(fn: Callable[[], Any], repeats: int) -> tuple[Any, Timing]:
    """Call `fn()` once, then `repeats` more times; (the first call's result, the timing)."""
    result, compile_s = timed_call(fn)
    return result, Timing(compile_s, tuple(timed_call(fn)[1] for _ in range(repeats)))

"""The timing helper of the desert and shafts_speed benchmarks: compile (first call) apart from run time."""

from __future__ import annotations

import statistics
import time

import jax


def timed(fn, repeats: int) -> tuple[float, float]:
    """(seconds of the first call, compilation included; median seconds of `repeats` more calls),
    each call waited for with `block_until_ready`."""
    start = time.perf_counter()
    jax.block_until_ready(fn())
    compile_s = time.perf_counter() - start
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return compile_s, statistics.median(times)

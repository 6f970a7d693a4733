"""The timing helper of the desert and shafts_speed benchmarks: compile (first call) apart from run time."""

from __future__ import annotations

from jaxrender.timing import time_calls


def timed(fn, repeats: int) -> tuple[float, float]:
    """(seconds of the first call, compilation included; median seconds of `repeats` more calls)."""
    _, timing = time_calls(fn, repeats)
    return timing.compile_s, timing.median_s

"""`--time N`, the timing contract of the render commands: compile apart from the runs after it."""

from __future__ import annotations

import argparse
import statistics
from collections.abc import Callable, Sequence

from jaxrender.timing import time_calls

from .arguments import count


def add_time_argument(parser: argparse.ArgumentParser, what: str = "render") -> None:
    """`--time N`: after compiling, time N more runs (the render commands share this contract)."""
    parser.add_argument("--time", type=count, default=0, metavar="N",
                        help=f"after compiling, {what} N more times and print compile_s=... median_frame_s=...")


def print_timing(compile_s: float, times: Sequence[float]) -> None:
    """The one line `--time` prints: `compile_s=<float> median_frame_s=<float>`."""
    print(f"compile_s={compile_s:.4f} median_frame_s={statistics.median(times):.4f}")


def render_timed(render: Callable[[], object], repeats: int):
    """render() once (compilation included), then `repeats` more timed runs printed with
    `print_timing` when repeats > 0; returns the first result."""
    result, timing = time_calls(render, repeats)
    if repeats > 0:
        print_timing(timing.compile_s, timing.runs_s)
    return result

"""The one command-line driver shared by `jaxrender`, `fitting` and `sims`.

Each subcommand lives in its own module exposing `configure(parser)` and `run(args) -> int`;
it is imported only when asked for, so `jaxrender --help` stays fast. Bad input raises
`jaxrender.io.InputError`, which becomes one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import sys
import time
from collections.abc import Callable, Sequence


def run_cli(prog: str, description: str, commands: dict[str, tuple[str, str]],
            argv: Sequence[str] | None = None) -> int:
    """`commands` maps a name to (module path, one-line help)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in commands:
        lines = [f"usage: {prog} COMMAND [options]", "", description, "", "commands:"]
        lines += [f"  {name:<10} {help_}" for name, (_, help_) in commands.items()]
        text = "\n".join(lines)
        if argv and argv[0] not in ("-h", "--help"):
            print(f"{prog}: unknown command {argv[0]!r}\n\n{text}", file=sys.stderr)
            return 2
        print(text)
        return 0 if argv else 2
    name = argv[0]
    module_path, help_ = commands[name]
    module = importlib.import_module(module_path)
    parser = argparse.ArgumentParser(prog=f"{prog} {name}", description=help_)
    module.configure(parser)
    args = parser.parse_args(argv[1:])
    from jaxrender.io import InputError  # imported late: keeps --help free of jax

    try:
        return int(module.run(args) or 0)
    except InputError as error:
        print(f"{prog} {name}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog} {name}: interrupted", file=sys.stderr)
        return 130


def add_time_argument(parser: argparse.ArgumentParser, what: str = "render") -> None:
    """`--time N`: after compiling, time N more runs (the render commands share this contract)."""
    parser.add_argument("--time", type=int, default=0, metavar="N",
                        help=f"after compiling, {what} N more times and print compile_s=... median_frame_s=...")


def print_timing(compile_s: float, times: Sequence[float]) -> None:
    """The one line `--time` prints: `compile_s=<float> median_frame_s=<float>`."""
    print(f"compile_s={compile_s:.4f} median_frame_s={statistics.median(times):.4f}")


def render_timed(render: Callable[[], object], repeats: int):
    """render() once (compilation included), then `repeats` more timed runs printed with
    `print_timing` when repeats > 0; returns the first result."""
    start = time.perf_counter()
    result = render()
    compile_s = time.perf_counter() - start
    if repeats > 0:
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            render()
            times.append(time.perf_counter() - start)
        print_timing(compile_s, times)
    return result

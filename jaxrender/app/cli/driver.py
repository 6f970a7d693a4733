"""The one command-line driver shared by `jaxrender`, `fitting` and `sims`.

Each subcommand lives in its own module exposing `configure(parser)` and `run(args) -> int`;
it is imported only when asked for, so `jaxrender --help` answers without importing jax.

Every failure becomes one line on stderr naming the file and the problem, with the exit code of
its kind (`jaxrender.errors`: 2 bad input, 3 a fault of the machine, 4 the output busy, 1 a bug);
`--debug` or `JAXRENDER_DEBUG=1` prints the traceback above it. Compiled programs are kept between
runs (`compile_cache`).
"""

from __future__ import annotations

import argparse
import errno
import importlib
import logging
import os
import sys
import traceback
import warnings
from collections.abc import Sequence
from types import ModuleType

from jaxrender.errors import (
    EXIT_BUSY,
    EXIT_INPUT,
    EXIT_INTERNAL,
    EXIT_INTERRUPTED,
    EXIT_MACHINE,
    InputError,
    NonFiniteOutput,
    OutputBusy,
)

from .compile_cache import use_compile_cache

DEBUG_ENV = "JAXRENDER_DEBUG"
# an OSError with one of these names a path the user gave that is not there or not of the right kind
_INPUT_ERRNOS = {errno.ENOENT, errno.ENOTDIR, errno.EISDIR, errno.EEXIST, errno.ENAMETOOLONG, errno.ELOOP}
_OUTPUT_ARGUMENTS = ("out", "store", "out_dir")   # named when a failed write does not say which file


def _output_of(args) -> str | None:
    for name in _OUTPUT_ARGUMENTS:
        value = getattr(args, name, None)
        if value is not None:
            return os.fspath(value)
    return None


_OUT_OF_MEMORY = ("RESOURCE_EXHAUSTED", "out of memory", "bad_alloc", "failed to allocate")
_MEMORY_OPTIONS = ("memory_gb", "chunk")   # the options that lower a command's memory, where it has them


def _out_of_memory(error: BaseException) -> bool:
    if isinstance(error, MemoryError):
        return True
    text = str(error).lower()
    return type(error).__name__ in ("XlaRuntimeError", "JaxRuntimeError") and any(
        s.lower() in text for s in _OUT_OF_MEMORY)


def describe_failure(error: BaseException, output: str | None = None, options=()) -> tuple[int, str]:
    """(exit code, message) of a failure: the file and the problem, one line (an `InputErrors`: one per
    problem). `options`: the command's argument names (its advice names only options it has)."""
    if isinstance(error, InputError):
        return EXIT_INPUT, str(error)
    if isinstance(error, OutputBusy):
        return EXIT_BUSY, str(error)
    where = f"{output}: " if output else ""
    if isinstance(error, NonFiniteOutput):
        return EXIT_INTERNAL, (f"internal error: {error} (a bug: rerun with --debug or {DEBUG_ENV}=1 for the "
                               "traceback, and report it)")
    if _out_of_memory(error):
        lower = [f"--{name.replace('_', '-')}" for name in _MEMORY_OPTIONS if name in options]
        advice = f"free memory or lower {'/'.join(lower)}" if lower else "free memory or ask for a smaller output"
        said = str(error) if isinstance(error, MemoryError) and str(error) else type(error).__name__
        return EXIT_MACHINE, f"{where}out of memory ({said}); {advice}"
    if isinstance(error, OSError):
        # a failed write names no file (a full disk): name the command's output; an error without an
        # errno (a Dask scheduler that does not answer) is not about the output
        path = error.filename if error.filename is not None else (output if error.errno is not None else None)
        problem = error.strerror or str(error) or type(error).__name__
        if error.filename2 is not None:
            problem += f" ({os.fspath(error.filename2)})"
        text = f"{os.fspath(path)}: {problem}" if path is not None else problem
        return (EXIT_INPUT if error.errno in _INPUT_ERRNOS else EXIT_MACHINE), text
    first = (str(error).strip().splitlines() or [""])[0]
    return EXIT_INTERNAL, (f"internal error: {type(error).__name__}: {first} (a bug: rerun with --debug or "
                           f"{DEBUG_ENV}=1 for the traceback, and report it)")


class UsageError(Exception):
    """A command line argparse refuses (a bad option or value): one line, exit code 2."""


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):   # argparse would print the usage too: the one line is enough
        raise UsageError(f"{self.prog}: error: {message} (--help lists the options)")


def command_parser(prog: str, name: str, commands: dict[str, tuple[str, str]]
                   ) -> tuple[ModuleType, argparse.ArgumentParser]:
    """The subcommand's module (imported now) and its configured parser (also read by the docs' CLI pages)."""
    module_path, help_ = commands[name]
    module = importlib.import_module(module_path)
    parser = _Parser(prog=f"{prog} {name}", description=help_)
    module.configure(parser)
    parser.add_argument("--debug", action="store_true",
                        help=f"on failure, print the traceback above the one-line error (also: {DEBUG_ENV}=1)")
    return module, parser


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
    module, parser = command_parser(prog, name, commands)
    try:
        args = parser.parse_args(argv[1:])
    except UsageError as error:
        print(error, file=sys.stderr)
        return EXIT_INPUT
    shown = warnings.showwarning
    # a warning is one line too, naming the command (Python's shows the source line below it)
    warnings.showwarning = lambda message, *rest, **kw: print(f"{prog} {name}: warning: {message}", file=sys.stderr)
    try:
        use_compile_cache()   # a second run loads what the first compiled
        return int(module.run(args) or 0)
    except KeyboardInterrupt:
        print(f"{prog} {name}: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as error:
        if args.debug or os.environ.get(DEBUG_ENV, "") not in ("", "0"):
            traceback.print_exc()
        else:
            # the line below is the whole report: background tasks a failed write left behind (zarr's
            # chunk writes) must not add their own at exit
            logging.getLogger("asyncio").disabled = True
        code, text = describe_failure(error, _output_of(args), options=vars(args))
        for line in text.splitlines() or [""]:   # one line per problem, each naming the command
            print(f"{prog} {name}: error: {line}", file=sys.stderr)
        return code
    finally:
        warnings.showwarning = shown

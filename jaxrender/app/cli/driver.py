"""The one command-line driver shared by `jaxrender`, `fitting` and `sims`.

Each subcommand lives in its own module exposing `configure(parser)` and `run(args) -> int`;
it is imported only when asked for, so `jaxrender --help` answers without importing jax. Bad
input raises `jaxrender.errors.InputError`, which becomes one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from types import ModuleType

from jaxrender.errors import InputError


def command_parser(prog: str, name: str, commands: dict[str, tuple[str, str]]
                   ) -> tuple[ModuleType, argparse.ArgumentParser]:
    """The subcommand's module (imported now) and its configured parser (also read by the docs' CLI pages)."""
    module_path, help_ = commands[name]
    module = importlib.import_module(module_path)
    parser = argparse.ArgumentParser(prog=f"{prog} {name}", description=help_)
    module.configure(parser)
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
    args = parser.parse_args(argv[1:])
    try:
        return int(module.run(args) or 0)
    except InputError as error:
        print(f"{prog} {name}: error: {error}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog} {name}: interrupted", file=sys.stderr)
        return 130

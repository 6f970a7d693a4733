"""The errors every command line turns into one line on stderr, and their exit codes (no jax needed).

Exit codes (README, "When a command fails"): 0 done, 1 an internal error (a bug: the line says how
to see the traceback), 2 bad input (`InputError`: a file or field and what is wrong with it),
3 a fault of the machine (disk full, read-only file system, permission denied, out of memory, an
I/O error), 4 the output is busy (`OutputBusy`: another process is writing it), 130 interrupted.
"""

from __future__ import annotations

import os

EXIT_INTERNAL = 1
EXIT_INPUT = 2
EXIT_MACHINE = 3
EXIT_BUSY = 4
EXIT_INTERRUPTED = 130


class InputError(Exception):
    """Bad user input: a file (or field) and what is wrong with it, printed as one line.

    Command lines turn it into `error: PATH: problem` on stderr and exit code 2.
    """

    def __init__(self, path: str | os.PathLike | None, problem: str):
        self.path = None if path is None else os.fspath(path)
        self.problem = problem
        super().__init__(problem if path is None else f"{self.path}: {problem}")

    def __reduce__(self):  # pickled with its fields: crosses Dask and process boundaries intact
        return (_rebuild, (type(self), self.args, self.__dict__))


class InputErrors(InputError):
    """Several problems of one input, one `PATH: problem` line each (`str` joins them with newlines)."""

    def __init__(self, problems: list[str]):
        self.problems = list(problems)
        super().__init__(None, "\n".join(self.problems))


class NonFiniteOutput(Exception):
    """A command was about to write NaN or infinite values: a bug (exit code 1), nothing written.

    Inputs that cannot be represented are refused as `InputError`s before the work starts; a
    non-finite value that still appears is the toolkit's fault, reported as such.
    """

    def __init__(self, path: str | os.PathLike | None, problem: str):
        self.path, self.problem = (None if path is None else os.fspath(path)), problem
        super().__init__(problem if path is None else f"{self.path}: {problem}")

    def __reduce__(self):
        return (_rebuild, (type(self), self.args, self.__dict__))


class OutputBusy(Exception):
    """Another live process is writing this output (its lock file names it): exit code 4."""

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path, self.problem = os.fspath(path), problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self):
        return (_rebuild, (type(self), self.args, self.__dict__))


def _rebuild(cls: type, args: tuple, state: dict) -> Exception:
    """An error of class `cls` with its message `args` and fields `state`, without calling `cls.__init__`."""
    error = cls.__new__(cls)
    Exception.__init__(error, *args)
    error.__dict__.update(state)
    return error

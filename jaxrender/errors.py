"""The user-input error every command line turns into one line on stderr and exit code 2 (no jax needed)."""

from __future__ import annotations

import os


class InputError(Exception):
    """Bad user input: a file (or field) and what is wrong with it, printed as one line.

    Command lines turn it into `error: PATH: problem` on stderr and exit code 2.
    """

    def __init__(self, path: str | os.PathLike | None, problem: str):
        self.path = None if path is None else os.fspath(path)
        self.problem = problem
        super().__init__(problem if path is None else f"{self.path}: {problem}")


class InputErrors(InputError):
    """Several problems of one input, one `PATH: problem` line each (`str` joins them with newlines)."""

    def __init__(self, problems: list[str]):
        self.problems = list(problems)
        super().__init__(None, "\n".join(self.problems))

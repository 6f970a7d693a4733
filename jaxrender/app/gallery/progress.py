"""A gallery section's progress bar: drawn by tqdm on a terminal, also where the section renders in
a process of its own (its steps are sent to the gallery's process, which draws it)."""

from __future__ import annotations

from tqdm import tqdm

__all__ = ["progress_bar", "relay_to"]

_PARENT = None   # in a section's own process: the pipe to the gallery's process (`_section_process`)


class _RelayedBar:
    """A section's bar in a process of its own: its steps sent to the gallery's process, which shows it."""

    def __init__(self, total: int, desc: str, unit: str):
        _PARENT.send(("bar", (desc, total, unit)))

    def update(self, n: int = 1) -> None:
        _PARENT.send(("advance", n))

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        _PARENT.send(("bar_done", None))


def relay_to(connection) -> None:
    """In a section's own process: send its bars' steps on `connection` (a pipe's end)."""
    global _PARENT
    _PARENT = connection


def progress_bar(total: int, desc: str, unit: str):
    """A section's progress bar (a context manager with `update(n)`): on a terminal only, also where
    the section renders in a process of its own (the gallery's process draws it)."""
    if _PARENT is not None:
        return _RelayedBar(total, desc, unit)
    return tqdm(total=total, desc=desc, unit=unit, leave=False, disable=None)

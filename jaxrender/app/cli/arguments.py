"""Argument types shared by the subcommands: a bad value is argparse's one-line error (exit 2); and
`check_cells`, the bound on sizes derived from arguments, checked before anything is allocated."""

from __future__ import annotations

import argparse
import math
import os

import numpy as np

from jaxrender.errors import InputError

FLOAT32_MAX = float(np.finfo(np.float32).max)   # what the kernels compute in
MAX_CELLS = 2**31 - 1   # the kernels index cells and pixels with int32


def physical_memory() -> int:
    """Bytes of memory this machine has."""
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def check_cells(what: str, cells: int, *, bytes_per_cell: float) -> None:
    """Refuse a grid or image of `cells` cells before it is allocated: beyond int32 indexing is bad
    input (`InputError`, exit 2); more memory than the machine has (`bytes_per_cell`: the peak
    measured per cell) is a fault of the machine (`MemoryError`, exit 3)."""
    if cells > MAX_CELLS:
        raise InputError(None, f"{what}: {cells:,} cells is beyond what the kernels index (at most {MAX_CELLS:,})")
    need, have = cells * bytes_per_cell, physical_memory()
    if need > have:
        raise MemoryError(f"{what} needs about {need / 2**30:.3g} GiB of memory; this machine has "
                          f"{have / 2**30:.3g} GiB")


def _number(value: str, kind: type, what: str):
    try:
        x = kind(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{value!r} is not {what}") from None
    if kind is float and not (math.isfinite(x) and abs(x) <= FLOAT32_MAX):
        raise argparse.ArgumentTypeError(f"{value!r} is not a finite number within float32's range")
    return x


def number(value: str) -> float:
    """A finite number that float32 represents (inf, nan and 1e39 are refused)."""
    return _number(value, float, "a number")


def count(value: str) -> int:
    """An integer >= 0."""
    n = _number(value, int, "an integer")
    if n < 0:
        raise argparse.ArgumentTypeError("must be >= 0")
    return n


def positive_int(value: str) -> int:
    n = _number(value, int, "an integer")
    if n < 1:
        raise argparse.ArgumentTypeError("must be >= 1")
    return n


def positive_float(value: str) -> float:
    x = _number(value, float, "a number")
    if not x > 0:
        raise argparse.ArgumentTypeError("must be > 0")
    return x


def non_negative(value: str) -> float:
    x = _number(value, float, "a number")
    if not x >= 0:
        raise argparse.ArgumentTypeError("must be >= 0")
    return x


"""Argument types shared by the subcommands: a bad value is argparse's one-line error (exit 2)."""

from __future__ import annotations

import argparse


def _number(value: str, kind: type, what: str):
    try:
        return kind(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{value!r} is not {what}") from None


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


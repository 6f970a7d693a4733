"""Typed reads of a parsed document's fields (JSON objects, CSV rows), every problem collected with
where it is: `SOURCE: camera.fov_y_deg: expected a number`.

    doc = Fields.document(data, "scene.json")
    camera = doc.section("camera")
    fov = camera.number("fov_y_deg", lo=0.0, hi=179.0, lo_open=True)   # None when missing or bad
    doc.problems.check()                                                # raises InputErrors listing all

A read that fails notes its problem and returns None, so a validator reads every field and reports
every problem at once; a section that is missing or malformed reads as empty (None, no further
notes). `Problems` stops at `limit` lines (an `InputErrors` raised at once), so a huge bad input
fails fast.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from ..errors import InputErrors

__all__ = ["Fields", "Problems", "MAX_PROBLEMS", "FLOAT32_MAX", "is_number"]

MAX_PROBLEMS = 200  # report this many problems, then stop reading
FLOAT32_MAX = float(np.finfo(np.float32).max)  # the kernels compute in float32: a larger value is infinite there
_MISSING = object()


def is_number(value: Any) -> bool:
    """A finite int or float (bools are not numbers here)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


class Problems:
    """Problem lines of one validation; `add` raises `InputErrors` at once when `limit` is reached."""

    def __init__(self, *, limit: int = MAX_PROBLEMS, error: type[InputErrors] = InputErrors):
        self.lines: list[str] = []
        self.limit, self.error = limit, error

    def __bool__(self) -> bool:
        return bool(self.lines)

    def __len__(self) -> int:
        return len(self.lines)

    def add(self, line: str) -> None:
        self.lines.append(line)
        if len(self.lines) >= self.limit:
            raise self.error(self.lines + [f"... stopped after {self.limit} problems"])

    def extend(self, lines: Iterable[str]) -> None:
        for line in lines:
            self.add(line)

    def check(self) -> None:
        """Raise every problem noted so far (one line each), if any."""
        if self.lines:
            raise self.error(list(self.lines))


class Fields:
    """One object of a document: typed reads of its keys (see the module docstring).

    `where` is the object's path in the document ("" for the top, "lights[3]", "camera");
    `source` the file named in every problem line.
    """

    def __init__(self, data: Any, where: str, source: str, problems: Problems):
        self.data = data if isinstance(data, dict) else None
        self.where, self.source, self.problems = where, str(source), problems

    @classmethod
    def document(cls, data: Any, source, *, limit: int = MAX_PROBLEMS,
                 error: type[InputErrors] = InputErrors) -> "Fields":
        """The top-level object of a parsed document (a problem when it is not an object)."""
        problems = Problems(limit=limit, error=error)
        if not isinstance(data, dict):
            problems.add(f"{source}: expected a JSON object at the top level")
        return cls(data, "", str(source), problems)

    @property
    def valid(self) -> bool:
        return self.data is not None

    def path(self, key: str | None = None) -> str:
        if key is None:
            return self.where
        return f"{self.where}.{key}" if self.where else key

    def problem(self, key: str | None, text: str) -> None:
        """Note `SOURCE: path.key: text` (key None: the object itself)."""
        where = self.path(key)
        self.problems.add(f"{self.source}: {where}: {text}" if where else f"{self.source}: {text}")

    def has(self, key: str) -> bool:
        return self.data is not None and key in self.data

    def raw(self, key: str, default: Any = _MISSING) -> Any:
        """The value as it is; None (and a 'missing field' problem) when absent without a default."""
        if self.data is None:
            return None
        if key not in self.data:
            if default is _MISSING:
                self.problem(key, "missing field")
                return None
            return default
        return self.data[key]

    def known(self, keys: Sequence[str]) -> None:
        """A problem for every key that is not one of `keys` (a typo must not pass silently)."""
        if self.data is None:
            return
        for key in self.data:
            if key not in keys:
                self.problem(key, f"unknown field (expected one of: {', '.join(keys)})")

    def section(self, key: str, *, required: bool = True, defaults: bool = False) -> "Fields":
        """The object under `key` (empty when missing or not an object; a problem noted unless it
        is optional and absent). With `defaults`, an absent optional section reads as `{}`: every
        read of it gives its default."""
        value = self.raw(key, default=_MISSING if required else ({} if defaults else None))
        if value is not None and not isinstance(value, dict):
            self.problem(key, "expected an object")
        return Fields(value, self.path(key), self.source, self.problems)

    def items(self, key: str, *, required: bool = True, nonempty: bool = False) -> list["Fields"]:
        """Each object of the list under `key` (entries that are not objects noted and skipped)."""
        value = self.raw(key, default=_MISSING if required else [])
        if value is None:
            return []
        if not isinstance(value, list):
            self.problem(key, "expected a list")
            return []
        if nonempty and not value:
            self.problem(key, "must not be empty")
        out = []
        for i, entry in enumerate(value):
            item = Fields(entry, f"{self.path(key)}[{i}]", self.source, self.problems)
            if not item.valid:
                item.problem(None, "expected an object")
            else:
                out.append(item)
        return out

    def number(self, key: str, *, default: Any = _MISSING, lo: float | None = None, hi: float | None = None,
               lo_open: bool = False, hi_open: bool = False) -> float | None:
        value = self.raw(key, default)
        if value is None or (value is default and default is not _MISSING):
            return value
        return self.check_number(value, key, lo=lo, hi=hi, lo_open=lo_open, hi_open=hi_open)

    def check_number(self, value: Any, key: str, *, lo: float | None = None, hi: float | None = None,
                     lo_open: bool = False, hi_open: bool = False) -> float | None:
        """`value` as a float within the bounds, or None with a problem noted under `key`."""
        if not is_number(value):
            self.problem(key, f"expected a number, got {value!r}")
            return None
        value = float(value)
        if abs(value) > FLOAT32_MAX:
            self.problem(key, f"{value:g} is beyond float32's range (|x| <= {FLOAT32_MAX:.4g}), in which the "
                              "toolkit computes")
            return None
        if lo is not None and (value < lo or (lo_open and value == lo)):
            self.problem(key, f"must be {'>' if lo_open else '>='} {lo:g}, got {value:g}")
            return None
        if hi is not None and (value > hi or (hi_open and value == hi)):
            self.problem(key, f"must be {'<' if hi_open else '<='} {hi:g}, got {value:g}")
            return None
        return value

    def integer(self, key: str, *, default: Any = _MISSING, lo: int | None = None,
                hi: int | None = None) -> int | None:
        value = self.raw(key, default)
        if value is None or (value is default and default is not _MISSING):
            return value
        if isinstance(value, bool) or not isinstance(value, int):
            self.problem(key, f"expected an integer, got {value!r}")
            return None
        if lo is not None and value < lo:
            self.problem(key, f"must be >= {lo}, got {value}")
            return None
        if hi is not None and value > hi:
            self.problem(key, f"must be <= {hi}, got {value}")
            return None
        return int(value)

    def vector(self, key: str, n: int = 3, *, default: Any = _MISSING, lo: float | None = None) -> np.ndarray | None:
        """A list of `n` numbers (each >= lo when given) as float64."""
        value = self.raw(key, default)
        if value is None:
            return None
        if not isinstance(value, (list, tuple)) or len(value) != n or not all(is_number(v) for v in value):
            self.problem(key, f"expected a list of {n} numbers, got {value!r}")
            return None
        out = np.asarray(value, dtype=np.float64)
        if np.any(np.abs(out) > FLOAT32_MAX):
            self.problem(key, f"{value!r} is beyond float32's range (|x| <= {FLOAT32_MAX:.4g}), in which the "
                              "toolkit computes")
            return None
        if lo is not None and np.any(out < lo):
            self.problem(key, f"every value must be >= {lo:g}, got {value!r}")
            return None
        return out

    def rgb(self, key: str, *, default: Any = _MISSING, positive: bool = False) -> np.ndarray | None:
        """A number (grey) or an RGB triple, >= 0 (> 0 when `positive`), as 3 float64 values."""
        value = self.raw(key, default)
        if value is None:
            return None
        values = [value] * 3 if is_number(value) else value
        ok = isinstance(values, (list, tuple)) and len(values) == 3 and all(is_number(v) for v in values)
        if ok and any(abs(v) > FLOAT32_MAX for v in values):
            self.problem(key, f"{value!r} is beyond float32's range (|x| <= {FLOAT32_MAX:.4g}), in which the "
                              "toolkit computes")
            return None
        if ok and all((v > 0) if positive else (v >= 0) for v in values):
            return np.asarray(values, dtype=np.float64)
        self.problem(key, f"expected a {'positive' if positive else 'non-negative'} number or RGB triple, "
                          f"got {value!r}")
        return None

    def choice(self, key: str, options: Sequence[str], *, default: Any = _MISSING) -> str | None:
        value = self.raw(key, default)
        if value is None:
            return None
        if value not in options:
            self.problem(key, f"{value!r} is not one of {', '.join(repr(o) for o in options)}")
            return None
        return value

    def string(self, key: str, *, default: Any = _MISSING) -> str | None:
        value = self.raw(key, default)
        if value is None:
            return None
        if not isinstance(value, str) or not value:
            self.problem(key, f"expected a non-empty string, got {value!r}")
            return None
        return value

    def strings(self, key: str, *, default: Any = _MISSING) -> list[str] | None:
        value = self.raw(key, default)
        if value is None:
            return None
        if not (isinstance(value, list) and value and all(isinstance(v, str) and v for v in value)):
            self.problem(key, "expected a non-empty list of strings (paths)")
            return None
        return list(value)

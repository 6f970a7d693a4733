"""BVH motion capture files (Biovision hierarchy + motion): `read_bvh`, `write_bvh`.

The format, the reading of its channels and what readers get wrong: docs/noh.md, "Motion capture".
Bad input raises `InputError` naming the file and the line.
"""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path

import numpy as np

from ..errors import InputError
from ._atomic import atomic_path
from ._fields import FLOAT32_MAX

__all__ = ["CHANNEL_NAMES", "BVHMotion", "read_bvh", "write_bvh"]

CHANNEL_NAMES = ("Xposition", "Yposition", "Zposition", "Xrotation", "Yrotation", "Zrotation")
MIN_FRAME_TIME, MAX_FRAME_TIME = 1e-6, 3600.0   # s: a MHz capture to a frame an hour
_CANONICAL = {name.lower(): name for name in CHANNEL_NAMES}


@dataclasses.dataclass(frozen=True, eq=False)
class BVHMotion:
    """A BVH file's content. Joints in file order (every parent before its children); an End
    Site is a joint with no channels named `<parent>_end`, `end_site` True. `motion` holds one row
    per frame, the channels of every joint in joint order, as the file lists them (degrees and
    the file's length unit)."""

    names: tuple[str, ...]
    parents: tuple[int, ...]                 # -1 for a root
    offsets: np.ndarray                      # J 3, float64
    channels: tuple[tuple[str, ...], ...]    # per joint, in the file's order
    end_site: tuple[bool, ...]
    frame_time: float                        # s
    motion: np.ndarray                       # F C, float64

    @property
    def frames(self) -> int:
        return int(self.motion.shape[0])

    def channel_columns(self) -> list[range]:
        """Each joint's columns of `motion`."""
        out, start = [], 0
        for ch in self.channels:
            out.append(range(start, start + len(ch)))
            start += len(ch)
        return out

    def index(self, name: str) -> int:
        return self.names.index(name)


class _Tokens:
    """The hierarchy's words with their line numbers."""

    def __init__(self, path: Path, lines: list[str], start: int):
        self.path = path
        self.words: list[tuple[str, int]] = []
        self.motion_line = None
        for n, line in enumerate(lines[start:], start=start + 1):
            if line.strip().upper() == "MOTION":
                self.motion_line = n
                break
            self.words += [(w, n) for w in re.findall(r"[{}]|[^\s{}]+", line)]
        self.pos = 0
        self.last_line = len(lines)

    def error(self, line: int, problem: str) -> InputError:
        return InputError(self.path, f"line {line}: {problem}")

    def peek(self) -> tuple[str, int]:
        if self.pos >= len(self.words):
            line = self.motion_line or self.last_line
            return "", line
        return self.words[self.pos]

    def take(self, what: str) -> tuple[str, int]:
        word, line = self.peek()
        if not word:
            raise self.error(line, f"expected {what}, the hierarchy ends here")
        self.pos += 1
        return word, line

    def expect(self, word: str) -> int:
        got, line = self.take(repr(word))
        if got.upper() != word.upper():
            raise self.error(line, f"expected {word!r}, got {got!r}")
        return line

    def number(self, what: str) -> float:
        word, line = self.take(what)
        try:
            value = float(word)
        except ValueError:
            raise self.error(line, f"{what}: {word!r} is not a number") from None
        if not np.isfinite(value):
            raise self.error(line, f"{what}: {word!r} is not finite")
        if abs(value) > FLOAT32_MAX:
            raise self.error(line, f"{what}: {word!r} is beyond float32's range, in which the toolkit computes")
        return value


def _hierarchy(tok: _Tokens, root: str, out: dict) -> None:
    """A ROOT block (its name already read) and every joint below it, with an explicit stack of the
    open joints (a chain of any depth reads without recursion)."""
    open_joints = [_joint(tok, root, -1, out)]
    while open_joints:
        word, line = tok.take("JOINT, End Site or '}'")
        parent = open_joints[-1]
        if word == "}":
            open_joints.pop()
        elif word.upper() == "JOINT":
            child, _ = tok.take("a joint name")
            open_joints.append(_joint(tok, child, parent, out))
        elif word.upper() == "END":
            tok.expect("Site")
            tok.expect("{")
            tok.expect("OFFSET")
            offset = [tok.number("OFFSET x"), tok.number("OFFSET y"), tok.number("OFFSET z")]
            tok.expect("}")
            out["names"].append(f"{out['names'][parent]}_end")
            out["parents"].append(parent)
            out["end_site"].append(True)
            out["offsets"].append(offset)
            out["channels"].append(())
        else:
            raise tok.error(line, f"expected JOINT, End Site or '}}' in joint {out['names'][parent]!r}, got {word!r}")


def _joint(tok: _Tokens, name: str, parent: int, out: dict) -> int:
    """The head of a JOINT/ROOT block (its name already read): '{', OFFSET, CHANNELS; its index."""
    index = len(out["names"])
    out["names"].append(name)
    out["parents"].append(parent)
    out["end_site"].append(False)
    tok.expect("{")
    tok.expect("OFFSET")
    out["offsets"].append([tok.number("OFFSET x"), tok.number("OFFSET y"), tok.number("OFFSET z")])
    word, line = tok.peek()
    channels: list[str] = []
    if word.upper() == "CHANNELS":
        tok.take("CHANNELS")
        count = tok.number("the channel count")
        if count != int(count) or count < 0:
            raise tok.error(line, f"the channel count must be a whole number >= 0, got {count:g}")
        for _ in range(int(count)):
            ch, ch_line = tok.take(f"{int(count)} channel names")
            if ch.lower() not in _CANONICAL:
                raise tok.error(ch_line, f"unknown channel {ch!r} (use {', '.join(CHANNEL_NAMES)})")
            channels.append(_CANONICAL[ch.lower()])
        if len(set(channels)) != len(channels):
            raise tok.error(line, f"joint {name!r} lists a channel twice: {' '.join(channels)}")
    out["channels"].append(tuple(channels))
    return index


def _header_value(path: Path, lines: list[str], n: int, key: str) -> tuple[str, int]:
    """The value after `key:` on the next non-blank line from line n (1-based), and its line."""
    while n <= len(lines) and not lines[n - 1].strip():
        n += 1
    if n > len(lines):
        raise InputError(path, f"line {len(lines)}: expected {key!r}, the file ends here")
    line = lines[n - 1].strip()
    if not line.lower().startswith(key.lower()):
        raise InputError(path, f"line {n}: expected {key!r}, got {line[:40]!r}")
    return line[len(key):].strip(), n


def read_bvh(path: str | os.PathLike) -> BVHMotion:
    """Read a BVH file (docs/noh.md, "Motion capture"); `InputError` naming the file and the line
    on anything malformed."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig", errors="strict")   # a byte-order mark is not content
    except FileNotFoundError:
        raise InputError(path, "no such file") from None
    except UnicodeDecodeError:
        raise InputError(path, "not a text file (a BVH file is text)") from None
    except OSError as error:
        raise InputError(path, f"cannot be read: {error.strerror or error}") from None
    lines = text.splitlines()
    first = next((n for n, line in enumerate(lines, start=1) if line.strip()), None)
    if first is None:
        raise InputError(path, "line 1: empty file, expected HIERARCHY")
    if lines[first - 1].strip().upper() != "HIERARCHY":
        raise InputError(path, f"line {first}: expected HIERARCHY, got {lines[first - 1].strip()[:40]!r}")
    tok = _Tokens(path, lines, first)
    out: dict = {"names": [], "parents": [], "offsets": [], "channels": [], "end_site": []}
    while tok.pos < len(tok.words):
        word, line = tok.take("ROOT")
        if word.upper() != "ROOT":
            raise tok.error(line, f"expected ROOT, got {word!r}")
        name, _ = tok.take("the root's name")
        _hierarchy(tok, name, out)
    if not out["names"]:
        raise InputError(path, f"line {first + 1}: no ROOT in the hierarchy")
    if tok.motion_line is None:
        raise InputError(path, f"line {len(lines)}: no MOTION section")
    dupes = sorted({n for n in out["names"] if out["names"].count(n) > 1})
    if dupes:
        raise InputError(path, f"joint names used twice: {', '.join(dupes)}")
    value, n = _header_value(path, lines, tok.motion_line + 1, "Frames:")
    try:
        frames = int(value)
    except ValueError:
        raise InputError(path, f"line {n}: Frames: {value!r} is not a whole number") from None
    if frames < 1:
        raise InputError(path, f"line {n}: Frames: must be >= 1, got {frames}")
    value, n = _header_value(path, lines, n + 1, "Frame Time:")
    try:
        frame_time = float(value)
    except ValueError:
        raise InputError(path, f"line {n}: Frame Time: {value!r} is not a number") from None
    if not (np.isfinite(frame_time) and MIN_FRAME_TIME <= frame_time <= MAX_FRAME_TIME):
        raise InputError(path, f"line {n}: Frame Time: must be {MIN_FRAME_TIME:g} to {MAX_FRAME_TIME:g} s, got {value}")
    width = sum(len(c) for c in out["channels"])
    rows = []
    for k in range(n, len(lines)):
        line = lines[k]
        if not line.strip():
            continue
        words = line.split()
        if len(rows) == frames:
            raise InputError(path, f"line {k + 1}: more motion lines than Frames: {frames}")
        if len(words) != width:
            raise InputError(path, f"line {k + 1}: expected {width} channel values, got {len(words)}")
        try:
            row = np.asarray(words, dtype=np.float64)
        except ValueError:
            bad = next(w for w in words if not _is_number(w))
            raise InputError(path, f"line {k + 1}: {bad!r} is not a number") from None
        if not np.all(np.isfinite(row)):
            raise InputError(path, f"line {k + 1}: a channel value is not finite")
        if np.any(np.abs(row) > FLOAT32_MAX):
            raise InputError(path, f"line {k + 1}: a channel value is beyond float32's range, in which the toolkit "
                                   "computes")
        rows.append(row)
    if len(rows) < frames and width:   # (no channels at all: a frame is an empty line, blank lines are frames)
        raise InputError(path, f"line {len(lines)}: Frames: {frames} but the file ends after {len(rows)} motion lines")
    motion = np.stack(rows) if width else np.zeros((frames, 0))
    return BVHMotion(tuple(out["names"]), tuple(out["parents"]), np.asarray(out["offsets"], np.float64),
                     tuple(out["channels"]), tuple(out["end_site"]), frame_time, motion)


def _is_number(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


def write_bvh(path: str | os.PathLike, bvh: BVHMotion) -> Path:
    """Write `bvh` as a BVH file (atomically); numbers with 17 significant digits, so that
    `read_bvh` gives back the same values."""
    path = Path(path)
    children: dict[int, list[int]] = {}
    for j, p in enumerate(bvh.parents):
        children.setdefault(p, []).append(j)
    num = lambda x: f"{float(x):.17g}"  # noqa: E731
    lines = ["HIERARCHY"]

    def block(j: int, depth: int) -> None:
        pad = "  " * depth
        if bvh.end_site[j]:
            lines.extend([f"{pad}End Site", f"{pad}{{", f"{pad}  OFFSET {' '.join(num(v) for v in bvh.offsets[j])}",
                          f"{pad}}}"])
            return
        kind = "ROOT" if bvh.parents[j] < 0 else "JOINT"
        lines.extend([f"{pad}{kind} {bvh.names[j]}", f"{pad}{{",
                      f"{pad}  OFFSET {' '.join(num(v) for v in bvh.offsets[j])}"])
        if bvh.channels[j]:
            lines.append(f"{pad}  CHANNELS {len(bvh.channels[j])} {' '.join(bvh.channels[j])}")
        for c in children.get(j, []):
            block(c, depth + 1)
        lines.append(f"{pad}}}")

    for root in children.get(-1, []):
        block(root, 0)
    lines += ["MOTION", f"Frames: {bvh.frames}", f"Frame Time: {num(bvh.frame_time)}"]
    lines += [" ".join(num(v) for v in row) for row in np.asarray(bvh.motion)]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return path

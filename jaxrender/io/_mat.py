"""Numeric arrays of MATLAB level-5 MAT files (what DiLiGenT ships its ground-truth normals in),
read without scipy: compressed or plain elements, real double/single/integer matrices."""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

import numpy as np

from ..errors import InputError

__all__ = ["read_mat"]

_MI_MATRIX, _MI_COMPRESSED = 14, 15
_MI_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 9: "f8", 12: "i8", 13: "u8"}


def _elements(data: bytes):
    """(type, payload) of each data element (the small 4-byte form included), 8-byte aligned."""
    pos = 0
    while pos + 8 <= len(data):
        kind, size = struct.unpack_from("<II", data, pos)
        if kind >> 16:  # small data element: size in the upper half, payload in the next 4 bytes
            kind, size = kind & 0xFFFF, kind >> 16
            yield kind, data[pos + 4:pos + 4 + size]
            pos += 8
            continue
        yield kind, data[pos + 8:pos + 8 + size]
        pos += 8 + size + (-size % 8 if kind != _MI_COMPRESSED else 0)


def _matrix(payload: bytes) -> tuple[str, np.ndarray | None]:
    parts = list(_elements(payload))
    if len(parts) < 4:
        return "", None
    flags = struct.unpack_from("<I", parts[0][1])[0]
    matrix_class = flags & 0xFF
    dims = tuple(np.frombuffer(parts[1][1], "<i4"))
    name = parts[2][1].decode("latin-1")
    if matrix_class not in range(6, 16) or flags & 0x800:  # numeric classes only, no complex
        return name, None
    kind, real = parts[3]
    values = np.frombuffer(real, "<" + _MI_TYPES[kind]).astype(np.float64)
    return name, values.reshape(dims, order="F")


def read_mat(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """The real numeric matrices of a level-5 MAT file, by variable name, as float64 arrays."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as error:
        raise InputError(path, f"cannot read ({error.strerror or error})") from None
    if len(data) < 128 or not data.startswith(b"MATLAB 5.0 MAT-file") or data[126:128] != b"IM":
        raise InputError(path, "not a MATLAB level-5 MAT file (v7.3 HDF5 files are not read)")
    out = {}
    try:
        for kind, payload in _elements(data[128:]):
            if kind == _MI_COMPRESSED:
                kind, payload = next(_elements(zlib.decompress(payload)))
            if kind == _MI_MATRIX:
                name, array = _matrix(payload)
                if array is not None:
                    out[name] = array
    except (zlib.error, struct.error, ValueError, KeyError, StopIteration) as error:
        raise InputError(path, f"damaged MAT file ({type(error).__name__}: {error})") from None
    return out

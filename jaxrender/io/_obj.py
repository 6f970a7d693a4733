"""Wavefront OBJ: triangle meshes with texture coordinates, for other tools (Blender, mesh
checkers) to open what a scene rendered."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ._atomic import atomic_path
from ._outputs import check_finite

__all__ = ["write_obj"]


def write_obj(path: str | os.PathLike, vertices, triangles, *, uv=None, uv_triangles=None,
              name: str | None = None) -> Path:
    """`vertices` (V 3) and `triangles` (T 3, 0-based into them) as OBJ (`v`, then `vt`, then 1-based
    faces `f v/vt ...`), 9 significant digits, atomically. `uv` (U 2) are the texture coordinates,
    `uv_triangles` (T 3, default `triangles`) each corner's: a point on a seam keeps one vertex and
    two coordinates, so a closed surface stays closed. `name`: an `o` line. Values that are not
    finite are refused and nothing is written."""
    path = Path(path)
    v = np.asarray(vertices, np.float64).reshape(-1, 3)
    f = np.asarray(triangles, np.int64).reshape(-1, 3)
    ft = f if uv_triangles is None else np.asarray(uv_triangles, np.int64).reshape(-1, 3)
    t = None if uv is None else np.asarray(uv, np.float64).reshape(-1, 2)
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"{path}: a triangle indexes beyond the {len(v)} vertices")
    if t is not None and (ft.shape != f.shape or (ft.size and (ft.min() < 0 or ft.max() >= len(t)))):
        raise ValueError(f"{path}: the uv triangles do not match the triangles and the {len(t)} uv")
    check_finite(v, path)
    lines = [f"o {name}"] if name else []
    lines += [f"v {a:.9g} {b:.9g} {c:.9g}" for a, b, c in v]
    if t is None:
        lines += [f"f {a} {b} {c}" for a, b, c in f + 1]
    else:
        check_finite(t, path)
        lines += [f"vt {a:.9g} {b:.9g}" for a, b in t]
        lines += [f"f {a}/{x} {b}/{y} {c}/{z}" for (a, b, c), (x, y, z) in zip(f + 1, ft + 1)]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n", encoding="ascii")
    return path

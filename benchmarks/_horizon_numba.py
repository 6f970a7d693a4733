"""Numba peers of the horizon maps (numba is a test dependency, not a runtime one): the brute-force
scan of every path step and the O(N) convex-hull sweep (Timonen & Westerholm 2010), both compiled,
`parallel=True` over lines/rows (the thread count is numba's: `numba.set_num_threads`). Same
periodic lattice paths and the same per-sample formula (h_j - h_t) * ((1 / k) / |e|) as
`jaxrender.shadows.horizon_map`, so the maps agree to rounding (tests/test_horizon_sweep.py).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from jaxrender.shadows import horizon_directions


def _steps_and_coef(size: int, directions: int, texel_size: float, dtype) -> tuple[np.ndarray, np.ndarray]:
    steps = np.array([(int(ex), int(ey)) for ex, ey in horizon_directions(directions)], np.int64)
    if not np.all(np.abs(steps) <= 1):
        raise ValueError("numba peers: lattice directions only (4 or 8)")
    inv_k = (1.0 / np.maximum(np.arange(size), 1).astype(dtype)).astype(dtype)
    lengths = np.array([math.hypot(ex, ey) * texel_size for ex, ey in steps], dtype)
    return steps, (inv_k[None, :] / lengths[:, None]).astype(dtype)


@numba.njit(parallel=True, cache=True, fastmath=False)
def _scan(h, steps, coef, out):
    """Per (direction, row): for each step k, the row k e_y below read k e_x texels on, split at the
    wrap into two contiguous runs (no modulo in the inner loop, which LLVM vectorizes)."""
    size = h.shape[0]
    for dy in numba.prange(steps.shape[0] * size):  # one parallel region over (direction, row)
        d, y = dy // size, dy % size
        ix, iy = steps[d, 0], steps[d, 1]
        best = out[d, y]
        best[:] = 0
        here = h[y]
        for k in range(1, size):
            row = h[(y + k * iy) % size]
            sx = (k * ix) % size
            c = coef[d, k]
            for x in range(size - sx):
                best[x] = max(best[x], (row[x + sx] - here[x]) * c)
            for x in range(size - sx, size):
                best[x] = max(best[x], (row[x + sx - size] - here[x]) * c)


@numba.njit(parallel=True, cache=True, fastmath=False)
def _sweep(h, steps, coef, out):
    size = h.shape[0]
    for dl in numba.prange(steps.shape[0] * size):  # one parallel region over (direction, line)
        d, lane = dl // size, dl % size
        ix, iy = steps[d, 0], steps[d, 1]
        y0 = np.int64(lane) * (iy == 0)  # the line starts at (lane, 0) or at (0, lane)
        x0 = np.int64(lane) * (iy != 0)
        line = np.empty(size, h.dtype)  # the line, rotated to end at its maximum
        ys = np.empty(size, np.int64)
        xs = np.empty(size, np.int64)
        m = 0
        for k in range(size):
            yy, xx = (y0 + k * iy) % size, (x0 + k * ix) % size
            if h[yy, xx] > h[(y0 + m * iy) % size, (x0 + m * ix) % size]:
                m = k
        for k in range(size):
            p = (k + m + 1) % size
            ys[k] = (y0 + p * iy) % size
            xs[k] = (x0 + p * ix) % size
            line[k] = h[ys[k], xs[k]]
        hull = np.empty(size, np.int64)  # stack of hull vertices, nearest on top
        top = 0
        hull[0] = size - 1
        out[d, ys[size - 1], xs[size - 1]] = 0
        for t in range(size - 2, -1, -1):
            ht = line[t]
            # pop while the next vertex is seen at a slope at least as steep
            while top > 0:
                j, nj = hull[top], hull[top - 1]
                if (line[nj] - ht) * (j - t) >= (line[j] - ht) * (nj - t):
                    top -= 1
                else:
                    break
            j = hull[top]
            s = (line[j] - ht) * coef[d, j - t]
            out[d, ys[t], xs[t]] = s if s > 0 else 0
            top += 1
            hull[top] = t


def horizon_scan_numba(h: np.ndarray, directions: int = 8, texel_size: float = 1.0) -> np.ndarray:
    """Brute force: every step k = 1 .. S - 1 of every lattice path. O(D S^3)."""
    h = np.ascontiguousarray(h)
    steps, coef = _steps_and_coef(h.shape[0], directions, texel_size, h.dtype)
    out = np.empty((directions,) + h.shape, h.dtype)
    _scan(h, steps, coef, out)
    return out


def horizon_sweep_numba(h: np.ndarray, directions: int = 8, texel_size: float = 1.0) -> np.ndarray:
    """The convex-hull sweep, one line at a time (a stack per line). O(D S^2)."""
    h = np.ascontiguousarray(h)
    if h.shape[0] != h.shape[1]:
        raise ValueError("numba peers: square fields only")
    steps, coef = _steps_and_coef(h.shape[0], directions, texel_size, h.dtype)
    out = np.empty((directions,) + h.shape, h.dtype)
    _sweep(h, steps, coef, out)
    return out

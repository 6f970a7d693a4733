"""Horizon maps by an O(N x directions) sweep (Timonen & Westerholm 2010, "Scalable height field
self-shadowing"): the exact horizon of the full search for the lattice directions (D = 4 or 8) of a
square periodic heightfield, in O(1) amortised work per texel and direction instead of O(S).

Each lattice direction splits the field into S lines (cycles of S texels along e). Along a line
the horizon slope of texel t is the largest slope (h_j - h_t) / (|j - t| |e|) to the texels ahead
of it; that maximum lies on the upper convex hull of the profile ahead, and the slope from t to
the hull vertices rises then falls, so walking the hull from its nearest vertex until the slope
stops rising finds it. Sweeping each line backward keeps that hull as a linked list (`nxt[j]`: the
hull vertex after j); t's tangent vertex becomes `nxt[t]`, and the vertices walked past are below
the segment from t to it, i.e. off every later hull (each texel is passed over at most once).

The path is periodic (note 2 of paper 001): P + e, ..., P + (S - 1) e. Every line is rotated to
end at its highest texel M and swept from there: a texel beyond M along the path (farther than M)
is no higher than M, so its slope never exceeds the slope to M (or 0), and the sweep of the S
texels of one turn, started with the hull {M}, is exact. All lines of all directions are swept
together, one vectorised step per position (a loop of S steps over D * S lanes); the loop only
finds each texel's tangent vertex (integers), and the slopes are computed from those afterwards,
with the full search's formula, so they are equal to it and differentiable like it.

Where the time goes (CPU): each step's walk is a while loop over all D S lanes that runs until
the lane with the longest walk is done (about 8-10 rounds for 8192 lanes where the average walk
is ~1), and each round is two gathers; a compiled sequential sweep (benchmarks/_horizon_numba.py)
walks only as far as each line needs. See benchmarks/RESULTS.md, horizon maps.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int


def _flip(a: Array) -> Array:
    """a[(-k) mod S] along axis 0 (a periodic reversal; its own inverse)."""
    return jnp.roll(a[::-1], 1, axis=0)


def _skew(a: Array, sign: int) -> Array:
    """c[k, l] = a[k, (l + sign k) mod S] for a square a, by reshaping the row-doubled field (a copy,
    no gather): row k of the doubled field, read with a stride of 2 S + sign, starts k places on."""
    size = a.shape[0]
    flat = jnp.concatenate([a, a], axis=1).ravel()
    if sign > 0:
        return jnp.pad(flat, (0, size)).reshape(size, 2 * size + 1)[:, :size]
    return flat[size:].reshape(size, 2 * size - 1)[:, :size]


def _to_lines(height: Array, steps: list[tuple[int, int]]) -> Array:
    """(S positions, D S lanes): lane d S + l holds line l of direction d, position k at texel
    (y, x) = (l, k e_x) for the horizontal directions and (k e_y, l + k e_x) otherwise (mod S)."""
    blocks = []
    for ix, iy in steps:
        if iy == 0:
            blocks.append(height.T if ix > 0 else _flip(height.T))
        else:
            g = height if iy > 0 else _flip(height)
            blocks.append(g if ix == 0 else _skew(g, ix))
    return jnp.concatenate(blocks, axis=1)


def _from_lines(lines: Array, steps: list[tuple[int, int]]) -> Array:
    """The inverse of `_to_lines`: (D, S, S) maps from line order."""
    size = lines.shape[0]
    maps = []
    for d, (ix, iy) in enumerate(steps):
        block = lines[:, d * size:(d + 1) * size]
        if iy == 0:
            maps.append(block.T if ix > 0 else _flip(block).T)
        else:
            g = block if ix == 0 else _skew(block, -ix)
            maps.append(g if iy > 0 else _flip(g))
    return jnp.stack(maps)


def _tangent_vertices(rows: Array) -> Int[Array, "S L"]:
    """For lines that each end at their highest sample (`rows` (S, L): sample k of line l, row S - 1
    the maxima), the sample j > k that sees sample k under the steepest slope (h_j - h_k) / (j - k);
    S for the last row (nothing ahead)."""
    size, lanes = rows.shape
    rows = jax.lax.stop_gradient(rows)
    flat = rows.ravel()
    lane = jnp.arange(lanes, dtype=jnp.int32)

    def rises_more(j, h_j, nj, h_n, t, h_t):
        """Is hull vertex nj (height h_n) seen from t under a steeper slope than j? (No division.)"""
        return (nj < size) & ((h_n - h_t) * (j - t).astype(rows.dtype) >= (h_j - h_t) * (nj - t).astype(rows.dtype))

    def step(i, state):
        nxt, j_prev, h_prev = state
        t = size - 2 - i
        h_t = rows[t]

        def walk(carry):  # on along the hull while the slope rises
            j, h_j, _ = carry
            nj = nxt[j * lanes + lane]
            h_n = flat[jnp.minimum(nj, size - 1) * lanes + lane]
            up = rises_more(j, h_j, nj, h_n, t, h_t)
            return jnp.where(up, nj, j), jnp.where(up, h_n, h_j), jnp.any(up)

        # t + 1 is the nearest hull vertex; its successor is the vertex step t + 1 chose (carried)
        up = rises_more(t + 1, rows[t + 1], j_prev, h_prev, t, h_t)
        j = jnp.where(up, j_prev, t + 1)
        h_j = jnp.where(up, h_prev, rows[t + 1])
        j, h_j, _ = jax.lax.while_loop(lambda c: c[2], walk, (j, h_j, jnp.any(up)))
        return jax.lax.dynamic_update_slice(nxt, j, (t * lanes,)), j, h_j

    nxt = jnp.full((size * lanes,), size, jnp.int32)  # `size`: no next vertex (the line's maximum)
    init = (nxt, jnp.full((lanes,), size, jnp.int32), rows[size - 1])
    nxt, _, _ = jax.lax.fori_loop(0, size - 1, step, init)
    return nxt.reshape(size, lanes)


def lattice_sweep(height: Float[Array, "S S"], steps: list[tuple[int, int]],
                  lengths: list[float]) -> Float[Array, "D S S"]:
    """Horizon slopes max(0, max_k (h(P + k e) - h(P)) / (k |e|)) of a square periodic field along
    lattice steps e = (e_x, e_y) in {-1, 0, 1}^2 (not both 0), `lengths` |e| texel_size, by the sweep."""
    size = height.shape[0]
    dtype = height.dtype
    lines = _to_lines(height, steps)
    # rotate each line to end at its maximum: rotated[k] = lines[(k + argmax + 1) mod S]
    shift = jnp.argmax(jax.lax.stop_gradient(lines), axis=0).astype(jnp.int32) + 1
    k = jnp.arange(size, dtype=jnp.int32)[:, None]
    rotated = jnp.take_along_axis(lines, (k + shift[None, :]) % size, axis=0)
    best = _tangent_vertices(rotated)
    # slopes with the full search's rounding: (h_j - h_t) * ((1 / k) / |e|)
    inv_k = 1.0 / jnp.arange(size + 1, dtype=dtype).at[0].set(1.0)
    coef = inv_k[None, :] / jnp.asarray(lengths, dtype)[:, None]  # (D, S + 1)
    ahead = jnp.take_along_axis(rotated, jnp.minimum(best, size - 1), axis=0)
    lane_dir = jnp.arange(rotated.shape[1]) // size
    slope = (ahead - rotated) * coef[lane_dir[None, :], best - k]
    slope = jnp.where(best < size, jnp.maximum(slope, 0.0), 0.0)
    return _from_lines(jnp.take_along_axis(slope, (k - shift[None, :]) % size, axis=0), steps)

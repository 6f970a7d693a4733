"""Horizon maps by an O(N x directions) convex-hull sweep (Timonen & Westerholm 2010): the exact
horizon of the full search for D = 4 or 8 on a square periodic field, every line of every
direction swept together. Why it is exact and where its time goes: docs/desert.md.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int


def _slope(h_j: Array, h_t: Array, dist: Array, length: Array) -> Array:
    """(h_j - h_t) * ((1 / k) / |e|), clamped at 0: the full search's formula and rounding."""
    return jnp.maximum((h_j - h_t) * ((1.0 / dist.astype(h_t.dtype)) / length), 0.0)


def _scan(rows: Array, length: Array) -> tuple[Int[Array, "S L"], Float[Array, "S L"]]:
    """For lines that each end at their highest sample (`rows` (S, L): sample k of line l, row S - 1
    the maxima; `length` (L,): |e| texel_size per line): per sample k the sample j > k seen under
    the steepest slope (S for the last row: nothing ahead), and that slope (`_slope`)."""
    size, lanes = rows.shape
    flat = rows.ravel()
    lane = jnp.arange(lanes, dtype=jnp.int32)

    def rises_more(j, h_j, nj, h_n, t, h_t):
        """Is hull vertex nj (height h_n) seen from t under a steeper slope than j? (No division.)"""
        return (nj < size) & ((h_n - h_t) * (j - t).astype(rows.dtype) >= (h_j - h_t) * (nj - t).astype(rows.dtype))

    def step(i, state):
        nxt, out, j_prev, h_prev = state
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
        out = jax.lax.dynamic_update_slice(out, _slope(h_j, h_t, j - t, length)[None], (t, 0))
        return jax.lax.dynamic_update_slice(nxt, j, (t * lanes,)), out, j, h_j

    nxt = jnp.full((size * lanes,), size, jnp.int32)  # `size`: no next vertex (the line's maximum)
    init = (nxt, jnp.zeros_like(rows), jnp.full((lanes,), size, jnp.int32), rows[size - 1])
    nxt, out, _, _ = jax.lax.fori_loop(0, size - 1, step, init)
    return nxt.reshape(size, lanes), out


@jax.custom_jvp
def _swept_slopes(rows: Array, length: Array) -> Float[Array, "S L"]:
    """The slopes of `_scan`, differentiable in `rows` like the full search (through the chosen
    sample's height and the texel's own)."""
    return _scan(rows, length)[1]


def _slopes_at(rows: Array, length: Array, best: Array) -> Array:
    """`_scan`'s slopes recomputed from its choices (what the derivative goes through)."""
    size = rows.shape[0]
    k = jnp.arange(size, dtype=jnp.int32)[:, None]
    ahead = jnp.take_along_axis(rows, jnp.minimum(best, size - 1), axis=0)
    return jnp.where(best < size, _slope(ahead, rows, jnp.maximum(best - k, 1), length[None, :]), 0.0)


@_swept_slopes.defjvp
def _swept_slopes_jvp(primals, tangents):
    rows, length = primals
    best, slopes = _scan(rows, length)
    _, tangent = jax.jvp(lambda r, n: _slopes_at(r, n, best), primals, tangents)
    return slopes, tangent


def lattice_sweep(height: Float[Array, "S S"], steps: list[tuple[int, int]],
                  lengths: list[float]) -> Float[Array, "D S S"]:
    """Horizon slopes max(0, max_k (h(P + k e) - h(P)) / (k |e|)) of a square periodic field along
    lattice steps e = (e_x, e_y) in {-1, 0, 1}^2 (not both 0; steps[d + D/2] = -steps[d]), `lengths`
    |e| texel_size, by the sweep. Line l of direction d: position k at texel (y, x) = (l, k e_x) for
    the horizontal directions, (k e_y, l + k e_x) otherwise (mod S); all layouts are gathers with
    computed indices (no transposed or skewed copies)."""
    size, n_dir = height.shape[0], len(steps)
    ix = jnp.asarray([e[0] for e in steps], jnp.int32)[:, None, None]
    iy = jnp.asarray([e[1] for e in steps], jnp.int32)[:, None, None]
    horizontal = iy == 0
    flat = height.ravel()

    def texel(k, line):  # flat texel index of position k of `line`, per direction
        y = jnp.where(horizontal, line, (k * iy) % size)
        x = jnp.where(horizontal, (k * ix) % size, (line + k * ix) % size)
        return y * size + x

    k = jnp.arange(size, dtype=jnp.int32)[None, :, None]
    line = jnp.arange(size, dtype=jnp.int32)[None, None, :]
    # each line's highest sample; direction d + D/2 walks the lines of d backward (position k <-> -k)
    half = n_dir // 2
    top = jnp.argmax(jax.lax.stop_gradient(flat)[texel(k, line)[:half]], axis=1).astype(jnp.int32)
    shift = jnp.concatenate([top, (-top) % size])[:, None, :] + 1
    # rotated[r, d S + l] = sample (r + shift) mod S of line l of direction d: each line ends at its maximum
    rotated = jnp.moveaxis(flat[texel((k + shift) % size, line)], 0, 1).reshape(size, n_dir * size)
    length = jnp.repeat(jnp.asarray(lengths, height.dtype), size)
    slopes = _swept_slopes(rotated, length).ravel()
    # back to texels: texel (d, y, x) is position kp of line l, rotated position (kp - shift) mod S
    y = jnp.arange(size, dtype=jnp.int32)[None, :, None]
    x = jnp.arange(size, dtype=jnp.int32)[None, None, :]
    kp = jnp.where(horizontal, (x * ix) % size, (y * iy) % size)
    ln = jnp.where(horizontal, y, (x - kp * ix) % size)
    d = jnp.arange(n_dir, dtype=jnp.int32)[:, None, None]
    r = (kp - shift[:, 0, :][d, ln]) % size
    return slopes[r * (n_dir * size) + d * size + ln]

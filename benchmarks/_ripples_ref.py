"""Peers for the ripple benchmarks: the same update as sims.ripple_step (paper 001 eqs. 1-4,
split/nearest hop along +x, periodic; amounts, shares and creep fluxes on the sand grid so the
total is conserved exactly) in vectorized numpy and in numba. Not part of the package."""

from __future__ import annotations

import math

import numpy as np


def _quantum(h: np.ndarray, q: float) -> float:
    """The sand grid of sims._transport.sand_quantum: the last bit of 2x max(|h|, q)."""
    _, exponent = np.frexp(max(float(np.max(np.abs(h))), abs(q)))
    return float(np.ldexp(1.0, int(exponent) + 1 - (np.finfo(h.dtype).nmant + 1)))


def numpy_step(h: np.ndarray, *, L0: float = 7.3, q: float = 0.6, b: float = 2.0, D: float = 0.8,
               hop: str = "split") -> np.ndarray:
    """One synchronous step, the update of sims.ripple_step: heights, amount, split shares and
    creep fluxes on the sand grid (exact conservation); saltation along +x (np.bincount
    deposit), then creep as fluxes between neighbours (np.roll)."""
    height, width = h.shape
    grid = _quantum(h, q)
    h = np.round(h / grid) * grid
    q = np.round(q / grid) * grid
    L = L0 + b * h
    rows = np.arange(height)[:, None] * width
    cols = np.arange(width)[None, :]
    if hop == "split":
        base = np.floor(L)
        far = np.round(q * (L - base) / grid) * grid
        target = rows + (cols + base.astype(np.int64)) % width
        target1 = rows + (cols + base.astype(np.int64) + 1) % width
        dep = (np.bincount(target.ravel(), (q - far).ravel(), minlength=h.size)
               + np.bincount(target1.ravel(), far.ravel(), minlength=h.size))
    else:
        target = rows + (cols + np.round(L).astype(np.int64)) % width
        dep = np.bincount(target.ravel(), np.full(h.size, q), minlength=h.size)
    h = h - q + dep.reshape(h.shape)
    # fluxes into each cell from its east, south, south-east and south-west neighbour
    south = np.roll(h, -1, 0)
    fluxes = ((D / 6.0, np.roll(h, -1, 1), (0, 1)), (D / 6.0, south, (1, 0)),
              (D / 12.0, np.roll(south, -1, 1), (1, 1)), (D / 12.0, np.roll(south, 1, 1), (1, -1)))
    out = h.copy()
    for weight, neighbour, (dy, dx) in fluxes:
        flux = np.round(weight * (neighbour - h) / grid) * grid
        out += flux - np.roll(flux, (dy, dx), (0, 1))
    return out


def make_numba_steps(parallel: bool = False):
    """A numba kernel running `steps` steps of the same update (split hop along +x, sand grid,
    creep as fluxes); compiled on first call. With `parallel`, the rows are spread over numba's
    threads (`prange`): the wind is along the rows, so a row's hops stay in the row."""
    import numba

    rows = numba.prange if parallel else range

    @numba.njit(cache=False, fastmath=False, parallel=parallel)
    def run(h, steps, L0, q_in, b, D):
        height, width = h.shape
        cur = h.copy()
        tmp = np.empty_like(h)
        flux = np.empty((4, height, width))
        row_max = np.empty(height)
        side, corner = D / 6.0, D / 12.0
        for _ in range(steps):
            for i in rows(height):
                top = 0.0
                for j in range(width):
                    top = max(top, abs(cur[i, j]))
                row_max[i] = top
            _, exponent = math.frexp(max(row_max.max(), abs(q_in)))
            grid = math.ldexp(1.0, exponent + 1 - 53)
            q = np.rint(q_in / grid) * grid
            for i in rows(height):
                for j in range(width):
                    cur[i, j] = np.rint(cur[i, j] / grid) * grid
                    tmp[i, j] = cur[i, j] - q
                for j in range(width):
                    L = L0 + b * cur[i, j]
                    base = np.floor(L)
                    far = np.rint(q * (L - base) / grid) * grid
                    t = (j + int(base)) % width
                    tmp[i, t] += q - far
                    tmp[i, (t + 1) % width] += far
            for i in rows(height):
                ip = (i + 1) % height
                for j in range(width):
                    jm, jp = (j - 1) % width, (j + 1) % width
                    c = tmp[i, j]
                    flux[0, i, j] = np.rint(side * (tmp[i, jp] - c) / grid) * grid
                    flux[1, i, j] = np.rint(side * (tmp[ip, j] - c) / grid) * grid
                    flux[2, i, j] = np.rint(corner * (tmp[ip, jp] - c) / grid) * grid
                    flux[3, i, j] = np.rint(corner * (tmp[ip, jm] - c) / grid) * grid
            for i in rows(height):
                im = (i - 1) % height
                for j in range(width):
                    jm, jp = (j - 1) % width, (j + 1) % width
                    cur[i, j] = tmp[i, j] + ((flux[0, i, j] - flux[0, i, jm]) + (flux[1, i, j] - flux[1, im, j])
                                             + (flux[2, i, j] - flux[2, im, jm]) + (flux[3, i, j] - flux[3, im, jp]))
        return cur

    return run


def make_jax_roll_gather():
    """The gather formulation measured against the scatter (the design choice in sims._transport):
    received sand = sum over the dynamic hop range of roll(q w_k, k), in Horner form (split, +x)."""
    import jax
    import jax.numpy as jnp
    from jax import lax

    from sims._transport import creep

    def deposit(amount, hop):
        k_lo = jnp.floor(jnp.min(hop)).astype(jnp.int32)
        k_hi = jnp.ceil(jnp.max(hop)).astype(jnp.int32)

        def w(k):
            return amount * jnp.maximum(0.0, 1.0 - jnp.abs(hop - k.astype(hop.dtype)))

        def body(state):
            k, acc = state
            return k - 1, jnp.roll(acc, 1, axis=-1) + w(k)

        _, acc = lax.while_loop(lambda s: s[0] >= k_lo, body, (k_hi - 1, w(k_hi)))
        return jnp.roll(acc, k_lo, axis=-1)

    def step(h, _):
        amount = jnp.full_like(h, 0.6)
        h = h - amount + deposit(amount, 7.3 + 2.0 * h)
        return creep(h, 0.8), None

    return jax.jit(lambda h, steps: lax.scan(step, h, None, length=steps)[0], static_argnums=1)

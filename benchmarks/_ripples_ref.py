"""Peers for the ripple benchmarks: the same rules (paper 001 eqs. 1-4, split/nearest hop along
+x, periodic) in vectorized numpy and in numba. Not part of the package."""

from __future__ import annotations

import numpy as np


def numpy_step(h: np.ndarray, *, L0: float = 7.3, q: float = 0.6, b: float = 2.0, D: float = 0.8,
               hop: str = "split") -> np.ndarray:
    """One synchronous step: saltation along +x (np.bincount deposit), then creep (np.roll)."""
    height, width = h.shape
    L = L0 + b * h
    rows = np.arange(height)[:, None] * width
    cols = np.arange(width)[None, :]
    if hop == "split":
        base = np.floor(L)
        frac = L - base
        target = rows + (cols + base.astype(np.int64)) % width
        target1 = rows + (cols + base.astype(np.int64) + 1) % width
        dep = (np.bincount(target.ravel(), (q * (1.0 - frac)).ravel(), minlength=h.size)
               + np.bincount(target1.ravel(), (q * frac).ravel(), minlength=h.size))
    else:
        target = rows + (cols + np.round(L).astype(np.int64)) % width
        dep = np.bincount(target.ravel(), np.full(h.size, q), minlength=h.size)
    h = h - q + dep.reshape(h.shape)
    nn = np.roll(h, 1, 0) + np.roll(h, -1, 0) + np.roll(h, 1, 1) + np.roll(h, -1, 1)
    nnn = (np.roll(np.roll(h, 1, 0), 1, 1) + np.roll(np.roll(h, 1, 0), -1, 1)
           + np.roll(np.roll(h, -1, 0), 1, 1) + np.roll(np.roll(h, -1, 0), -1, 1))
    return h + D * (nn / 6.0 + nnn / 12.0 - h)


def make_numba_steps():
    """A numba kernel running `steps` steps (split hop along +x); compiled on first call."""
    import numba

    @numba.njit(cache=False, fastmath=False)
    def run(h, steps, L0, q, b, D):
        height, width = h.shape
        cur = h.copy()
        tmp = np.empty_like(h)
        for _ in range(steps):
            for i in range(height):
                for j in range(width):
                    tmp[i, j] = cur[i, j] - q
            for i in range(height):
                for j in range(width):
                    L = L0 + b * cur[i, j]
                    base = np.floor(L)
                    f = L - base
                    t = (j + int(base)) % width
                    tmp[i, t] += q * (1.0 - f)
                    tmp[i, (t + 1) % width] += q * f
            for i in range(height):
                im, ip = (i - 1) % height, (i + 1) % height
                for j in range(width):
                    jm, jp = (j - 1) % width, (j + 1) % width
                    nn = tmp[im, j] + tmp[ip, j] + tmp[i, jm] + tmp[i, jp]
                    nnn = tmp[im, jm] + tmp[im, jp] + tmp[ip, jm] + tmp[ip, jp]
                    cur[i, j] = tmp[i, j] + D * (nn / 6.0 + nnn / 12.0 - tmp[i, j])
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

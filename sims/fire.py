"""Procedural flames for firelight (paper 004 section 4.4, after Perlin's noise, paper ref. 20).

`gradient_noise` is Perlin's improved gradient noise in 3D (quintic fade, 12 edge gradients,
a permutation table drawn from a `key`), written in JAX and vectorised over points. `fbm` sums
octaves of it and `turbulence` sums their absolute values. `fire_frames` renders F frames of a
bonfire as emission textures (linear RGB radiance, row 0 at the top, flame base at the bottom):
a flame-shaped mask (wide at the base, narrowing to a tip) is displaced and eroded by
turbulence scrolling upward with time, so the flame rises and flickers; a slow noise of time
modulates the overall intensity; the temperature maps to colour by a black-body-like ramp
(deep red -> orange -> yellow-white). Frames are periodic in time (the noise's time axis wraps
after `frames` steps), so an animation loops without a jump.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

from jaxrender.maths import default_float

__all__ = ["permutation_table", "gradient_noise", "fbm", "turbulence", "fire_frames", "flame_colour"]

_GRADIENTS = (
    (1, 1, 0), (-1, 1, 0), (1, -1, 0), (-1, -1, 0), (1, 0, 1), (-1, 0, 1),
    (1, 0, -1), (-1, 0, -1), (0, 1, 1), (0, -1, 1), (0, 1, -1), (0, -1, -1),
)


def permutation_table(key: PRNGKeyArray) -> Int[Array, "512"]:
    """Perlin's doubled permutation of 0..255, drawn from `key`."""
    perm = jax.random.permutation(key, 256).astype(jnp.int32)
    return jnp.concatenate([perm, perm])


def _fade(t: Array) -> Array:
    return t * t * t * (t * (t * 6 - 15) + 10)


def gradient_noise(p: Float[ArrayLike, "... 3"], perm: Int[Array, "512"], *,
                   period: Int[ArrayLike, "3"] | None = None) -> Float[Array, "..."]:
    """Perlin gradient noise at points `p` (range about [-1, 1], 0 at integer lattice points).

    `period` (optional, integers per axis) makes the noise periodic along that axis.
    """
    p = jnp.asarray(p)
    cell = jnp.floor(p)
    f = p - cell
    ci = cell.astype(jnp.int32)
    grads = jnp.asarray(_GRADIENTS, dtype=p.dtype)
    per = None if period is None else jnp.asarray(period, dtype=jnp.int32)

    def corner(dx: int, dy: int, dz: int) -> Array:
        off = jnp.asarray([dx, dy, dz], dtype=jnp.int32)
        c = ci + jnp.reshape(off, (1,) * (ci.ndim - 1) + (3,))
        if per is not None:
            c = jnp.mod(c, jnp.reshape(per, (1,) * (ci.ndim - 1) + (3,)))
        c = jnp.bitwise_and(c, 255)
        h = perm[perm[perm[c[..., 0]] + c[..., 1]] + c[..., 2]]
        g = grads[jnp.mod(h, 12)]
        d = f - jnp.reshape(off.astype(p.dtype), (1,) * (f.ndim - 1) + (3,))
        return jnp.sum(g * d, axis=-1)

    u = _fade(f)
    ux, uy, uz = u[..., 0], u[..., 1], u[..., 2]
    lerp = lambda a, b, t: a + t * (b - a)  # noqa: E731
    x00 = lerp(corner(0, 0, 0), corner(1, 0, 0), ux)
    x10 = lerp(corner(0, 1, 0), corner(1, 1, 0), ux)
    x01 = lerp(corner(0, 0, 1), corner(1, 0, 1), ux)
    x11 = lerp(corner(0, 1, 1), corner(1, 1, 1), ux)
    return lerp(lerp(x00, x10, uy), lerp(x01, x11, uy), uz)


def fbm(p: Float[ArrayLike, "... 3"], perm: Int[Array, "512"], *, octaves: int = 4, lacunarity: float = 2.0,
        gain: float = 0.5, period: Int[ArrayLike, "3"] | None = None) -> Float[Array, "..."]:
    """Fractional Brownian motion: sum of `octaves` noise octaves (a handful: unrolled)."""
    p = jnp.asarray(p)
    total, amp, freq = 0.0, 1.0, 1.0
    for o in range(octaves):
        per = None if period is None else jnp.asarray(period, dtype=jnp.int32) * int(round(freq))
        total = total + amp * gradient_noise(p * freq, perm, period=per)
        amp, freq = amp * gain, freq * lacunarity
    return total


def turbulence(p: Float[ArrayLike, "... 3"], perm: Int[Array, "512"], *, octaves: int = 4, lacunarity: float = 2.0,
               gain: float = 0.5, period: Int[ArrayLike, "3"] | None = None) -> Float[Array, "..."]:
    """Perlin's turbulence: sum of |noise| over octaves (non-negative)."""
    p = jnp.asarray(p)
    total, amp, freq = 0.0, 1.0, 1.0
    for o in range(octaves):
        per = None if period is None else jnp.asarray(period, dtype=jnp.int32) * int(round(freq))
        total = total + amp * jnp.abs(gradient_noise(p * freq, perm, period=per))
        amp, freq = amp * gain, freq * lacunarity
    return total


def flame_colour(temperature: Float[ArrayLike, "..."]) -> Float[Array, "... 3"]:
    """Black-body-like ramp for a normalised temperature in [0, 1] (linear RGB, peak ~1)."""
    t = jnp.clip(jnp.asarray(temperature), 0.0, 1.0)
    r = jnp.clip(t * 2.2, 0.0, 1.0)
    g = jnp.clip((t - 0.25) * 1.6, 0.0, 1.0) ** 1.6
    b = jnp.clip((t - 0.7) * 2.5, 0.0, 1.0) ** 2
    return jnp.stack([r, 0.85 * g, 0.6 * b], axis=-1) * t[..., None]


@functools.partial(jax.jit, static_argnames=("frames", "height", "width"))
def fire_frames(key: PRNGKeyArray, *, frames: int = 20, height: int = 64, width: int = 32,
                intensity: float = 12.0, speed: float = 2.5, scale: float = 3.0) -> Float[Array, "F H W 3"]:
    """F frames of a flickering bonfire: linear RGB emitted radiance, H x W, row 0 at the top.

    Deterministic per `key`; non-negative; the sequence loops (frame F would equal frame 0).
    `intensity` is the peak radiance of the hottest part; `speed` is how many noise cells the
    flame rises per loop; `scale` the number of noise cells across the flame's width.
    """
    perm = permutation_table(key)
    dtype = default_float()
    x = (jnp.arange(width, dtype=dtype) + 0.5) / width * 2 - 1          # -1 .. 1 across
    y = 1 - (jnp.arange(height, dtype=dtype) + 0.5) / height            # 0 at bottom, 1 at top
    yy, xx = jnp.meshgrid(y, x, indexing="ij")
    t_cells = 4  # time axis of the noise: periodic over `t_cells` cells per loop
    rise_cells = max(1, int(round(speed)))
    period = jnp.asarray([1024, rise_cells * 64, t_cells], dtype=jnp.int32)

    def one(f: Array) -> Array:
        phase = f / frames
        t = phase * t_cells
        # noise coordinates scroll downward in the image (flame features rise)
        px = xx * scale * 0.5 + 17.0
        py = yy * scale - phase * rise_cells * 1.0 + 64.0
        pt = jnp.full_like(xx, t)
        p = jnp.stack([px, py, pt], axis=-1)
        turb = turbulence(p, perm, octaves=4, period=period)
        sway = fbm(jnp.stack([yy * 1.5 + 3.0, jnp.full_like(xx, 5.0), pt], axis=-1), perm, octaves=2,
                   period=jnp.asarray([1024, 1024, t_cells], dtype=jnp.int32))
        # flame mask: a teardrop, wide at the base, narrow at the top; displaced sideways by `sway`
        xs = xx - 0.35 * sway * yy
        half_width = 0.75 * (1 - yy) ** 0.6 * jnp.minimum(1.0, 4 * yy + 0.35)
        shape = 1 - jnp.abs(xs) / jnp.maximum(half_width, 1e-3)
        heat = shape - 1.3 * turb * (0.25 + yy) + 0.25 * (1 - yy)
        heat = jnp.clip(heat, 0.0, 1.0)
        # global flicker from a slow 1D noise of time
        flick = 1 + 0.35 * gradient_noise(jnp.asarray([[0.5, 0.5, t + 0.37]], dtype=dtype), perm,
                                          period=jnp.asarray([1024, 1024, t_cells], dtype=jnp.int32))[0]
        return intensity * flick * flame_colour(heat ** 0.8)

    return jax.vmap(one)(jnp.arange(frames, dtype=dtype))

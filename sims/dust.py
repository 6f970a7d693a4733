"""Sand dust (paper 001 section 3.7, eq. 7): billboards that creep over the dune surface.

Each particle (a spherical cloud of grains, drawn by the renderer as a camera-facing billboard)
moves per time step as

    x_t = x_{t-1} + dx + a_x,   y_t = y_{t-1} + a_y,   z_t = H_dune(x_t, y_t) + dz + a_z,   (7)

with dx the mean advance along the wind per step, dz the height above the dune surface, and
a_x, a_y, a_z zero-mean Gaussian jitter (standard deviations `jitter`). The paper's wind blows
along +x; here the horizontal step (dx + a_x, a_y) is rotated by `wind_deg` (from +x toward +y,
the convention of `sims.ripples`). Positions are in dune cells: cell (row i, column j) is at
(x, y) = (j, i); the dune wraps periodically, H_dune is sampled bilinearly
(`jaxrender.textures.bilinear`, the toolkit's one sampler). A billboard's size is proportional
to the local ripple height (the paper: "the height at each position of the ripple height field"):
the ripple field tiles every dune cell `ripple_tiling` times per axis, its heights are taken
relative to their minimum (the automaton's heights can be negative) and scaled so that the
highest crest gets `size_scale`.

Example::

    pos, size = simulate_dust(key, dune, ripples, n_particles=512, steps=60)
    # pos: (60, 512, 3) x, y (dune cells), z (height units); size: (60, 512)
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Float

from jaxrender.textures import bilinear


class DustParams(eqx.Module):
    """Eq. 7 constants (dune cells per step, height units); `wind_deg` static."""

    drift: Float[ArrayLike, ""] = 0.4
    lift: Float[ArrayLike, ""] = 0.3
    jitter: tuple[float, float, float] = (0.15, 0.15, 0.08)
    size_scale: Float[ArrayLike, ""] = 0.5
    wind_deg: float = eqx.field(static=True, default=0.0)


def sample_periodic(field: Float[Array, "H W"], xy: Float[Array, "... 2"]) -> Float[Array, "..."]:
    """Bilinear value of a periodic grid at (x, y) in cells (cell (i, j) at x = j, y = i)."""
    field = jnp.asarray(field)
    h, w = field.shape
    uv = jnp.stack([(xy[..., 0] + 0.5) / w, (xy[..., 1] + 0.5) / h], axis=-1)
    return bilinear(field[..., None], uv, wrap="repeat")[..., 0]


def init_dust(key: Array, n_particles: int, dune_shape: tuple[int, int], *, dtype=None) -> Float[Array, "N 2"]:
    """Launch positions (x, y), uniform over the dune domain."""
    dtype = dtype or jnp.result_type(float)
    h, w = dune_shape
    u = jax.random.uniform(key, (n_particles, 2), dtype=dtype)
    return u * jnp.array([w, h], dtype)[None, :]


@functools.partial(jax.jit, static_argnames=("ripple_tiling",))
def dust_sizes(xy: Float[Array, "... 2"], ripple_height: Float[Array, "h w"], *, ripple_tiling: float = 1.0,
               size_scale: ArrayLike = 0.5) -> Float[Array, "..."]:
    """Billboard size at dune positions: size_scale (r - min r) / (max r - min r) of the ripple
    height r sampled where the ripple field, tiled `ripple_tiling` times per dune cell, covers xy."""
    ripple_height = jnp.asarray(ripple_height)
    lo, hi = jnp.min(ripple_height), jnp.max(ripple_height)
    rh, rw = ripple_height.shape
    scale = jnp.array([rw, rh], xy.dtype).reshape((1,) * (xy.ndim - 1) + (2,))
    local = xy * ripple_tiling * scale  # ripple cells (periodic)
    r = sample_periodic(ripple_height, local - 0.5)
    span = jnp.where(hi > lo, hi - lo, 1.0)
    return jnp.asarray(size_scale, xy.dtype) * (r - lo) / span


@functools.partial(jax.jit, static_argnames=("steps",))
def advect_dust(key: Array, xy0: Float[Array, "N 2"], dune_height: Float[Array, "H W"], *, steps: int,
                params: DustParams = DustParams(), noise: Float[Array, "T N 3"] | None = None) -> Float[Array, "T N 3"]:
    """Eq. 7 for `steps` steps as one `lax.scan`; returns positions (x, y, z) after each step.

    `noise` (standard normal, (steps, N, 3)) replaces the draws from `key` when given.
    """
    xy0 = jnp.asarray(xy0)
    dtype = xy0.dtype
    dune_height = jnp.asarray(dune_height, dtype)
    n = xy0.shape[0]
    if noise is None:
        noise = jax.random.normal(key, (steps, n, 3), dtype=dtype)
    sigma = jnp.asarray(params.jitter, dtype).reshape(1, 3)
    angle = math.radians(params.wind_deg)
    c, s = math.cos(angle), math.sin(angle)
    drift = jnp.asarray(params.drift, dtype)
    lift = jnp.asarray(params.lift, dtype)

    def step(xy, eps):
        a = eps * sigma
        along, across = drift + a[:, 0], a[:, 1]  # eq. 7 in the wind frame
        xy = xy + jnp.stack([c * along - s * across, s * along + c * across], axis=-1)
        z = sample_periodic(dune_height, xy) + lift + a[:, 2]
        return xy, jnp.concatenate([xy, z[:, None]], axis=-1)

    _, out = lax.scan(step, xy0, noise)
    return out


@functools.partial(jax.jit, static_argnames=("n_particles", "steps", "ripple_tiling"))
def simulate_dust(key: Array, dune_height: Float[Array, "H W"], ripple_height: Float[Array, "h w"], *,
                  n_particles: int = 256, steps: int = 60, params: DustParams = DustParams(),
                  ripple_tiling: float = 1.0) -> tuple[Float[Array, "T N 3"], Float[Array, "T N"]]:
    """Launch `n_particles` over the dune, advect them by eq. 7; positions (x, y, z) per step
    and billboard sizes from the ripple heights under them."""
    dune_height = jnp.asarray(dune_height)
    k_init, k_walk = jax.random.split(key)
    xy0 = init_dust(k_init, n_particles, dune_height.shape, dtype=dune_height.dtype)
    positions = advect_dust(k_walk, xy0, dune_height, steps=steps, params=params)
    sizes = dust_sizes(positions[..., :2], ripple_height, ripple_tiling=ripple_tiling, size_scale=params.size_scale)
    return positions, sizes

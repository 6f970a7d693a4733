"""Percentage-closer soft shadows (Fernando 2005; paper 004 section 4.5) over a `ShadowMap`.

The shadow map is SHAFTS's format (`jaxrender.shadows._shadow_map`: Euclidean distance from the
light position along each texel-centre ray, a square perspective grid of half-angle c); depths
are converted to depth along the light's axis (z = distance * cos of the texel ray's angle) so
that the similar-triangle relations below are exact for planes parallel to the light.

The light is a square of side `light_size` centred on the map's position, facing along its axis.
For a receiver at axis depth z_r (map coordinates uv, tan-space scale 1 / (2 tan c) per unit):
1. Blocker search: an n_b x n_b grid over the square of half-width
   r_s = (light_size / 2) (z_r - near) / (z_r near) / (2 tan c)  (uv; the light's frustum seen
   from the receiver, cut at the `near` plane); blockers are texels with z < z_r - bias; their mean
   depth is z_b. No blocker: fully lit.
2. Penumbra: a point on the light offset by s sees the blocker plane at a uv offset
   s (z_r - z_b) / (z_r z_b) / (2 tan c), so the light's square maps to the filter half-width
   r_p = (light_size / 2) (z_r - z_b) / (z_r z_b) / (2 tan c).
3. PCF: the fraction of an n_p x n_p grid of texels (cell centres) over that square with
   z >= z_r - bias: for a planar blocker parallel to a square light this is the visible fraction
   of the light, up to the grid's discretisation. As light_size -> 0 it becomes the single
   nearest-texel test of `shadow_test` (the hard-shadow limit).
Radii are clamped to `max_radius` (uv). Points outside the map or behind the light are lit.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ..textures import nearest
from ._shadow_map import ShadowMap

__all__ = ["pcss", "pcf"]


def _grid(n: int, dtype) -> Array:
    c = (jnp.arange(n, dtype=dtype) + 0.5) / n * 2 - 1   # cell centres in [-1, 1]
    gy, gx = jnp.meshgrid(c, c, indexing="ij")
    return jnp.stack([gx.reshape(-1), gy.reshape(-1)], axis=-1)   # S 2


def _local(sm: ShadowMap, points: Array) -> tuple[Array, Array, Array]:
    rel = points - jnp.broadcast_to(sm.position, points.shape)
    local = rel @ sm.rotation.T
    z = local[..., 2]
    front = z > 1e-9
    safe_z = jnp.where(front, z, 1.0)
    uv = 0.5 + local[..., :2] * (0.5 / (safe_z * sm.tan_cutoff))[..., None]
    return uv, z, front


def _z_at(sm: ShadowMap, uv: Array) -> Array:
    """Axis depth of the texels at `uv` (inf where nothing was hit)."""
    d = nearest(sm.depth[..., None], uv, wrap="clamp")[..., 0]
    n = sm.depth.shape[0]
    centre = (jnp.floor(jnp.clip(uv, 0.0, 1.0 - 1e-7) * n) + 0.5) / n * 2 - 1
    tan2 = jnp.sum((centre * sm.tan_cutoff) ** 2, axis=-1)
    return d / jnp.sqrt(1 + tan2)


def pcf(sm: ShadowMap, uv: Float[Array, "... 2"], z: Float[Array, "..."], radius: Float[Array, "..."], *,
        samples: int = 6, bias: float | Array = 0.01) -> Float[Array, "..."]:
    """Fraction of an n x n grid over the uv square of half-width `radius` that is lit at depth z."""
    g = _grid(samples, uv.dtype)
    offs = radius[..., None, None] * g.reshape((1,) * radius.ndim + g.shape)
    zt = _z_at(sm, uv[..., None, :] + offs)
    return jnp.mean((zt >= z[..., None] - bias).astype(uv.dtype), axis=-1)


def pcss(sm: ShadowMap, points: Float[ArrayLike, "... 3"], *, light_size: float | Array, near: float = 0.05,
         blocker_samples: int = 5, pcf_samples: int = 6, bias: float | Array = 0.01,
         max_radius: float = 0.2) -> Float[Array, "..."]:
    """Soft visibility (1 lit .. 0 umbra) of `points` from a square light of side `light_size`."""
    points = jnp.asarray(points)
    uv, z, front = _local(sm, points)
    tc = sm.tan_cutoff
    safe_z = jnp.where(front, z, 1.0)
    half = 0.5 * light_size
    r_search = jnp.clip(half * jnp.maximum(safe_z - near, 0.0) / (safe_z * near) / (2 * tc), 0.0, max_radius)
    g = _grid(blocker_samples, uv.dtype)
    offs = r_search[..., None, None] * g.reshape((1,) * r_search.ndim + g.shape)
    zt = _z_at(sm, uv[..., None, :] + offs)
    blocker = zt < z[..., None] - bias
    n_block = jnp.sum(blocker.astype(uv.dtype), axis=-1)
    z_b = jnp.sum(jnp.where(blocker, zt, 0.0), axis=-1) / jnp.maximum(n_block, 1.0)
    z_b = jnp.where(n_block > 0, jnp.maximum(z_b, 1e-6), safe_z)
    r_pen = jnp.clip(half * (safe_z - z_b) / (safe_z * z_b) / (2 * tc), 0.0, max_radius)
    vis = pcf(sm, uv, z, r_pen, samples=pcf_samples, bias=bias)
    inside = front & jnp.all((uv >= 0.0) & (uv <= 1.0), axis=-1)
    return jnp.where(inside & (n_block > 0), vis, 1.0)

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

Written for XLA's CPU backend (the Noh frame runs it at ~10^5 points x 4 fires every frame): the
map's distances are converted to axis depths once per map (not per tap), taps are flat gathers
at integer texel indices computed per grid row and column (n_b + n_b floors, not n_b^2), the
tap axis leads (reductions over a major axis) and the light-space transform is written out
component by component (minor-axis contractions over xyz/uv are slow there).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._shadow_map import ShadowMap

__all__ = ["pcss", "pcf"]


def _cells(n: int) -> list[float]:
    """Cell centres of an n-cell grid over [-1, 1]."""
    return [(i + 0.5) / n * 2 - 1 for i in range(n)]


def _axis_depth(sm: ShadowMap) -> Array:
    """The map as axis depths z = distance * cos(texel ray's angle), flattened (inf = nothing)."""
    n = sm.depth.shape[0]
    t = ((jnp.arange(n, dtype=sm.depth.dtype) + 0.5) / n * 2 - 1) * sm.tan_cutoff
    return (sm.depth * jnp.sqrt(1.0 / (1.0 + t[:, None] ** 2 + t[None, :] ** 2))).reshape(-1)


def _local(sm: ShadowMap, points: Array) -> tuple[Array, Array, Array, Array]:
    """(u, v, z, in front) of the points in the map's projection."""
    rel = [points[..., i] - sm.position[i] for i in range(3)]
    r = sm.rotation
    x, y, z = (rel[0] * r[i, 0] + rel[1] * r[i, 1] + rel[2] * r[i, 2] for i in range(3))
    front = z > 1e-9
    scale = 0.5 / (jnp.where(front, z, 1.0) * sm.tan_cutoff)
    return 0.5 + x * scale, 0.5 + y * scale, z, front


def _taps(zflat: Array, n: int, u: Array, v: Array, radius: Array, samples: int) -> Array:
    """Axis depths of the nearest texels (clamped) at the cell centres of a samples x samples grid
    over the uv square of half-width `radius`: (samples^2, ...)."""
    tx, ty, rt = u * n, v * n, radius * n
    cols = [jnp.clip(jnp.floor(tx + rt * g), 0, n - 1).astype(jnp.int32) for g in _cells(samples)]
    rows = [jnp.clip(jnp.floor(ty + rt * g), 0, n - 1).astype(jnp.int32) * n for g in _cells(samples)]
    index = jnp.stack([r + c for r in rows for c in cols])
    return zflat[index]


def _pcf(zflat: Array, n: int, u: Array, v: Array, z: Array, radius: Array, samples: int, bias) -> Array:
    zt = _taps(zflat, n, u, v, radius, samples)
    return jnp.mean((zt >= z[None] - bias).astype(u.dtype), axis=0)


def pcf(sm: ShadowMap, uv: Float[Array, "... 2"], z: Float[Array, "..."], radius: Float[Array, "..."], *,
        samples: int = 6, bias: float | Array = 0.01) -> Float[Array, "..."]:
    """Fraction of an n x n grid over the uv square of half-width `radius` that is lit at depth z."""
    uv = jnp.asarray(uv)
    return _pcf(_axis_depth(sm), sm.depth.shape[0], uv[..., 0], uv[..., 1], jnp.asarray(z, uv.dtype),
                jnp.asarray(radius, uv.dtype), samples, bias)


def pcss(sm: ShadowMap, points: Float[ArrayLike, "... 3"], *, light_size: float | Array, near: float = 0.05,
         blocker_samples: int = 5, pcf_samples: int = 6, bias: float | Array = 0.01,
         max_radius: float = 0.2) -> Float[Array, "..."]:
    """Soft visibility (1 lit .. 0 umbra) of `points` from a square light of side `light_size`."""
    points = jnp.asarray(points)
    u, v, z, front = _local(sm, points)
    n = sm.depth.shape[0]
    zflat = _axis_depth(sm)
    tc = sm.tan_cutoff
    safe_z = jnp.where(front, z, 1.0)
    half = 0.5 * light_size
    r_search = jnp.clip(half * jnp.maximum(safe_z - near, 0.0) / (safe_z * near) / (2 * tc), 0.0, max_radius)
    zt = _taps(zflat, n, u, v, r_search, blocker_samples)
    blocker = zt < z[None] - bias
    n_block = jnp.sum(blocker.astype(u.dtype), axis=0)
    z_b = jnp.sum(jnp.where(blocker, zt, 0.0), axis=0) / jnp.maximum(n_block, 1.0)
    z_b = jnp.where(n_block > 0, jnp.maximum(z_b, 1e-6), safe_z)
    r_pen = jnp.clip(half * (safe_z - z_b) / (safe_z * z_b) / (2 * tc), 0.0, max_radius)
    vis = _pcf(zflat, n, u, v, z, r_pen, pcf_samples, bias)
    inside = front & (u >= 0.0) & (u <= 1.0) & (v >= 0.0) & (v <= 1.0)
    return jnp.where(inside & (n_block > 0), vis, 1.0)

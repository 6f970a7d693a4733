"""Shadows on a heightfield by rays marched toward a distant light (paper 001 section 3.4).

The heightfield is a grid of vertex heights z[j, i] at world (x, y) = (i, j) * spacing; the
surface is two triangles per cell, so along every grid line it is the linear interpolation of the
two vertices. A shadow ray from P toward the light is sampled where its xy projection crosses the
grid lines x = i * spacing and y = j * spacing (Fig. 7): consecutive crossings of one family are
a constant step apart, and the ray height at them grows by a constant increment, so positions and
heights are computed incrementally. P is in shadow when the ray passes below the surface at a
crossing (Fig. 8). Rays leaving the grid are unblocked.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

__all__ = ["heightfield_light", "heightfield_shadow", "triangle_height"]


def triangle_height(z: Float[ArrayLike, "Ny Nx"], xy: Float[ArrayLike, "... 2"], *,
                    spacing: float = 1.0) -> Float[Array, "..."]:
    """Height of the triangulated surface (diagonal from (i, j) to (i+1, j+1) in each cell) at
    world xy, clamped to the grid."""
    z = jnp.asarray(z)
    xy = jnp.asarray(xy)
    ny, nx = z.shape
    gx = jnp.clip(xy[..., 0] / spacing, 0.0, nx - 1.0)
    gy = jnp.clip(xy[..., 1] / spacing, 0.0, ny - 1.0)
    i = jnp.clip(jnp.floor(gx).astype(jnp.int32), 0, nx - 2)
    j = jnp.clip(jnp.floor(gy).astype(jnp.int32), 0, ny - 2)
    fx = gx - i.astype(gx.dtype)
    fy = gy - j.astype(gy.dtype)
    z00, z10 = z[j, i], z[j, i + 1]
    z01, z11 = z[j + 1, i], z[j + 1, i + 1]
    lower = z00 + fx * (z10 - z00) + fy * (z11 - z10)  # fx >= fy: triangle (00, 10, 11)
    upper = z00 + fy * (z01 - z00) + fx * (z11 - z01)  # fy > fx: triangle (00, 01, 11)
    return jnp.where(fx >= fy, lower, upper)


def _family_depth(z: Array, p: Array, hdir: Array, slope: Array, spacing: float, n_steps: int,
                  axis: int, bias: float) -> Array:
    """How far the ray passes below the surface (max of surface - bias - ray height, -inf when it
    never does) at the crossings of the lines x = i*spacing (axis 0) or y = j*spacing (axis 1);
    blocked where > 0."""
    ny, nx = z.shape
    d_a = hdir[axis]
    d_b = hdir[1 - axis]
    n_a, n_b = (nx, ny) if axis == 0 else (ny, nx)
    moving = jnp.abs(d_a) > 1e-9
    safe_da = jnp.where(moving, d_a, 1.0)
    sign = jnp.where(d_a > 0, 1.0, -1.0).astype(p.dtype)
    g_a = p[..., axis] / spacing
    first = jnp.where(d_a > 0, jnp.floor(g_a) + 1.0, jnp.ceil(g_a) - 1.0)
    t0 = (first - g_a) * spacing / safe_da  # horizontal distance to the first crossing
    dt = spacing / jnp.abs(safe_da)  # constant step between crossings (incremental)
    b0 = p[..., 1 - axis] + t0 * d_b
    h0 = p[..., 2] + t0 * slope
    db = dt * d_b
    dh = dt * slope

    def step(k, state):
        line, b, h, depth = state
        inside = (line >= 0) & (line <= n_a - 1) & (b >= 0) & (b <= (n_b - 1) * spacing)
        li = jnp.clip(line, 0, n_a - 1).astype(jnp.int32)
        gb = jnp.clip(b / spacing, 0.0, n_b - 1.0)
        bi = jnp.clip(jnp.floor(gb).astype(jnp.int32), 0, n_b - 2)
        fb = gb - bi.astype(gb.dtype)
        if axis == 0:
            surf = z[bi, li] * (1 - fb) + z[bi + 1, li] * fb
        else:
            surf = z[li, bi] * (1 - fb) + z[li, bi + 1] * fb
        depth = jnp.maximum(depth, jnp.where(inside, surf - bias - h, -jnp.inf))
        return line + sign, b + db, h + dh, depth

    init = (first, b0, h0, jnp.full(p.shape[:-1], -jnp.inf, p.dtype))
    _, _, _, depth = jax.lax.fori_loop(0, n_steps, step, init)
    return jnp.where(moving, depth, -jnp.inf)


def _depth(z, points, light_dir, spacing, n_steps, bias):
    """(depth below the surface over both families, light has a horizontal component, slope)."""
    z = jnp.asarray(z)
    points = jnp.asarray(points)
    light_dir = jnp.asarray(light_dir)
    flat = jnp.sqrt(light_dir[0] ** 2 + light_dir[1] ** 2)
    has_flat = flat > 1e-9
    safe_flat = jnp.where(has_flat, flat, 1.0)
    hdir = jnp.where(has_flat, light_dir[:2] / safe_flat, jnp.zeros(2, light_dir.dtype))
    slope = light_dir[2] / safe_flat  # rise of the ray per unit of horizontal distance
    depth = jnp.maximum(_family_depth(z, points, hdir, slope, spacing, n_steps, 0, bias),
                        _family_depth(z, points, hdir, slope, spacing, n_steps, 1, bias))
    return depth, has_flat, slope


def heightfield_shadow(z: Float[ArrayLike, "Ny Nx"], points: Float[ArrayLike, "... 3"],
                       light_dir: Float[ArrayLike, "3"], *, spacing: float = 1.0, n_steps: int = 64,
                       bias: float = 1e-4) -> Bool[Array, "..."]:
    """True where the ray from `points` toward the distant light `light_dir` (unit, z up) passes
    below the heightfield at one of the next `n_steps` crossings of each family of grid lines.

    `n_steps` is static: (relief / tan(light elevation)) / spacing + 1 crossings per family are
    enough for a ray to clear the highest vertex. `bias` (world units) keeps a point from
    shadowing itself through rounding."""
    depth, has_flat, _ = _depth(z, points, light_dir, spacing, n_steps, bias)
    return has_flat & (depth > 0) | (jnp.asarray(light_dir)[2] <= 0)


def heightfield_light(z: Float[ArrayLike, "Ny Nx"], points: Float[ArrayLike, "... 3"],
                      light_dir: Float[ArrayLike, "3"], *, spacing: float = 1.0, n_steps: int = 64, bias: float = 1e-4,
                      footprint: float | Float[ArrayLike, "..."] = 0.0) -> Float[Array, "..."]:
    """The lit fraction of `heightfield_shadow`'s test over a shading footprint: 1 where the test
    says unblocked, 0 where the ray passes deeper below the surface than one footprint's worth,
    a linear ramp in between (the shadow's edge antialiased instead of a hard step).

    Moving a point by `footprint` (world units, e.g. a texel) toward the light changes its shadow
    ray's height at a crossing by about footprint * slope, so a ray d below the surface gets
    1 - d / (footprint * slope), clipped. The ramp lies on the shadow side only: a lit point's ray
    passes just above the surface near the point itself, which must not darken it. footprint 0
    gives the binary test."""
    depth, has_flat, slope = _depth(z, points, light_dir, spacing, n_steps, bias)
    width = jnp.asarray(footprint, depth.dtype) * jnp.maximum(slope, 0.0)
    soft = jnp.clip(1.0 - depth / jnp.where(width > 0, width, 1.0), 0.0, 1.0)
    lit = jnp.where(width > 0, soft, (depth <= 0).astype(depth.dtype))
    lit = jnp.where(has_flat, lit, 1.0)
    return jnp.where(jnp.asarray(light_dir)[2] <= 0, 0.0, lit)

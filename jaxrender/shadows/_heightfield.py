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

__all__ = ["heightfield_shadow", "triangle_height"]


def triangle_height(z: Float[ArrayLike, "Ny Nx"], xy: Float[ArrayLike, "... 2"], *, spacing: float = 1.0) -> Float[Array, "..."]:
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


def _family_blocked(z: Array, p: Array, hdir: Array, slope: Array, spacing: float, n_steps: int,
                    axis: int, bias: float) -> Array:
    """Blocked by the crossings of the lines x = i*spacing (axis 0) or y = j*spacing (axis 1)."""
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
        line, b, h, blocked = state
        inside = (line >= 0) & (line <= n_a - 1) & (b >= 0) & (b <= (n_b - 1) * spacing)
        li = jnp.clip(line, 0, n_a - 1).astype(jnp.int32)
        gb = jnp.clip(b / spacing, 0.0, n_b - 1.0)
        bi = jnp.clip(jnp.floor(gb).astype(jnp.int32), 0, n_b - 2)
        fb = gb - bi.astype(gb.dtype)
        if axis == 0:
            surf = z[bi, li] * (1 - fb) + z[bi + 1, li] * fb
        else:
            surf = z[li, bi] * (1 - fb) + z[li, bi + 1] * fb
        blocked = blocked | (inside & (h < surf - bias))
        return line + sign, b + db, h + dh, blocked

    init = (first, b0, h0, jnp.zeros(p.shape[:-1], bool))
    _, _, _, blocked = jax.lax.fori_loop(0, n_steps, step, init)
    return blocked & moving


def heightfield_shadow(z: Float[ArrayLike, "Ny Nx"], points: Float[ArrayLike, "... 3"], light_dir: Float[ArrayLike, "3"], *,
                       spacing: float = 1.0, n_steps: int = 64, bias: float = 1e-4) -> Bool[Array, "..."]:
    """True where the ray from `points` toward the distant light `light_dir` (unit, z up) passes
    below the heightfield at one of the next `n_steps` crossings of each family of grid lines.

    `n_steps` is static: (relief / tan(light elevation)) / spacing + 1 crossings per family are
    enough for a ray to clear the highest vertex. `bias` (world units) keeps a point from
    shadowing itself through rounding."""
    z = jnp.asarray(z)
    points = jnp.asarray(points)
    light_dir = jnp.asarray(light_dir)
    flat = jnp.sqrt(light_dir[0] ** 2 + light_dir[1] ** 2)
    has_flat = flat > 1e-9
    safe_flat = jnp.where(has_flat, flat, 1.0)
    hdir = jnp.where(has_flat, light_dir[:2] / safe_flat, jnp.zeros(2, light_dir.dtype))
    slope = light_dir[2] / safe_flat  # rise of the ray per unit of horizontal distance
    bx = _family_blocked(z, points, hdir, slope, spacing, n_steps, 0, bias)
    by = _family_blocked(z, points, hdir, slope, spacing, n_steps, 1, bias)
    return has_flat & (bx | by) | (light_dir[2] <= 0)

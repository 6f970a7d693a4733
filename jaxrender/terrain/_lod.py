"""Per-quad culling and level of detail (paper 001 section 3.3).

A quad of the dune grid is culled when both its triangles face away from the eye (back-face) or
its four corners lie on the outer side of one edge of the view frustum (or behind the eye). Its
ripple level is chosen from its projected area on screen (Williams' pyramidal parametrics): level
l has n0 / 2^l texels across the quad, and the level is the one whose texel count is nearest (in
log scale) to the quad's pixel count."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from ..camera import Camera

__all__ = ["quad_corners", "quad_visibility", "quad_screen_area", "quad_levels"]


def quad_corners(z: Float[ArrayLike, "Ny Nx"], *, spacing: float = 1.0) -> Float[Array, "Ny Nx 3"]:
    """World positions of the grid vertices: (i s, j s, z[j, i])."""
    z = jnp.asarray(z)
    ny, nx = z.shape
    gy, gx = jnp.meshgrid(jnp.arange(ny, dtype=z.dtype) * spacing, jnp.arange(nx, dtype=z.dtype) * spacing,
                          indexing="ij")
    return jnp.stack([gx, gy, z], axis=-1)


def _corners4(v: Array) -> tuple[Array, Array, Array, Array]:
    return v[:-1, :-1], v[:-1, 1:], v[1:, 1:], v[1:, :-1]  # 00, 10, 11, 01 (counter-clockwise from above)


def quad_visibility(z: Float[ArrayLike, "Ny Nx"], camera: Camera, *, spacing: float = 1.0, backface: bool = True,
                    frustum: bool = True) -> Bool[Array, "Ny-1 Nx-1"]:
    """True for quads that survive back-face and view-frustum culling."""
    p = quad_corners(z, spacing=spacing)
    p00, p10, p11, p01 = _corners4(p)
    eye = jnp.reshape(camera.eye.astype(p.dtype), (1, 1, 3))
    visible = jnp.ones(p00.shape[:2], bool)
    if backface:
        n1 = jnp.cross(p10 - p00, p11 - p00)
        n2 = jnp.cross(p11 - p00, p01 - p00)
        to_eye = eye - p00
        # a little tolerance keeps quads seen exactly edge-on (conservative culling)
        tol = 1e-6 * jnp.sqrt(jnp.sum(n1 * n1, -1) * jnp.sum(to_eye * to_eye, -1))
        visible &= (jnp.sum(n1 * to_eye, -1) > -tol) | (jnp.sum(n2 * to_eye, -1) > -tol)
    if frustum:
        pix, depth = camera.project(p)
        c4 = [c[..., 0] for c in _corners4(pix)]
        r4 = [c[..., 1] for c in _corners4(pix)]
        d4 = _corners4(depth)
        all_in_front = jnp.all(jnp.stack([d > 0 for d in d4]), axis=0)
        all_behind = jnp.all(jnp.stack([d <= 0 for d in d4]), axis=0)
        outside = (jnp.all(jnp.stack([c < 0 for c in c4]), axis=0)
                   | jnp.all(jnp.stack([c > camera.width for c in c4]), axis=0)
                   | jnp.all(jnp.stack([r < 0 for r in r4]), axis=0)
                   | jnp.all(jnp.stack([r > camera.height for r in r4]), axis=0))
        visible &= ~all_behind & ~(all_in_front & outside)
    return visible


def quad_screen_area(z: Float[ArrayLike, "Ny Nx"], camera: Camera, *,
                     spacing: float = 1.0) -> Float[Array, "Ny-1 Nx-1"]:
    """Projected area of each quad in pixels (shoelace over its 4 projected corners); +inf for a
    quad with a corner behind the eye."""
    p = quad_corners(z, spacing=spacing)
    pix, depth = camera.project(p)
    c = _corners4(pix)
    area = 0.0
    for a, b in zip(c, c[1:] + c[:1]):
        area = area + (a[..., 0] * b[..., 1] - b[..., 0] * a[..., 1])
    area = 0.5 * jnp.abs(area)
    behind = jnp.any(jnp.stack([d <= 0 for d in _corners4(depth)]), axis=0)
    return jnp.where(behind, jnp.inf, area)


def quad_levels(area: Float[ArrayLike, "..."], *, texels: int = 64, levels: int = 4,
                bias: float = 0.0) -> Int[Array, "..."]:
    """Ripple level per quad: round(log2(texels / sqrt(area)) + bias), clamped to [0, levels-1]
    (level 0 = `texels` across the quad, each level halves it)."""
    area = jnp.asarray(area)
    safe = jnp.maximum(area, 1e-6)
    lvl = jnp.floor(jnp.log2(texels / jnp.sqrt(safe)) + bias + 0.5)
    lvl = jnp.where(jnp.isfinite(area), lvl, 0.0)
    return jnp.clip(lvl, 0, levels - 1).astype(jnp.int32)

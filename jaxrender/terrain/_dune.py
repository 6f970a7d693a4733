"""Dune surface: a grid of quads (two triangles each) over a heightfield, its smooth normals,
and ray casting of camera rays against it."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ..maths import normalize
from ..shadows import triangle_height

__all__ = ["close_periodic", "vertex_normals", "ray_cast_heightfield"]


def close_periodic(height: Float[ArrayLike, "N M"]) -> Float[Array, "N+1 M+1"]:
    """Vertex grid of a periodic field: repeat the first row and column at the end, so an N x M
    periodic field becomes N x M quads."""
    h = jnp.asarray(height)
    h = jnp.concatenate([h, h[:1]], axis=0)
    return jnp.concatenate([h, h[:, :1]], axis=1)


def vertex_normals(z: Float[ArrayLike, "Ny Nx"], *, spacing: float = 1.0) -> Float[Array, "Ny Nx 3"]:
    """Smooth per-vertex normals by central differences (one-sided at the border)."""
    z = jnp.asarray(z)
    dzdx = jnp.gradient(z, spacing, axis=1)
    dzdy = jnp.gradient(z, spacing, axis=0)
    return normalize(jnp.stack([-dzdx, -dzdy, jnp.ones_like(z)], axis=-1))


def _slab(o: Array, d: Array, lo: Array, hi: Array) -> tuple[Array, Array]:
    safe = jnp.where(jnp.abs(d) > 1e-12, d, 1e-12)
    t_a = (lo - o) / safe
    t_b = (hi - o) / safe
    return jnp.minimum(t_a, t_b), jnp.maximum(t_a, t_b)


def _slab_segment(z: Array, o: Array, dirs: Array, spacing: float) -> tuple[Array, Array, Array]:
    """[t_near, t_far] of each ray inside the surface's bounding box, and whether it is non-empty."""
    ny, nx = z.shape
    # the z slab reaches a little below the lowest vertex so that rays end strictly below a flat floor
    pad = 1e-3 * spacing + 1e-3 * (jnp.max(z) - jnp.min(z))
    lo = jnp.stack([jnp.zeros((), z.dtype), jnp.zeros((), z.dtype), jnp.min(z) - pad])
    hi = jnp.stack([jnp.asarray((nx - 1) * spacing, z.dtype), jnp.asarray((ny - 1) * spacing, z.dtype), jnp.max(z)])
    t_near = jnp.zeros(dirs.shape[:-1], dirs.dtype)
    t_far = jnp.full(dirs.shape[:-1], jnp.inf, dirs.dtype)
    for a in range(3):
        t0, t1 = _slab(o[a], dirs[..., a], lo[a], hi[a])
        t_near = jnp.maximum(t_near, t0)
        t_far = jnp.minimum(t_far, t1)
    valid = t_far > t_near
    return t_near, jnp.where(valid, t_far, t_near), valid


def _march(z: Array, o: Array, dirs: Array, t_a: Array, t_b: Array, spacing: float, n_steps: int,
           n_refine: int) -> tuple[Array, Array]:
    """First sample below the surface among n_steps + 1 even samples of [t_a, t_b], bisected."""
    o_b = jnp.reshape(o, (1,) * (dirs.ndim - 1) + (3,))

    def below(t):
        p = o_b + dirs * t[..., None]
        return p[..., 2] - triangle_height(z, p[..., :2], spacing=spacing) <= 0.0

    def march(k, state):
        found, t_lo, t_hi = state
        t = t_a + (t_b - t_a) * (k.astype(dirs.dtype) / n_steps)
        hit = ~found & below(t)
        t_prev = t_a + (t_b - t_a) * (jnp.maximum(k - 1, 0).astype(dirs.dtype) / n_steps)
        return found | hit, jnp.where(hit, t_prev, t_lo), jnp.where(hit, t, t_hi)

    init = (jnp.zeros(dirs.shape[:-1], bool), t_a, t_b)
    found, t_lo, t_hi = jax.lax.fori_loop(0, n_steps + 1, march, init)

    def refine(_, state):
        t_lo, t_hi = state
        mid = 0.5 * (t_lo + t_hi)
        b = below(mid)
        return jnp.where(b, t_lo, mid), jnp.where(b, mid, t_hi)

    t_lo, t_hi = jax.lax.fori_loop(0, n_refine, refine, (t_lo, t_hi))
    return t_hi, found


def ray_cast_heightfield(z: Float[ArrayLike, "Ny Nx"], origin: Float[ArrayLike, "3"],
                         dirs: Float[ArrayLike, "... 3"], *, spacing: float = 1.0, n_steps: int = 96,
                         n_refine: int = 10) -> tuple[Float[Array, "..."], Array]:
    """Distance along each ray to the first hit of the triangulated heightfield, and a hit mask.

    The ray is clipped to the surface's bounding box [0, (Nx-1) s] x [0, (Ny-1) s] x [zmin, zmax];
    the clipped segment is sampled at `n_steps` even steps for the first sample below the surface,
    then bisected `n_refine` times. A ray entering through a side wall below the surface hits the
    wall (the edge of the world)."""
    z = jnp.asarray(z)
    dirs = jnp.asarray(dirs)
    o = jnp.asarray(origin, dtype=dirs.dtype)
    t_near, t_far, valid = _slab_segment(z, o, dirs, spacing)
    t, found = _march(z, o, dirs, t_near, t_far, spacing, n_steps, n_refine)
    hit = valid & found
    return jnp.where(hit, t, jnp.inf), hit


def ray_cast_coherent(z: Float[ArrayLike, "Ny Nx"], origin: Float[ArrayLike, "3"], dirs: Float[ArrayLike, "H W 3"], *,
                      spacing: float = 1.0, stride: int = 4, n_steps: int = 96, fine_steps: int = 16,
                      n_refine: int = 10) -> tuple[Float[Array, "H W"], Array]:
    """`ray_cast_heightfield` for an image of rays, using the coherence of neighbouring pixels.

    Every `stride`-th ray in both directions is cast in full (`n_steps` over its whole segment).
    Each pixel then searches only between the nearest and farthest hits of the 3 x 3 coarse rays
    around it (widened by a cell; to the far end of its segment where one of them missed) with
    `fine_steps` samples, and bisects. A feature thinner than about `stride` pixels that none of
    the coarse rays sees can be missed; otherwise the result is that of the full search."""
    z = jnp.asarray(z)
    dirs = jnp.asarray(dirs)
    o = jnp.asarray(origin, dtype=dirs.dtype)
    h, w = dirs.shape[:2]
    s = stride
    coarse_dirs = dirs[s // 2::s, s // 2::s]
    tc, hc = ray_cast_heightfield(z, o, coarse_dirs, spacing=spacing, n_steps=n_steps, n_refine=n_refine)
    big = jnp.asarray(jnp.finfo(dirs.dtype).max, dirs.dtype)
    t_lo_c = jnp.where(hc, tc, big)
    t_hi_c = jnp.where(hc, tc, big)
    pad_lo = jnp.pad(t_lo_c, 1, mode="edge")
    pad_hi = jnp.pad(t_hi_c, 1, mode="edge")
    hh, ww = tc.shape
    nb_min = jnp.min(jnp.stack([pad_lo[i:i + hh, j:j + ww] for i in range(3) for j in range(3)]), axis=0)
    nb_max = jnp.max(jnp.stack([pad_hi[i:i + hh, j:j + ww] for i in range(3) for j in range(3)]), axis=0)
    # each pixel takes the neighbourhood of the coarse ray nearest to it
    rows = jnp.clip(jnp.arange(h) // s, 0, hh - 1)
    cols = jnp.clip(jnp.arange(w) // s, 0, ww - 1)
    t_min = nb_min[rows][:, cols]
    t_max = nb_max[rows][:, cols]
    t_near, t_far, valid = _slab_segment(z, o, dirs, spacing)
    margin = 1.0 * spacing
    t_a = jnp.where(t_min < big, jnp.maximum(t_near, t_min - margin), t_near)
    t_b = jnp.where(t_max < big, jnp.minimum(t_far, t_max + margin), t_far)
    t_b = jnp.maximum(t_b, t_a)
    t, found = _march(z, o, dirs, t_a, t_b, spacing, fine_steps, n_refine)
    hit = valid & found
    return jnp.where(hit, t, jnp.inf), hit

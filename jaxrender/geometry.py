"""Analytic primitives (spheres, quads) and closest-hit ray casting.

In the MJX style: one intersection function per primitive written for ONE ray and one primitive,
vmapped over the packed primitives and over rays. A miss is `inf`. Every function is
gradient-safe: the square root of a negative discriminant and the division by a ray parallel to
a quad are guarded on both branches of `where`, so misses never put NaN into a gradient.

Packed primitives are eqx.Modules with a leading batch axis (`Spheres`, `Quads`); an empty
group (zero rows) is allowed and simply never hit. Quads follow design.md: centre and half-extent
vectors u, v (corners centre +- u +- v); their geometric normal is normalize(u x v) (surfaces are
two-sided; shading takes |cos|).
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

from .fusion import materialize
from .maths import SHORT_AXIS, dot, normalize

__all__ = ["Spheres", "Quads", "intersect_sphere", "intersect_quad", "cast_rays", "nearest_hits", "hit_attributes",
           "closest_hit", "nearest_distance", "occluded", "bounding_points", "hit_point"]

T_MIN = 1e-4  # ignore hits closer than this (self-intersection of rays leaving a surface)


def _as_rows(x, n_cols: int) -> Array:
    x = jnp.asarray(x, dtype=float)
    return x.reshape((-1, n_cols)) if n_cols else x.reshape((-1,))


class Spheres(eqx.Module):
    """N spheres: `center` (N, 3), `radius` (N,), `albedo` (N, 3) linear RGB."""

    center: Float[Array, "N 3"]
    radius: Float[Array, " N"]
    albedo: Float[Array, "N 3"]

    def __init__(self, center, radius, albedo=None):
        self.center = _as_rows(center, 3)
        self.radius = _as_rows(radius, 0)
        n = self.center.shape[0]
        self.albedo = jnp.full((n, 3), 0.8) if albedo is None else _as_rows(albedo, 3)

    @property
    def count(self) -> int:
        return self.center.shape[0]

    def intersect(self, origin: Float[Array, "3"], direction: Float[Array, "3"]) -> Float[Array, " N"]:
        """Hit distance of one ray against every sphere (inf = miss)."""
        return jax.vmap(intersect_sphere, in_axes=(None, None, 0, 0))(origin, direction, self.center, self.radius)

    def normal(self, index: Array, point: Float[Array, "3"]) -> Float[Array, "3"]:
        return normalize(point - self.center[index])

    def bounding_points(self) -> Float[Array, "M 3"]:
        """Corners of each sphere's bounding box (8 per sphere)."""
        signs = jnp.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
        pts = self.center[:, None, :] + self.radius[:, None, None] * signs[None, :, :]
        return pts.reshape((-1, 3))


class Quads(eqx.Module):
    """N parallelograms: `center` (N, 3), half-extent vectors `u`, `v` (N, 3), `albedo` (N, 3)."""

    center: Float[Array, "N 3"]
    u: Float[Array, "N 3"]
    v: Float[Array, "N 3"]
    albedo: Float[Array, "N 3"]

    def __init__(self, center, u, v, albedo=None):
        self.center = _as_rows(center, 3)
        self.u = _as_rows(u, 3)
        self.v = _as_rows(v, 3)
        n = self.center.shape[0]
        self.albedo = jnp.full((n, 3), 0.5) if albedo is None else _as_rows(albedo, 3)

    @property
    def count(self) -> int:
        return self.center.shape[0]

    def intersect(self, origin: Float[Array, "3"], direction: Float[Array, "3"]) -> Float[Array, " N"]:
        return jax.vmap(intersect_quad, in_axes=(None, None, 0, 0, 0))(origin, direction, self.center, self.u, self.v)

    def normal(self, index: Array, point: Float[Array, "3"]) -> Float[Array, "3"]:
        return normalize(jnp.cross(self.u[index], self.v[index]))

    def bounding_points(self) -> Float[Array, "M 3"]:
        """The four corners of each quad."""
        pts = [self.center + su * self.u + sv * self.v for su in (-1.0, 1.0) for sv in (-1.0, 1.0)]
        return jnp.stack(pts, axis=1).reshape((-1, 3))


Primitives = Sequence[Spheres | Quads]


def intersect_sphere(origin: Float[ArrayLike, "3"], direction: Float[ArrayLike, "3"],
                     center: Float[ArrayLike, "3"], radius: Float[ArrayLike, ""], *, t_min: float = T_MIN
                     ) -> Float[Array, ""]:
    """Nearest hit distance t > t_min of the ray origin + t * direction (direction unit length)
    with one sphere; inf when missed. Gradient-safe at tangency and on misses."""
    oc = jnp.asarray(origin) - jnp.asarray(center)
    d = jnp.asarray(direction)
    b = dot(oc, d)
    c = dot(oc, oc) - jnp.asarray(radius) ** 2
    disc = b * b - c
    hit = disc > 0
    root = jnp.sqrt(jnp.where(hit, disc, 1.0))
    t0 = -b - root
    t1 = -b + root
    t = jnp.where(t0 > t_min, t0, t1)
    ok = hit & (t > t_min)
    return jnp.where(ok, t, jnp.inf)


def intersect_quad(origin: Float[ArrayLike, "3"], direction: Float[ArrayLike, "3"], center: Float[ArrayLike, "3"],
                   u: Float[ArrayLike, "3"], v: Float[ArrayLike, "3"], *, t_min: float = T_MIN) -> Float[Array, ""]:
    """Hit distance of one ray with the parallelogram centre +- u +- v; inf when missed
    (also for rays parallel to it)."""
    o = jnp.asarray(origin)
    d = jnp.asarray(direction)
    c, u, v = jnp.asarray(center), jnp.asarray(u), jnp.asarray(v)
    n = jnp.cross(u, v)
    denom = dot(d, n)
    ok_denom = jnp.abs(denom) > 1e-12
    t = dot(c - o, n) / jnp.where(ok_denom, denom, 1.0)
    p = o + t * d - c
    # coordinates of p in the (u, v) basis (u, v need not be orthogonal)
    uu, vv, uv = dot(u, u), dot(v, v), dot(u, v)
    pu, pv = dot(p, u), dot(p, v)
    det = uu * vv - uv * uv
    safe_det = jnp.where(jnp.abs(det) > 1e-24, det, 1.0)
    a = (pu * vv - pv * uv) / safe_det
    b = (pv * uu - pu * uv) / safe_det
    ok = ok_denom & (t > t_min) & (jnp.abs(a) <= 1.0) & (jnp.abs(b) <= 1.0)
    return jnp.where(ok, t, jnp.inf)


def _soa(x: Array) -> tuple[Array, Array, Array]:
    return x[..., 0], x[..., 1], x[..., 2]


def _spheres_t_soa(o, d, spheres: Spheres, t_min: float) -> Array:
    """(R, N) hit distances, rays as component tuples of (R, 1) arrays (structure of arrays:
    XLA vectorizes these loops far better than reductions over a minor axis of size 3)."""
    cx, cy, cz = (spheres.center[None, :, i] for i in range(3))
    ocx, ocy, ocz = o[0] - cx, o[1] - cy, o[2] - cz
    b = ocx * d[0] + ocy * d[1] + ocz * d[2]
    c = ocx * ocx + ocy * ocy + ocz * ocz - spheres.radius[None, :] ** 2
    disc = b * b - c
    hit = disc > 0
    root = jnp.sqrt(jnp.where(hit, disc, 1.0))
    t0, t1 = -b - root, -b + root
    t = jnp.where(t0 > t_min, t0, t1)
    return jnp.where(hit & (t > t_min), t, jnp.inf)


def _quads_t_soa(o, d, quads: Quads, t_min: float) -> Array:
    c, u, v = quads.center, quads.u, quads.v
    n = jnp.cross(u, v)
    uu, vv, uv = dot(u, u), dot(v, v), dot(u, v)
    det = uu * vv - uv * uv
    inv_det = 1.0 / jnp.where(jnp.abs(det) > 1e-24, det, 1.0)
    row = lambda x, i: x[None, :, i]  # noqa: E731
    denom = d[0] * row(n, 0) + d[1] * row(n, 1) + d[2] * row(n, 2)
    ok_denom = jnp.abs(denom) > 1e-12
    dcx, dcy, dcz = row(c, 0) - o[0], row(c, 1) - o[1], row(c, 2) - o[2]
    t = (dcx * row(n, 0) + dcy * row(n, 1) + dcz * row(n, 2)) / jnp.where(ok_denom, denom, 1.0)
    px, py, pz = t * d[0] - dcx, t * d[1] - dcy, t * d[2] - dcz
    pu = px * row(u, 0) + py * row(u, 1) + pz * row(u, 2)
    pv = px * row(v, 0) + py * row(v, 1) + pz * row(v, 2)
    a = (pu * vv[None, :] - pv * uv[None, :]) * inv_det[None, :]
    b = (pv * uu[None, :] - pu * uv[None, :]) * inv_det[None, :]
    ok = ok_denom & (t > t_min) & (jnp.abs(a) <= 1.0) & (jnp.abs(b) <= 1.0)
    return jnp.where(ok, t, jnp.inf)


def _group_t(o, d, group, t_min: float) -> Array:
    if isinstance(group, Spheres):
        return _spheres_t_soa(o, d, group, t_min)
    return _quads_t_soa(o, d, group, t_min)


def _closest_one(origin: Float[Array, "3"], direction: Float[Array, "3"], prims: Primitives):
    """(t, normal, albedo) of the nearest hit of one ray; normal/albedo are 0 on a miss."""
    best_t = jnp.asarray(jnp.inf, dtype=origin.dtype)
    best_n = jnp.zeros(3, dtype=origin.dtype)
    best_a = jnp.zeros(3, dtype=origin.dtype)
    for group in prims:  # a handful of primitive kinds: unrolled
        if group.count == 0:
            continue
        ts = group.intersect(origin, direction)
        i = jnp.argmin(ts)
        t = ts[i]
        closer = t < best_t
        safe_t = jnp.where(jnp.isfinite(t), t, 0.0)
        n = group.normal(i, origin + safe_t * direction)
        best_t = jnp.where(closer, t, best_t)
        best_n = jnp.where(closer, n, best_n)
        best_a = jnp.where(closer, group.albedo[i], best_a)
    return best_t, best_n, best_a


def closest_hit(origin: Float[ArrayLike, "3"], direction: Float[ArrayLike, "3"], prims: Primitives):
    """Single-ray closest hit: (t, normal, albedo)."""
    return _closest_one(jnp.asarray(origin), jnp.asarray(direction), prims)


def cast_rays(origins: Float[ArrayLike, "*B 3"], dirs: Float[ArrayLike, "*B 3"], prims: Primitives
              ) -> tuple[Float[Array, "*B"], Float[Array, "*B 3"], Float[Array, "*B 3"]]:
    """Closest hit of every ray against a sequence of primitive groups (`Spheres`, `Quads`).

    `origins` may be a single point (3,) shared by all rays; `dirs` unit vectors. Returns
    (t, normal, albedo): t = inf and normal = albedo = 0 on a miss; the normal is the geometric
    one (not flipped toward the ray). Same result as vmapping `closest_hit`: `nearest_hits`, stored
    once (`fusion.materialize`: else XLA intersects every primitive again inside each consumer of
    the normals, albedo and hit points), then `hit_attributes`. Per-image code: under `vmap` the
    store becomes a select that evaluates `nearest_hits` twice.
    """
    t, index = materialize(nearest_hits, origins, dirs, prims)
    return (t,) + hit_attributes(origins, dirs, t, index, prims)


def nearest_hits(origins: Float[ArrayLike, "*B 3"], dirs: Float[ArrayLike, "*B 3"], prims: Primitives
                 ) -> tuple[Float[Array, "*B"], Int[Array, "*B"]]:
    """(t, index) of every ray's nearest hit: t = inf and index = -1 on a miss; index counts the
    primitives of the non-empty groups in order (`hit_attributes` reads it)."""
    dirs = jnp.asarray(dirs)
    origins = jnp.broadcast_to(jnp.asarray(origins, dtype=dirs.dtype), dirs.shape)
    o, d = _soa(origins.reshape((-1, 1, 3))), _soa(dirs.reshape((-1, 1, 3)))
    best = jnp.full((o[0].shape[0],), jnp.inf, dtype=dirs.dtype)
    index = jnp.full(best.shape, -1, jnp.int32)
    offset = 0
    for group in prims:  # a handful of primitive kinds: unrolled
        if group.count == 0:
            continue
        ts = _group_t(o, d, group, T_MIN)
        if ts.shape[1] > SHORT_AXIS:
            columns = [(jnp.min(ts, axis=1), jnp.argmin(ts, axis=1).astype(jnp.int32) + offset)]
        else:  # column by column, as `_min_columns` (and as fast)
            columns = [(ts[:, j], offset + j) for j in range(ts.shape[1])]
        for t, i in columns:
            closer = t < best
            best = jnp.where(closer, t, best)
            index = jnp.where(closer, i, index)
        offset += group.count
    return best.reshape(dirs.shape[:-1]), index.reshape(dirs.shape[:-1])


def hit_attributes(origins: Float[ArrayLike, "*B 3"], dirs: Float[ArrayLike, "*B 3"], t: Float[Array, "*B"],
                   index: Int[Array, "*B"], prims: Primitives) -> tuple[Float[Array, "*B 3"], Float[Array, "*B 3"]]:
    """(normal, albedo) at the hits `nearest_hits` found (0 where index is -1): a sphere's normal
    points from its centre to the hit point, a quad's is normalize(u x v)."""
    dirs = jnp.asarray(dirs)
    groups = [g for g in prims if g.count > 0]
    if not groups:
        return jnp.zeros_like(dirs), jnp.zeros_like(dirs)
    albedo = jnp.concatenate([g.albedo for g in groups]).astype(dirs.dtype)
    # per primitive: a sphere's centre and 1 / radius (its normal at p: (p - centre) / radius, no
    # square root), a quad's unit normal and 0
    anchor = jnp.concatenate([g.center if isinstance(g, Spheres) else normalize(jnp.cross(g.u, g.v))
                              for g in groups]).astype(dirs.dtype)
    inv_radius = jnp.concatenate([1.0 / g.radius if isinstance(g, Spheres) else jnp.zeros(g.count)
                                  for g in groups]).astype(dirs.dtype)
    if albedo.shape[0] <= SHORT_AXIS:  # a few primitives: selects, several times faster than gathers on CPU
        albedo_at, anchor_at = jnp.zeros_like(dirs), jnp.zeros_like(dirs)
        inv_radius_at = jnp.zeros(dirs.shape[:-1], dirs.dtype)
        for k in range(albedo.shape[0]):
            this = index == k
            albedo_at = jnp.where(this[..., None], albedo[k], albedo_at)
            anchor_at = jnp.where(this[..., None], anchor[k], anchor_at)
            inv_radius_at = jnp.where(this, inv_radius[k], inv_radius_at)
    else:
        i, hit = jnp.maximum(index, 0), (index >= 0)[..., None]
        albedo_at, anchor_at = jnp.where(hit, albedo[i], 0.0), jnp.where(hit, anchor[i], 0.0)
        inv_radius_at = jnp.where(hit[..., 0], inv_radius[i], 0.0)
    p = hit_point(origins, dirs, t, far=0.0)
    sphere = (inv_radius_at > 0)[..., None]
    return jnp.where(sphere, (p - anchor_at) * inv_radius_at[..., None], anchor_at), albedo_at


def nearest_distance(origins: Float[ArrayLike, "*B 3"], dirs: Float[ArrayLike, "*B 3"], prims: Primitives
                     ) -> Float[Array, "*B"]:
    """The t of `nearest_hits` alone (inf on a miss), for shadow maps and reach tests."""
    return nearest_hits(origins, dirs, prims)[0]


def _min_columns(ts: Float[Array, "R N"]) -> Float[Array, " R"]:
    """min over axis 1: column by column up to SHORT_AXIS columns. XLA on CPU runs a min over a
    short minor axis several times slower than these fused selects (the five-spot stage's 512^2
    shadow maps: 48 -> 9 ms)."""
    if ts.shape[1] > SHORT_AXIS:
        return jnp.min(ts, axis=1)
    return functools.reduce(jnp.minimum, [ts[:, j] for j in range(ts.shape[1])])


def occluded(origins: Float[ArrayLike, "*B 3"], dirs: Float[ArrayLike, "*B 3"], max_t: Float[ArrayLike, "*B"],
             prims: Primitives, *, t_min: float = T_MIN) -> Float[Array, "*B"]:
    """1.0 where something lies between t_min and max_t along the ray (shadow rays), else 0.0."""
    dirs = jnp.asarray(dirs)
    origins = jnp.broadcast_to(jnp.asarray(origins, dtype=dirs.dtype), dirs.shape)
    max_t = jnp.broadcast_to(jnp.asarray(max_t, dtype=dirs.dtype), dirs.shape[:-1]).reshape((-1, 1))
    o, d = _soa(origins.reshape((-1, 1, 3))), _soa(dirs.reshape((-1, 1, 3)))
    hit = jnp.zeros((max_t.shape[0],), dtype=bool)
    for group in prims:
        if group.count == 0:
            continue
        hit = hit | (_min_columns(_group_t(o, d, group, t_min)) < max_t[:, 0])
    return jnp.where(hit, 1.0, 0.0).astype(dirs.dtype).reshape(dirs.shape[:-1])


def bounding_points(prims: Primitives) -> Float[Array, "M 3"]:
    """Points whose convex hull contains every primitive (box corners, quad corners)."""
    pts = [g.bounding_points() for g in prims if g.count > 0]
    if not pts:
        return jnp.zeros((1, 3))
    return jnp.concatenate(pts, axis=0)


def hit_point(origin: Float[ArrayLike, "*B 3"], direction: Float[ArrayLike, "*B 3"], t: Float[ArrayLike, "*B"],
              *, far: float = 1e6) -> Float[Array, "*B 3"]:
    """origin + t * direction with misses (t = inf) clamped to `far` (finite, gradient-safe)."""
    direction = jnp.asarray(direction)
    t = jnp.asarray(t)
    safe_t = jnp.where(jnp.isfinite(t), t, far)
    return jnp.broadcast_to(jnp.asarray(origin), direction.shape) + safe_t[..., None] * direction

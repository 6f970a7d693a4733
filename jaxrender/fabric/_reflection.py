"""Glossy planar reflection in a polished floor (paper 004 section 4.5: the performer and the
fires mirrored in the stage floor).

Mirror geometry: a plane through `point` with unit `normal` reflects a point P to
    P' = P - 2 ((P - point) . n) n
and a direction d to d - 2 (d . n) n. Seen through a camera, the reflection of P in the plane
lies where P' projects: the camera ray toward P' crosses the plane at Q, and from Q on the
mirrored ray goes to P (|Q - P| = |Q - P'|). So rasterizing the mirrored scene (`mirror_mesh`)
with the camera's own pinhole gives, at every floor pixel, what the floor reflects there, and
the distance beyond the floor |Q - P|.

Glossy: the floor's roughness spreads the mirrored ray into a cone of half-angle ~ `roughness`
(radians); at the reflected surface, a distance b beyond the floor, the cone is ~ roughness b
wide, which the camera, (t + b) away along the unfolded ray, sees as
    blur = focal_px roughness b / (t + b)  pixels
(t: the distance from the eye to the floor point). `glossy_reflection` reads the reflected
image from its box mip pyramid at level log2(blur) (`jaxrender.textures.trilinear`): a convex
combination of the reflected radiance around the pixel, so it is never brighter than the
brightest radiance it blends. It is weighted by the Fresnel reflectance of the polished coat
(Schlick: F = F0 + (1 - F0)(1 - cos theta)^5, theta the angle of incidence), so the
reflection is never brighter than what it reflects times the floor's reflectance F <= 1.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

from ..textures import mip_pyramid, trilinear

__all__ = ["reflect_points", "reflect_directions", "mirror_mesh", "fresnel_schlick", "glossy_blur_pixels",
           "glossy_reflection"]


def reflect_points(points: Float[ArrayLike, "... 3"], point: Float[ArrayLike, "3"],
                   normal: Float[ArrayLike, "3"]) -> Float[Array, "... 3"]:
    """The mirror images of `points` in the plane through `point` with unit `normal`."""
    p = jnp.asarray(points)
    q = jnp.reshape(jnp.asarray(point, p.dtype), (1,) * (p.ndim - 1) + (3,))
    n = jnp.reshape(jnp.asarray(normal, p.dtype), (1,) * (p.ndim - 1) + (3,))
    return p - 2.0 * jnp.sum((p - q) * n, -1, keepdims=True) * n


def reflect_directions(directions: Float[ArrayLike, "... 3"], normal: Float[ArrayLike, "3"]) -> Float[Array, "... 3"]:
    """Directions mirrored in a plane with unit `normal` (d - 2 (d . n) n)."""
    d = jnp.asarray(directions)
    n = jnp.reshape(jnp.asarray(normal, d.dtype), (1,) * (d.ndim - 1) + (3,))
    return d - 2.0 * jnp.sum(d * n, -1, keepdims=True) * n


def mirror_mesh(vertices: Float[ArrayLike, "V 3"], normals: Float[ArrayLike, "V 3"], triangles: Int[ArrayLike, "T 3"],
                point: Float[ArrayLike, "3"], normal: Float[ArrayLike, "3"]
                ) -> tuple[Float[Array, "V 3"], Float[Array, "V 3"], Int[Array, "T 3"]]:
    """The mesh mirrored in the plane: vertices and normals reflected, and every triangle's
    winding reversed (a reflection flips orientation), so it faces the way the original did."""
    v = reflect_points(vertices, point, normal)
    n = reflect_directions(normals, normal)
    t = jnp.asarray(triangles)
    return v, n, t[:, ::-1]


def fresnel_schlick(cos_theta: Float[ArrayLike, "..."], f0: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """Schlick's approximation of the Fresnel reflectance at incidence cos(theta) (clamped to
    [0, 1]) for normal-incidence reflectance `f0` (0.04 for a varnish or wax of index ~1.5)."""
    c = jnp.clip(jnp.asarray(cos_theta), 0.0, 1.0)
    f0 = jnp.asarray(f0, c.dtype)
    return f0 + (1.0 - f0) * (1.0 - c) ** 5


def glossy_blur_pixels(roughness: Float[ArrayLike, "..."], beyond: Float[ArrayLike, "..."],
                       to_floor: Float[ArrayLike, "..."], focal_px: float) -> Float[Array, "..."]:
    """Width in pixels of the reflected cone (module docstring): focal roughness b / (t + b);
    0 for a perfect mirror, growing with the reflected surface's distance beyond the floor."""
    b = jnp.asarray(beyond)
    t = jnp.asarray(to_floor, b.dtype)
    return focal_px * jnp.asarray(roughness, b.dtype) * b / jnp.maximum(t + b, 1e-12)


def glossy_reflection(reflected: Float[Array, "H W 3"], blur_px: Float[Array, "H W"], cos_theta: Float[Array, "H W"], *,
                      f0: Float[ArrayLike, ""] = 0.04, levels: int = 6) -> Float[Array, "H W 3"]:
    """The floor's reflection at every pixel: `reflected` (the radiance of the mirrored scene
    at each pixel) blurred over `blur_px` pixels (mip level log2(blur), `levels` levels), times
    the Fresnel reflectance at incidence `cos_theta`."""
    h, w = reflected.shape[0], reflected.shape[1]
    dtype = reflected.dtype
    pyramid = mip_pyramid(reflected, levels=levels)
    rows, cols = jnp.meshgrid((jnp.arange(h, dtype=dtype) + 0.5) / h, (jnp.arange(w, dtype=dtype) + 0.5) / w,
                              indexing="ij")
    level = jnp.log2(jnp.maximum(blur_px, 1.0))
    blurred = trilinear(pyramid, jnp.stack([cols, rows], -1), level)
    return fresnel_schlick(cos_theta, f0)[..., None] * blurred

"""Pinhole camera: primary rays and projection. Image row 0 is at the top."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .maths import normalize, outer


def look_at_frame(eye: Float[ArrayLike, "3"], target: Float[ArrayLike, "3"], up: Float[ArrayLike, "3"]
                  ) -> tuple[Float[Array, "3"], Float[Array, "3"], Float[Array, "3"]]:
    """(x, y, z) of Mitsuba 3's look-at frame: z toward target, x = normalize(up x z), y = z x x."""
    z = normalize(jnp.asarray(target) - jnp.asarray(eye))
    x = normalize(jnp.cross(jnp.asarray(up), z))
    y = jnp.cross(z, x)
    return x, y, z


class Camera(eqx.Module):
    """Perspective pinhole camera. `fov_y_deg` is the full vertical field of view."""

    eye: Float[Array, "3"]
    target: Float[Array, "3"]
    up: Float[Array, "3"]
    fov_y_deg: Float[Array, ""]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __init__(self, eye, target, up=(0.0, 1.0, 0.0), fov_y_deg=40.0, *, width: int, height: int):
        self.eye = jnp.asarray(eye, dtype=float)
        self.target = jnp.asarray(target, dtype=float)
        self.up = jnp.asarray(up, dtype=float)
        self.fov_y_deg = jnp.asarray(fov_y_deg, dtype=float)
        self.width = int(width)
        self.height = int(height)

    def frame(self) -> tuple[Float[Array, "3"], Float[Array, "3"], Float[Array, "3"]]:
        """(right, up, forward) in world space; `right` is the image's +column direction, which is
        minus the look-at x axis (Mitsuba's perspective sensor mirrors camera-space x)."""
        x, y, z = look_at_frame(self.eye, self.target, self.up)
        return -x, y, z

    @property
    def tan_half_fov(self) -> Float[Array, ""]:
        return jnp.tan(jnp.deg2rad(self.fov_y_deg) / 2)

    def ray_direction(self, pixel: Float[ArrayLike, "... 2"]) -> Float[Array, "... 3"]:
        """Unit direction through continuous pixel coordinates (column, row); (0.5, 0.5) is the
        centre of the top-left pixel."""
        right, up, forward = self.frame()
        pixel = jnp.asarray(pixel)
        aspect = self.width / self.height
        sx = (2.0 * pixel[..., 0] / self.width - 1.0) * self.tan_half_fov * aspect
        sy = (1.0 - 2.0 * pixel[..., 1] / self.height) * self.tan_half_fov
        return normalize(outer(jnp.ones_like(sx), forward) + outer(sx, right) + outer(sy, up))

    def pixel_centers(self, *, supersample: int = 1) -> Float[Array, "H W S 2"]:
        """Pixel sample positions: the centre, or an s x s stratified grid per pixel."""
        offsets = (jnp.arange(supersample, dtype=float) + 0.5) / supersample
        oy, ox = jnp.meshgrid(offsets, offsets, indexing="ij")
        sub = jnp.stack([ox.ravel(), oy.ravel()], axis=-1)
        rows, cols = jnp.meshgrid(jnp.arange(self.height, dtype=float), jnp.arange(self.width, dtype=float),
                                  indexing="ij")
        base = jnp.stack([cols, rows], axis=-1)
        return base[:, :, None, :] + sub[None, None, :, :]

    def primary_rays(self) -> Float[Array, "H W 3"]:
        """Unit directions through every pixel centre (origins are all `eye`)."""
        return self.ray_direction(self.pixel_centers()[:, :, 0, :])

    def project(self, points: Float[ArrayLike, "... 3"]) -> tuple[Float[Array, "... 2"], Float[Array, "..."]]:
        """Continuous pixel coordinates (column, row) and depth along the view axis."""
        right, up, forward = self.frame()
        rel = jnp.asarray(points)
        rel = rel - jnp.broadcast_to(self.eye, rel.shape)
        depth = rel @ forward
        safe_depth = jnp.where(jnp.abs(depth) > 1e-12, depth, 1e-12)
        aspect = self.width / self.height
        sx = (rel @ right) / safe_depth / (self.tan_half_fov * aspect)
        sy = (rel @ up) / safe_depth / self.tan_half_fov
        col = (sx + 1.0) * 0.5 * self.width
        row = (1.0 - sy) * 0.5 * self.height
        return jnp.stack([col, row], axis=-1), depth

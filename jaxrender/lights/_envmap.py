"""Lat-long HDR environment maps in Mitsuba 3's `envmap` orientation (checked against Mitsuba),
importance sampled by luminance x sin(theta) with an exact solid-angle pdf. The orientation, the
pdf and the two reconstruction filters: docs/rendering.md.
"""

from __future__ import annotations

import os

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

from ..io import InputError, luminance, read_image
from ..maths import normalize

__all__ = ["EnvMap", "EnvSamples", "envmap_uv", "envmap_direction", "load_envmap", "env_radiance",
           "env_pdf", "sample_envmap", "env_texel_solid_angles"]

def envmap_uv(direction: Float[ArrayLike, "... 3"]) -> Float[Array, "... 2"]:
    """Mitsuba `envmap` (u, v) of a world direction (normalised here)."""
    d = normalize(jnp.asarray(direction))
    u = jnp.arctan2(d[..., 0], -d[..., 2]) / (2 * jnp.pi)
    u = u - jnp.floor(u)
    v = jnp.arccos(jnp.clip(d[..., 1], -1.0, 1.0)) / jnp.pi
    return jnp.stack([u, v], axis=-1)


def envmap_direction(uv: Float[ArrayLike, "... 2"]) -> Float[Array, "... 3"]:
    """The unit world direction of a Mitsuba `envmap` (u, v)."""
    uv = jnp.asarray(uv)
    theta, phi = jnp.pi * uv[..., 1], 2 * jnp.pi * uv[..., 0]
    st = jnp.sin(theta)
    return jnp.stack([st * jnp.sin(phi), jnp.cos(theta), -st * jnp.cos(phi)], axis=-1)


def env_texel_solid_angles(height: int, width: int, *, dtype=jnp.float32) -> Float[Array, " H"]:
    """Exact solid angle of one texel in each row of an H x W lat-long map."""
    j = jnp.arange(height + 1, dtype=dtype)
    c = jnp.cos(jnp.pi * j / height)
    return (2 * jnp.pi / width) * (c[:-1] - c[1:])


class EnvMap(eqx.Module):
    """A lat-long environment (linear RGB radiance) with its sampling tables.

    Build with `EnvMap.from_array(radiance)` or `load_envmap(path)`.
    """

    radiance: Float[Array, "H W 3"]
    cdf: Float[Array, " N"]          # cumulative texel probabilities (row-major), last = 1
    pdf_scale: Float[Array, ""]     # pdf(d) = luminance(texel) * pdf_scale (or uniform)
    uniform: Int[Array, ""]         # 1 when the map is black: sample the sphere uniformly

    @staticmethod
    def from_array(radiance: Float[ArrayLike, "H W 3"], *, scale: float = 1.0) -> "EnvMap":
        rad = jnp.asarray(radiance) * scale
        if rad.ndim != 3 or rad.shape[-1] != 3 or rad.shape[0] < 1 or rad.shape[1] < 1:
            raise ValueError(f"environment radiance must be H x W x 3, got {rad.shape}")
        h, w = rad.shape[0], rad.shape[1]
        lum = jnp.maximum(luminance(rad), 0.0)
        omega = env_texel_solid_angles(h, w, dtype=rad.dtype)
        weights = (lum * omega[:, None]).reshape(-1)
        total = jnp.sum(weights)
        black = total <= 0
        n = weights.shape[0]
        fallback = jnp.broadcast_to(omega[:, None], (h, w)).reshape(-1)
        weights = jnp.where(black, fallback, weights)
        cdf = jnp.cumsum(weights) / jnp.sum(weights)
        cdf = cdf.at[n - 1].set(1.0)
        pdf_scale = jnp.where(black, 1.0 / (4 * jnp.pi), 1.0 / jnp.where(black, 1.0, total))
        return EnvMap(rad, cdf, pdf_scale, black.astype(jnp.int32))


def load_envmap(path: str | os.PathLike, *, scale: float = 1.0) -> EnvMap:
    """Read a lat-long HDR map (EXR, linear; PNG is sRGB-decoded) in Mitsuba's orientation.

    Raises `InputError` naming the file for an unreadable file, a wrong shape, or non-finite or
    negative radiance.
    """
    img = np.asarray(read_image(path))
    if img.ndim == 2:
        img = img[..., None]
    if img.shape[-1] == 1:
        img = np.repeat(img, 3, axis=-1)
    if img.ndim != 3 or img.shape[-1] < 3 or img.shape[0] < 2 or img.shape[1] < 2:
        raise InputError(path, f"environment map must be an H x W RGB image, got shape {img.shape}")
    img = img[..., :3]
    if not np.all(np.isfinite(img)):
        raise InputError(path, "environment map contains NaN or infinite values")
    if np.any(img < 0):
        raise InputError(path, "environment map contains negative radiance")
    return EnvMap.from_array(jnp.asarray(img, dtype=jnp.float32), scale=scale)


def _texel_index(env: EnvMap, uv: Array) -> tuple[Array, Array]:
    h, w = env.radiance.shape[0], env.radiance.shape[1]
    i = jnp.clip(jnp.floor(uv[..., 0] * w).astype(jnp.int32), 0, w - 1)
    j = jnp.clip(jnp.floor(uv[..., 1] * h).astype(jnp.int32), 0, h - 1)
    return j, i


def env_radiance(env: EnvMap, direction: Float[ArrayLike, "... 3"], *,
                 filter: str = "nearest") -> Float[Array, "... 3"]:
    """Radiance arriving from `direction` (pointing away from the scene, toward the sky).

    `nearest`: the piecewise-constant map that is sampled and lit with. `mitsuba`: Mitsuba 3's
    bilinear reconstruction (for backgrounds; equal to Mitsuba's `eval`).
    """
    uv = envmap_uv(direction)
    rad = env.radiance
    if filter == "nearest":
        j, i = _texel_index(env, uv)
        return rad[j, i]
    if filter == "mitsuba":
        h, w = rad.shape[0], rad.shape[1]
        x = uv[..., 0] * w - 0.5
        y = uv[..., 1] * (h - 1)
        x0, y0 = jnp.floor(x), jnp.floor(y)
        fx, fy = (x - x0)[..., None], (y - y0)[..., None]
        xa = jnp.mod(x0.astype(jnp.int32), w)
        xb = jnp.mod(xa + 1, w)
        ya = jnp.clip(y0.astype(jnp.int32), 0, h - 1)
        yb = jnp.clip(ya + 1, 0, h - 1)
        top = rad[ya, xa] * (1 - fx) + rad[ya, xb] * fx
        bottom = rad[yb, xa] * (1 - fx) + rad[yb, xb] * fx
        return top * (1 - fy) + bottom * fy
    raise ValueError(f"unknown filter {filter!r}: use 'nearest' or 'mitsuba'")


def env_pdf(env: EnvMap, direction: Float[ArrayLike, "... 3"]) -> Float[Array, "..."]:
    """Solid-angle pdf (1/sr) with which `sample_envmap` draws `direction`."""
    j, i = _texel_index(env, envmap_uv(direction))
    lum = jnp.maximum(luminance(env.radiance[j, i]), 0.0)
    return jnp.where(env.uniform > 0, env.pdf_scale, lum * env.pdf_scale)


class EnvSamples(eqx.Module):
    """K light directions drawn from an environment: direction (world, toward the sky), the
    radiance arriving from it and its solid-angle pdf."""

    direction: Float[Array, "K 3"]
    radiance: Float[Array, "K 3"]
    pdf: Float[Array, " K"]


def sample_envmap(env: EnvMap, key: PRNGKeyArray, k: int = 20) -> EnvSamples:
    """Draw `k` directions by luminance x sin(theta); see the module docstring for the pdf."""
    h, w = env.radiance.shape[0], env.radiance.shape[1]
    dtype = env.radiance.dtype
    xi = jax.random.uniform(key, (k, 3), dtype=dtype)
    index = jnp.searchsorted(env.cdf, xi[:, 0], side="right")
    index = jnp.clip(index, 0, h * w - 1)
    j, i = index // w, index % w
    jf, i_f = j.astype(dtype), i.astype(dtype)
    phi = 2 * jnp.pi * (i_f + xi[:, 1]) / w
    c0, c1 = jnp.cos(jnp.pi * jf / h), jnp.cos(jnp.pi * (jf + 1) / h)
    cos_t = c0 + xi[:, 2] * (c1 - c0)
    sin_t = jnp.sqrt(jnp.maximum(1 - cos_t * cos_t, 0.0))
    d = jnp.stack([sin_t * jnp.sin(phi), cos_t, -sin_t * jnp.cos(phi)], axis=-1)
    rad = env.radiance[j, i]
    lum = jnp.maximum(luminance(rad), 0.0)
    pdf = jnp.where(env.uniform > 0, env.pdf_scale, lum * env.pdf_scale)
    return EnvSamples(d, rad, pdf)

"""Texture lookup, mip pyramids and N-bit quantization: the one sampler of the toolkit.

Convention (design.md): u runs along a texture's columns (u = 0 at the left edge of column 0),
v along its rows (v = 0 at the top edge of row 0); texel centres sit at (i + 1/2) / size.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

__all__ = ["bilinear", "nearest", "mip_pyramid", "trilinear", "quantize", "downsample2"]


def _wrap_index(i: Array, n: int, wrap: str) -> Array:
    if wrap == "clamp":
        return jnp.clip(i, 0, n - 1)
    if wrap == "repeat":
        return jnp.mod(i, n)
    raise ValueError(f"unknown wrap mode {wrap!r}: use 'clamp' or 'repeat'")


def bilinear(texture: Float[Array, "H W C"], uv: Float[ArrayLike, "... 2"], *,
             wrap: str = "clamp") -> Float[Array, "... C"]:
    """Bilinear lookup at continuous texture coordinates; differentiable in `texture` and `uv`."""
    texture = jnp.asarray(texture)
    uv = jnp.asarray(uv)
    h, w = texture.shape[0], texture.shape[1]
    x = uv[..., 0] * w - 0.5
    y = uv[..., 1] * h - 0.5
    x0 = jnp.floor(x)
    y0 = jnp.floor(y)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    x0 = x0.astype(jnp.int32)
    y0 = y0.astype(jnp.int32)
    xa, xb = _wrap_index(x0, w, wrap), _wrap_index(x0 + 1, w, wrap)
    ya, yb = _wrap_index(y0, h, wrap), _wrap_index(y0 + 1, h, wrap)
    top = texture[ya, xa] * (1 - fx) + texture[ya, xb] * fx
    bottom = texture[yb, xa] * (1 - fx) + texture[yb, xb] * fx
    return top * (1 - fy) + bottom * fy


def nearest(texture: Float[Array, "H W C"], uv: Float[ArrayLike, "... 2"], *,
            wrap: str = "clamp") -> Float[Array, "... C"]:
    """Nearest-texel lookup (e.g. shadow-map depths, which must not be blended)."""
    texture = jnp.asarray(texture)
    uv = jnp.asarray(uv)
    h, w = texture.shape[0], texture.shape[1]
    x = _wrap_index(jnp.floor(uv[..., 0] * w).astype(jnp.int32), w, wrap)
    y = _wrap_index(jnp.floor(uv[..., 1] * h).astype(jnp.int32), h, wrap)
    return texture[y, x]


def downsample2(texture: Float[Array, "H W C"]) -> Float[Array, "h w C"]:
    """Box-filter to ceil(H/2) x ceil(W/2); an odd last row/column is averaged with its copy."""
    h, w = texture.shape[0], texture.shape[1]
    pad = ((0, h % 2), (0, w % 2)) + ((0, 0),) * (texture.ndim - 2)
    t = jnp.pad(texture, pad, mode="edge")
    return 0.25 * (t[0::2, 0::2] + t[1::2, 0::2] + t[0::2, 1::2] + t[1::2, 1::2])


def mip_pyramid(texture: Float[Array, "H W C"], *, levels: int | None = None) -> tuple[Float[Array, "h w C"], ...]:
    """Level 0 is `texture`; level l+1 is `downsample2` of level l, down to 1x1 (or `levels`)."""
    pyramid = [jnp.asarray(texture)]
    while (levels is None and max(pyramid[-1].shape[:2]) > 1) or (levels is not None and len(pyramid) < levels):
        pyramid.append(downsample2(pyramid[-1]))
    return tuple(pyramid)


def trilinear(pyramid: tuple[Float[Array, "h w C"], ...], uv: Float[ArrayLike, "... 2"],
              level: Float[ArrayLike, "..."], *, wrap: str = "clamp") -> Float[Array, "... C"]:
    """Bilinear in each level, linear between the two levels around the continuous `level`."""
    level = jnp.clip(jnp.asarray(level), 0.0, len(pyramid) - 1.0)
    out = 0.0
    for index, texture in enumerate(pyramid):  # a handful of levels: unrolled, not a per-pixel loop
        weight = jnp.maximum(0.0, 1.0 - jnp.abs(level - index))[..., None]
        out = out + weight * bilinear(texture, uv, wrap=wrap)
    return out


@jax.custom_jvp
def _round_ste(x: Array) -> Array:
    return jnp.round(x)


@_round_ste.defjvp
def _round_ste_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    return jnp.round(x), dx  # straight-through: rounding passes gradients unchanged


def quantize(x: Float[ArrayLike, "..."], bits: int, *, scale: Float[ArrayLike, "..."] = 1.0) -> Float[Array, "..."]:
    """Round `x` to the nearest of 2^bits - 1 steps of `scale / (2^bits - 1)`, clamped to [0, scale].

    `bits = 0` means no quantization. The gradient is straight-through: d quantize / dx = 1 inside
    [0, scale] (the clamp still zeroes it outside), so inverse problems see the unquantized slope.
    """
    x = jnp.asarray(x)
    if bits == 0:
        return x
    levels = float(2**bits - 1)
    scale = jnp.asarray(scale, dtype=x.dtype)
    safe_scale = jnp.where(scale > 0, scale, 1.0)
    steps = _round_ste(jnp.clip(x / safe_scale, 0.0, 1.0) * levels)
    return jnp.where(scale > 0, steps / levels * safe_scale, 0.0)

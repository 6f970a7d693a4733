"""Texture lookup, mip pyramids and N-bit quantization: the one sampler of the toolkit.

Convention (design.md): u runs along a texture's columns (u = 0 at the left edge of column 0),
v along its rows (v = 0 at the top edge of row 0); texel centres sit at (i + 1/2) / size.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

__all__ = ["bilinear", "nearest", "mip_pyramid", "trilinear", "quantize", "downsample2", "PackedMips", "pack_mips"]


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
    """Box-filter to ceil(H/2) x ceil(W/2); an odd last row/column is averaged with its copy.
    A numpy array is filtered in numpy (no compilation for each new shape: a pyramid's levels)."""
    xp = np if isinstance(texture, np.ndarray) else jnp
    h, w = texture.shape[0], texture.shape[1]
    pad = ((0, h % 2), (0, w % 2)) + ((0, 0),) * (texture.ndim - 2)
    t = xp.pad(texture, pad, mode="edge")
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


class PackedMips(eqx.Module):
    """A square power-of-two mip pyramid with every level's texels in one array, for
    nearest-texel fetches at a level chosen per lookup (`pack_mips`).

    Level l has side `side >> l` (level `levels - 1` is 1 x 1); its texel (row, col) is
    `texels[offset(l) + row * (side >> l) + col]`. A texture whose channels are all equal (a gray
    light map) keeps one channel (C = 1): one scalar gather per fetch instead of a gather of
    C-vectors, which costs XLA's CPU backend 2-3x as much (and 3 scalar gathers more still)."""

    texels: Float[Array, "T C"]
    side: int = eqx.field(static=True)
    levels: int = eqx.field(static=True)

    @property
    def channels(self) -> int:
        return self.texels.shape[1]

    def fetch(self, index: Array) -> Array:
        """The texels at `index`: (..., C), C = 1 for a gray pyramid."""
        if self.channels == 1:
            return self.texels.reshape((-1,))[index][..., None]
        return self.texels[index]

    def offset(self, level: Array) -> Array:
        """Index of level `level`'s first texel: the sum of the finer levels' sizes (a table of
        `levels` entries: XLA's CPU backend has no vector integer division)."""
        sizes = [(self.side >> k) ** 2 for k in range(self.levels)]
        table = jnp.asarray([sum(sizes[:k]) for k in range(self.levels)], dtype=jnp.int32)
        return table[level]

    def index(self, u: Array, v: Array, level: Array, base: Array | None = None) -> Array:
        """Flat index of the texel holding (u, v) (clamped) at integer `level`; `base` =
        `offset(level)` when the caller has it already (e.g. one level per ray, many lookups)."""
        n = jnp.right_shift(jnp.int32(self.side), level)
        nf = n.astype(jnp.asarray(u).dtype)
        col = jnp.clip(jnp.floor(u * nf).astype(jnp.int32), 0, n - 1)
        row = jnp.clip(jnp.floor(v * nf).astype(jnp.int32), 0, n - 1)
        return (self.offset(level) if base is None else base) + row * n + col

    def level_for(self, footprint: Array) -> Array:
        """The finest level whose texels are no larger than `footprint` (in level-0 texels): the
        lookup is never blurrier than the footprint asks (int32, clamped to the pyramid)."""
        # floor(log2) is the exponent field of the float (>= 1: normal, positive): a log is a scalar
        # libm call on XLA's CPU backend, computed again in each gather's fusion
        x = jnp.maximum(jax.lax.stop_gradient(jnp.asarray(footprint)), 1.0)
        if x.dtype == jnp.float64:
            exponent = (jax.lax.bitcast_convert_type(x, jnp.int64) >> 52) - 1023
        else:
            exponent = (jax.lax.bitcast_convert_type(x.astype(jnp.float32), jnp.int32) >> 23) - 127
        return jnp.minimum(exponent.astype(jnp.int32), self.levels - 1)


def pack_mips(texture: Float[ArrayLike, "H W C"], *, min_side: int = 512) -> PackedMips:
    """The mip pyramid of `texture` packed for `PackedMips`. Level 0 is the texture itself when it
    is square with a power-of-two side of at least `min_side`; otherwise the bilinear (clamped)
    reconstruction of it sampled on the smallest such grid, so that a nearest fetch where the
    texture is magnified reads its bilinear value (to half a fine texel). Coarser levels are 2 x 2
    box averages (`downsample2`). Built once (when a light is made), not per frame. Channels
    all equal: one channel is kept (`PackedMips`); a traced texture keeps them all."""
    texture = jnp.asarray(texture)
    try:
        gray = bool(jnp.all(texture == texture[..., :1]))
    except jax.errors.ConcretizationTypeError:
        gray = False
    h, w = texture.shape[0], texture.shape[1]
    side = 1 << max(int(max(h, w, min_side)) - 1, 0).bit_length()
    if (h, w) != (side, side):
        c = (jnp.arange(side, dtype=texture.dtype) + 0.5) / side
        v, u = jnp.meshgrid(c, c, indexing="ij")
        texture = bilinear(texture, jnp.stack([u, v], axis=-1), wrap="clamp")
    pyramid = mip_pyramid(texture)
    flat = jnp.concatenate([level.reshape((-1, level.shape[-1])) for level in pyramid], axis=0)
    if gray:
        flat = flat[:, :1]
    return PackedMips(texels=flat, side=side, levels=len(pyramid))


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

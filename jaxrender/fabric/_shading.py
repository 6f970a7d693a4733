"""Shading woven fabric with multi-resolution BTFs (paper 004, eqs. 1-4 and section 4.4).

BTF pyramids: each material is a list of levels (`BTFTexel` H_l x W_l, 1 or 2 lobes per texel,
e.g. `fitting.pyramid` EM levels or `jaxrender.io.read_btf` levels). `MaterialSet` packs the
levels of all materials into one flat texel table with per-(level, material) offsets and sizes,
so a pixel's texel is one gather whatever its material, level or the materials' sizes (a
material with fewer levels repeats its coarsest one).

Mip level (per pixel, from the UV derivatives of neighbouring pixels as the paper's fragment
shader): rho = max(|d(uv)/dx * (W, H)|, |d(uv)/dy * (W, H)|) in level-0 texels per pixel and
lambda = log2(rho), clamped to [0, L - 1].

Level blending: texels are looked up with nearest filtering inside a level (BTF texels are
per-texel parameter sets; interpolating them mixes lobes of different directions) and the
SHADING RESULTS of levels floor(lambda) and floor(lambda) + 1 are blended linearly, never the
parameters: blending the parameters of a two-lobe level with another level would merge lobes
that EM kept apart (`blend="nearest"` instead uses the nearest level only, half the cost).

Shading (eqs. 2-4): with light samples (direction wi_k, radiance L_k, pdf p_k, visibility V_k)
the reflected radiance toward wo is
    I = sum_k R(wi_k, wo) / pi * L_k V_k / (K p_k),
R the toolkit's one BRDF in its observed-reflectance form (`jaxrender.brdf.reflectance`,
R / pi = f cos(theta_i)), evaluated in the surface's tangent frame: x = the direction of
increasing u, y = the direction of decreasing v (rows grow downward), z = the shading normal.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ..brdf import BTFTexel, lobe_reflectance, reflectance
from ..maths import dot, normalize

__all__ = ["MaterialSet", "stack_materials", "mip_level", "lookup_texels", "shade_samples", "shade_single_lobe",
           "shade_fabric", "tangent_frames"]


class MaterialSet(eqx.Module):
    """All levels of all materials in one flat table (see the module docstring)."""

    table: BTFTexel                 # N texels
    offsets: Int[Array, "L M"]      # first texel of level l of material m
    sizes: Int[Array, "L M 2"]      # (rows, cols) of level l of material m
    levels: Int[Array, " M"]        # number of real levels of material m

    @property
    def count(self) -> int:
        return self.offsets.shape[1]


def _flat(t: BTFTexel) -> BTFTexel:
    return jax.tree_util.tree_map(lambda a: jnp.reshape(a, (-1,) + a.shape[2:]), t)


def stack_materials(pyramids: list[list[BTFTexel]]) -> MaterialSet:
    """Pack `pyramids[m][l]` (BTFTexel H_l x W_l) into a `MaterialSet`."""
    if not pyramids or any(len(p) == 0 for p in pyramids):
        raise ValueError("every material needs at least one level")
    n_levels = max(len(p) for p in pyramids)
    parts, offsets, sizes = ([], np.zeros((n_levels, len(pyramids)), np.int32),
                             np.zeros((n_levels, len(pyramids), 2), np.int32))
    start = 0
    first = {}
    for m, pyr in enumerate(pyramids):
        for l, level in enumerate(pyr):
            h, w = level.weight.shape
            first[(m, l)] = (start, h, w)
            parts.append(_flat(level))
            start += h * w
        for l in range(n_levels):
            s, h, w = first[(m, min(l, len(pyr) - 1))]
            offsets[l, m], sizes[l, m] = s, (h, w)
    table = jax.tree_util.tree_map(lambda *a: jnp.concatenate(a, axis=0), *parts)
    return MaterialSet(table, jnp.asarray(offsets), jnp.asarray(sizes),
                       jnp.asarray([len(p) for p in pyramids], dtype=jnp.int32))


def mip_level(duv_dx: Float[ArrayLike, "... 2"], duv_dy: Float[ArrayLike, "... 2"],
              size: Float[ArrayLike, "... 2"]) -> Float[Array, "..."]:
    """Continuous mip level lambda = log2(max texel footprint of one pixel step), unclamped
    (negative when magnified). `size` = (rows, cols) of level 0, uv = (column, row) coordinates."""
    duv_dx, duv_dy, size = jnp.asarray(duv_dx), jnp.asarray(duv_dy), jnp.asarray(size)
    scale = jnp.stack([size[..., 1], size[..., 0]], axis=-1).astype(duv_dx.dtype)
    ax = jnp.sum((duv_dx * scale) ** 2, axis=-1)
    ay = jnp.sum((duv_dy * scale) ** 2, axis=-1)
    rho2 = jnp.maximum(jnp.maximum(ax, ay), 1e-12)
    return 0.5 * jnp.log2(rho2)


def lookup_texels(mats: MaterialSet, material: Int[Array, " N"], uv: Float[Array, "N 2"],
                  level: Int[Array, " N"]) -> BTFTexel:
    """Nearest texel (repeat wrap) of integer `level` of each pixel's material."""
    level = jnp.clip(level, 0, mats.offsets.shape[0] - 1)
    off = mats.offsets[level, material]
    hw = mats.sizes[level, material]
    frac = uv - jnp.floor(uv)
    hwf = hw.astype(uv.dtype)
    col = jnp.clip(jnp.floor(frac[:, 0] * hwf[:, 1]).astype(jnp.int32), 0, hw[:, 1] - 1)
    row = jnp.clip(jnp.floor(frac[:, 1] * hwf[:, 0]).astype(jnp.int32), 0, hw[:, 0] - 1)
    index = off + row * hw[:, 1] + col
    return jax.tree_util.tree_map(lambda a: a[index], mats.table)


def tangent_frames(normal: Float[Array, "N 3"], dpdu: Float[Array, "N 3"]) -> Float[Array, "N 3 3"]:
    """Rows (x, y, z) of the tangent frame: x = dP/du made orthogonal to the normal, z = normal."""
    n = normalize(normal)
    t = dpdu - dot(dpdu, n)[:, None] * n
    fallback = jnp.where(jnp.abs(n[:, 0:1]) < 0.9, jnp.asarray([[1.0, 0.0, 0.0]], dtype=n.dtype),
                         jnp.asarray([[0.0, 1.0, 0.0]], dtype=n.dtype))
    fallback = fallback - dot(fallback, n)[:, None] * n
    t = normalize(jnp.where(dot(t, t)[:, None] > 1e-16, t, fallback))
    b = jnp.cross(n, t)
    return jnp.stack([t, b, n], axis=1)


def _local_dirs(frame: Array, wo: Array, wi: Array) -> tuple[Array, Array]:
    """wo (N 1 3) and wi (N K 3) in the tangent frames; component form (XLA CPU is slow on tiny
    contractions over a minor axis of 3)."""
    wo_l = jnp.stack([sum(frame[:, r, c] * wo[:, c] for c in range(3)) for r in range(3)], -1)[:, None, :]
    wi_l = jnp.stack([sum(frame[:, r, c][:, None] * wi[:, :, c] for c in range(3)) for r in range(3)], -1)
    return wo_l, wi_l


def shade_samples(texel: BTFTexel, frame: Float[Array, "N 3 3"], wo: Float[Array, "N 3"],
                  wi: Float[Array, "N K 3"], weight: Float[Array, "N K 3"]) -> Float[Array, "N 3"]:
    """sum_k R(wi_k, wo) / pi * weight_k (weight = L V / (K p)); directions in world space."""
    wo_l, wi_l = _local_dirs(frame, wo, wi)
    t = jax.tree_util.tree_map(lambda a: a[:, None], texel)
    r = reflectance(t, wi_l, wo_l)
    return jnp.sum(r * weight, axis=1) / jnp.pi


def shade_single_lobe(texel: BTFTexel, frame: Float[Array, "N 3 3"], wo: Float[Array, "N 3"],
                      wi: Float[Array, "N K 3"], weight: Float[Array, "N K 3"]) -> Float[Array, "N 3"]:
    """`shade_samples` for texels known to have one lobe (weight 0): the same R of
    `jaxrender.brdf` (rho_d cos_i to lobe 0's normal + `lobe_reflectance` of lobe 0) without
    evaluating the unused second lobe."""
    wo_l, wi_l = _local_dirs(frame, wo, wi)
    lobe = jax.tree_util.tree_map(lambda a: a[:, None], texel.lobe0)
    n0 = normalize(lobe.normal)
    cos_i = jnp.maximum(dot(wi_l, n0), 0.0)
    r = texel.rho_d[:, None, :] * cos_i[..., None] + lobe_reflectance(lobe, wi_l, wo_l)
    geometric = (wi_l[..., 2] > 0) & (wo_l[..., 2] > 0)
    return jnp.sum(jnp.where(geometric[..., None], r, 0.0) * weight, axis=1) / jnp.pi


def shade_fabric(mats: MaterialSet, material: Int[Array, " N"], uv: Float[Array, "N 2"],
                 duv_dx: Float[Array, "N 2"], duv_dy: Float[Array, "N 2"], frame: Float[Array, "N 3 3"],
                 wo: Float[Array, "N 3"], wi: Float[Array, "N K 3"], weight: Float[Array, "N K 3"], *,
                 diffuse_override: Float[Array, "N 3"] | None = None, use_override: Float[Array, " N"] | None = None,
                 blend: str = "shading") -> Float[Array, "N 3"]:
    """Radiance toward `wo` of fabric pixels lit by K samples; mip level from the uv derivatives.

    `diffuse_override` / `use_override` (1 = use): the plain pattern colour replacing rho_d.
    """
    size0 = mats.sizes[0, material]
    lam = mip_level(duv_dx, duv_dy, size0)
    top = (mats.levels[material] - 1).astype(lam.dtype)
    lam = jnp.clip(lam, 0.0, top)
    l0 = jnp.floor(lam)
    frac = lam - l0

    def at(level):
        texel = lookup_texels(mats, material, uv, level.astype(jnp.int32))
        if diffuse_override is not None:
            use = use_override[:, None] > 0.5
            texel = eqx.tree_at(lambda t: t.rho_d, texel, jnp.where(use, diffuse_override, texel.rho_d))
        return shade_samples(texel, frame, wo, wi, weight)

    if blend == "nearest":
        return at(jnp.round(lam))
    if blend != "shading":
        raise ValueError(f"unknown blend {blend!r}: use 'shading' or 'nearest'")
    a = at(l0)
    b = at(jnp.minimum(l0 + 1, top))
    return a * (1 - frac)[:, None] + b * frac[:, None]

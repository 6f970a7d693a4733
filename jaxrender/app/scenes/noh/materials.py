"""The garment's materials: procedural level-0 BTFs of the four weaves and their EM pyramids
(`fitting.pyramid_levels`), or levels read from BTF directories."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PRNGKeyArray

from fitting import pyramid_levels, synth_maps
from jaxrender.brdf import BTFTexel
from jaxrender.maths import default_float

from .mask import LABELS


def procedural_btf(kind: str, size: int = 32, *, key: PRNGKeyArray | None = None) -> BTFTexel:
    """A one-lobe level-0 BTF `size x size` of a woven structure.

    `brocade`: `fitting.synth.synth_maps` (silk ground with gold weft floats); `hexagon`: a
    tortoise-shell hexagon weave (threads circling each cell: normals tilt away from the cell
    centre, anisotropy along the rim); `satin`: long warp floats (narrow highlights across them);
    `pattern`: a plain weave of white silk (rho_d replaced by the mask colour when rendering);
    `painted`: a smooth matte surface with a faint sheen (the mask's gofun, skin, tabi; rho_d from
    the body page's colour); `hair`: dark fibres along v, a highlight across them.
    """
    dtype = default_float()
    key = jax.random.key(0) if key is None else key
    if kind == "brocade":
        t = synth_maps(key, (size, size))
        # a warmer, gold-dominated brocade: make the silk ground a deep red
        gold = t.lobe0.rho_s[..., 0] > 1.0
        red = jnp.asarray([[[0.35, 0.03, 0.03]]], dtype=dtype)
        rho_d = jnp.where(gold[..., None], t.rho_d,
                          red * (t.rho_d[..., :1] / jnp.maximum(jnp.mean(t.rho_d[..., :1]), 1e-6)))
        return BTFTexel.single(rho_d.astype(dtype), t.lobe0.rho_s.astype(dtype), t.lobe0.normal.astype(dtype),
                               t.lobe0.sigma_x.astype(dtype), t.lobe0.sigma_y.astype(dtype))
    y, x = np.meshgrid((np.arange(size) + 0.5) / size, (np.arange(size) + 0.5) / size, indexing="ij")
    if kind == "hexagon":
        cells = 2.0
        # hexagonal lattice: nearest centre among two offset rectangular lattices
        sx, sy = x * cells, y * cells * math.sqrt(3) / 1.0
        a = np.stack([np.round(sx), np.round(sy / math.sqrt(3)) * math.sqrt(3)], -1)
        b = np.stack([np.floor(sx) + 0.5, (np.floor(sy / math.sqrt(3)) + 0.5) * math.sqrt(3)], -1)
        p = np.stack([sx, sy], -1)
        c = np.where((np.sum((p - a) ** 2, -1) < np.sum((p - b) ** 2, -1))[..., None], a, b)
        d = p - c
        r = np.hypot(d[..., 0], d[..., 1])
        rim = np.clip((r - 0.25) / 0.3, 0, 1)
        tilt = 0.6 * rim
        nx, ny = tilt * d[..., 0] / np.maximum(r, 1e-6), -tilt * d[..., 1] / np.maximum(r, 1e-6)
        normal = np.stack([nx, ny, np.ones_like(nx)], -1)
        rho_d = np.where((rim > 0.5)[..., None], [0.05, 0.22, 0.12], [0.02, 0.10, 0.08])
        rho_s = np.where((rim > 0.5)[..., None], [0.5, 0.55, 0.45], [0.25, 0.3, 0.25])
        sigma_x = np.where(rim > 0.5, 0.12, 0.3)
        sigma_y = np.where(rim > 0.5, 0.3, 0.12)
    elif kind == "satin":
        floats = 8
        a = (x * floats) % 1.0 * 2 - 1
        normal = np.stack([0.5 * a, 0.05 * np.sin(2 * np.pi * (y * 4 + np.floor(x * floats) * 0.37)), np.ones_like(a)],
                          -1)
        rho_d = np.broadcast_to(np.asarray([0.18, 0.35, 0.5]), x.shape + (3,)) * (1 - 0.3 * a[..., None] ** 4)
        rho_s = np.broadcast_to(np.asarray([0.7, 0.75, 0.8]), x.shape + (3,))
        sigma_x, sigma_y = np.full(x.shape, 0.25), np.full(x.shape, 0.06)
    elif kind == "pattern":
        p = max(2, size // 8)
        i, j = np.floor(y * size).astype(int) // p, np.floor(x * size).astype(int) // p
        warp_up = (i + j) % 2 == 0
        a = ((x * size) % p + 0.5 - 0.5) / p * 2 - 1
        b = ((y * size) % p + 0.5 - 0.5) / p * 2 - 1
        normal = np.stack([np.where(warp_up, 0.5 * a, 0.2 * a), np.where(warp_up, -0.2 * b, -0.5 * b), np.ones_like(a)],
                          -1)
        rho_d = np.broadcast_to(np.asarray([0.7, 0.7, 0.7]), x.shape + (3,)).copy()
        rho_s = np.broadcast_to(np.asarray([0.3, 0.3, 0.3]), x.shape + (3,))
        sigma_x = np.where(warp_up, 0.3, 0.12)
        sigma_y = np.where(warp_up, 0.12, 0.3)
    elif kind == "painted":
        normal = np.stack([np.zeros_like(x), np.zeros_like(x), np.ones_like(x)], -1)
        rho_d = np.ones(x.shape + (3,))
        rho_s = np.full(x.shape + (3,), 0.04)
        sigma_x = sigma_y = np.full(x.shape, 0.3)
    elif kind == "hair":
        wave = 0.25 * np.sin(2 * np.pi * x * 8)
        normal = np.stack([wave, np.zeros_like(x), np.ones_like(x)], -1)
        rho_d = np.broadcast_to(np.asarray([0.012, 0.010, 0.010]), x.shape + (3,))
        rho_s = np.full(x.shape + (3,), 0.25)
        sigma_x, sigma_y = np.full(x.shape, 0.35), np.full(x.shape, 0.06)
    else:
        raise ValueError(f"unknown BTF kind {kind!r}: use one of {LABELS}")
    normal = normal / np.linalg.norm(normal, axis=-1, keepdims=True)
    arr = lambda z: jnp.asarray(np.ascontiguousarray(z), dtype=dtype)  # noqa: E731
    return BTFTexel.single(arr(rho_d), arr(rho_s), arr(normal), arr(sigma_x), arr(sigma_y))


def btf_levels_from_channels(levels: list[dict]) -> list[BTFTexel]:
    """BTFTexel levels from `jaxrender.io.read_btf`'s channel dicts."""
    dtype = default_float()
    return [jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=dtype), BTFTexel.from_channels(c)) for c in levels]


def default_btfs(*, size: int = 32, pyramid: str = "em", key: PRNGKeyArray | None = None) -> dict[str, list[BTFTexel]]:
    """Level pyramids for every label from `procedural_btf`; `pyramid`: `em` (2-lobe EM levels,
    `fitting.pyramid.pyramid_levels`) or `none` (level 0 only)."""
    key = jax.random.key(0) if key is None else key
    out = {}
    for i, name in enumerate(LABELS):
        level0 = procedural_btf(name, size, key=jax.random.fold_in(key, i))
        levels = [level0]
        if pyramid == "em":
            levels += list(pyramid_levels(level0)[0])
        elif pyramid != "none":
            raise ValueError(f"unknown pyramid {pyramid!r}: use 'em' or 'none'")
        out[name] = levels
    return out

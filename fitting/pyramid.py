"""The EM multi-resolution pyramid of a BTF directory (paper 004, section 3.2).

Level l+1 (ceil-half size, odd sizes edge-padded as `jaxrender.textures.downsample2`) is built
from level l texel by texel with `fitting.em.em_downsample` (a large level 0 in bands of rows,
`banded_downsample`, so memory does not grow with it): up to two anisotropic lobes per
texel, `rho_d` averaged. `pyramid_channels` gives the levels of an in-memory level 0 (a fit writes
them with level 0, `btf.json` last); `build_pyramid` rebuilds them in a BTF directory through
`jaxrender.io.write_btf_levels`, which keeps level 0, writes `level_01.exr`, ... and rewrites
`btf.json` last, holding the directory's lock.
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array, Float

from jaxrender.brdf import BTFTexel
from jaxrender.io import MASK_CHANNEL, InputError, output_lock, read_btf, write_btf_levels
from jaxrender.textures import downsample2

from .em import DEFAULT_ITERATIONS, DEFAULT_ORDER, ONE_LOBE_TOLERANCE, TWO_LOBE_GAIN, compile_ahead, em_downsample

__all__ = ["build_pyramid", "pyramid_channels", "pyramid_levels", "pyramid_sizes", "banded_downsample",
           "masked_average", "compile_pyramid_ahead", "BAND_TEXELS", "EM_CHUNK"]

EM_CHUNK = 4096      # texels per EM kernel call (`em_downsample(..., fixed=True)`)
BAND_TEXELS = 65536  # output texels per band of a large one-lobe level (16 EM chunks of 4096)


def pyramid_sizes(size: tuple[int, int], *, levels: int | None = None) -> list[tuple[int, int]]:
    """Sizes of levels 0, 1, ... (ceil halving) down to 1x1, or the first `levels` of them."""
    sizes = [(int(size[0]), int(size[1]))]
    while (levels is None and max(sizes[-1]) > 1) or (levels is not None and len(sizes) < levels):
        sizes.append((math.ceil(sizes[-1][0] / 2), math.ceil(sizes[-1][1] / 2)))
    return sizes


def banded_downsample(level: BTFTexel, *, order: int = DEFAULT_ORDER, iterations: int = DEFAULT_ITERATIONS,
                      chunk: int = EM_CHUNK, band_texels: int = BAND_TEXELS, fixed: bool = False):
    """`em_downsample` of a large one-lobe level (a fit's level 0) in bands of output rows: the
    EM's buffers then grow with a band, not with the level (measured: ~0.7 kB per level-0 texel
    in one piece). Each band holds whole EM chunks of `chunk` texels at the same flat positions as
    in one piece (bands start at multiples of `chunk` output texels; the last band takes the rest),
    so every texel meets the same kernel call: the level is bit-identical to `em_downsample`'s.
    Levels with a second lobe somewhere, small levels, and widths that allow no such bands are
    downsampled in one piece (`em_downsample` picks its kernel from the whole level)."""
    level = jax.tree.map(np.asarray, level)   # cut and joined in numpy (`em_downsample` splits in numpy)
    h, w = level.weight.shape
    hh, ww = -(-h // 2), -(-w // 2)
    step = chunk // math.gcd(chunk, ww)   # output rows of a whole number of chunks
    rows = max(step, band_texels // ww // step * step)
    if hh < 2 * rows or bool(np.any(level.weight)):
        return em_downsample(level, order=order, iterations=iterations, chunk=chunk, fixed=fixed)
    starts = list(range(0, hh - rows + 1, rows))   # the last band runs to the end (rows .. 2 rows - 1)
    outs, infos = [], []
    for i, a in enumerate(starts):
        b = hh if i == len(starts) - 1 else a + rows
        band = jax.tree.map(lambda x: x[2 * a:min(2 * b, h)], level)
        out, info = em_downsample(band, order=order, iterations=iterations, chunk=chunk, fixed=fixed)
        jax.block_until_ready((out, info))   # one band's buffers at a time
        outs.append(out)
        infos.append(info)
    return (jax.tree.map(lambda *xs: np.concatenate(xs, axis=0), *outs),
            jax.tree.map(lambda *xs: np.concatenate(xs, axis=0), *infos))


def masked_average(coarse: BTFTexel, mask: Float[Array, "H W"]) -> tuple[BTFTexel, Float[Array, "h w"]]:
    """(`coarse` as the average over its children inside `mask` only, the coarse mask), in numpy
    (every level has its own shape: compiled, each would be compiled once more).

    Texels outside a capture's mask hold rho = 0, so a coarse texel's rho_d (the children's mean)
    and its lobes' rho_s (the children's energy / 4) are those of its inside children times the
    inside fraction f (`downsample2` of the mask, same padding): divided by f they are the inside
    children's own; the lobes' shape is unchanged (outside children carry no energy)."""
    coarse = jax.tree.map(np.asarray, coarse)
    mask = np.asarray(mask, coarse.rho_d.dtype)
    frac = downsample2(mask[..., None])[..., 0]
    inside = frac > 0
    scale = np.where(inside, 1 / np.where(inside, frac, 1), 0).astype(mask.dtype)[..., None]
    scaled = eqx.tree_at(lambda t: (t.rho_d, t.lobe0.rho_s, t.lobe1.rho_s), coarse,
                         (coarse.rho_d * scale, coarse.lobe0.rho_s * scale, coarse.lobe1.rho_s * scale))
    return scaled, inside.astype(mask.dtype)


def compile_pyramid_ahead() -> threading.Thread:
    """Start compiling the EM kernels of `pyramid_channels` (float32 levels, default order and
    iterations) in the background (`fitting.em.compile_ahead`): a fit calls it before fitting."""
    return compile_ahead(order=DEFAULT_ORDER, iterations=DEFAULT_ITERATIONS, chunk=EM_CHUNK, dtype=np.float32)


def pyramid_levels(level0: BTFTexel, *, levels: int | None = None, order: int = DEFAULT_ORDER,
                   iterations: int = DEFAULT_ITERATIONS, progress: Callable[[int], object] | None = None,
                   mask: Float[Array, "H W"] | None = None) -> tuple[list[BTFTexel], list[dict]]:
    """Levels 1, 2, ... of an `H W` BTFTexel (level 0 not included) and per-level statistics; with
    a `mask` (1 fitted, 0 not) every coarse texel averages its inside children only (`masked_average`)
    and each level's statistics carry its mask as `mask` (an `h w` array)."""
    count = len(pyramid_sizes(level0.weight.shape, levels=levels))
    out, infos, masks = [], [], []
    current = level0
    for _ in range(1, count):  # a handful of levels: each one is a vmapped kernel call
        current, info = banded_downsample(current, order=order, iterations=iterations, chunk=EM_CHUNK, fixed=True)
        if mask is not None:
            current, mask = masked_average(current, mask)
            masks.append(mask)
        out.append(current)
        infos.append(info)
        if progress is not None:
            progress(1)
    summary = _level_summary(infos)
    stats = [{"size": list(level.weight.shape), "two_lobe_fraction": float(two),
              "max_iterations": int(iterations), "converged_fraction": float(converged)}
             for level, (two, iterations, converged) in zip(out, summary)]
    for stat, level_mask in zip(stats, masks):
        stat["mask"] = np.asarray(level_mask, np.float32)
    return out, stats


def _level_summary(infos) -> np.ndarray:
    """Per level: fraction of two-lobe texels, most EM iterations, fraction converged (`L 3`)."""
    return np.array([[np.mean(np.asarray(info.two_lobes), dtype=np.float64), np.max(np.asarray(info.iterations)),
                      np.mean(np.asarray(info.converged), dtype=np.float64)] for info in infos]).reshape(-1, 3)


def pyramid_channels(level0: dict[str, np.ndarray], *, levels: int | None = None, order: int = DEFAULT_ORDER,
                     iterations: int = DEFAULT_ITERATIONS, progress: Callable[[int], object] | None = None,
                     ) -> tuple[list[dict[str, np.ndarray]], dict]:
    """(levels 1, 2, ... as BTF channel dicts, btf.json's `pyramid` entry) of level 0's channels
    (every lobe channel and the mask, as `jaxrender.io.complete_level` gives them): a masked level 0
    gives masked levels (`masked_average`). See `build_pyramid`."""
    texel = BTFTexel.from_channels(level0)
    if not np.all(np.isfinite(np.asarray(texel.weight))):
        raise ValueError("non-finite weight channel in level 0")
    mask = level0.get(MASK_CHANNEL)
    coarse, stats = pyramid_levels(texel, levels=levels, order=order, iterations=iterations, progress=progress,
                                   mask=None if mask is None or np.all(mask > 0) else mask)
    channels = [{name: np.asarray(v, dtype=np.float32) for name, v in t.to_channels().items()} for t in coarse]
    for level, stat in zip(channels, stats):
        if "mask" in stat:
            level[MASK_CHANNEL] = stat.pop("mask")
    meta = {"pyramid": {"method": "em", "order": order, "iterations": iterations,
                        "one_lobe_tolerance": ONE_LOBE_TOLERANCE, "two_lobe_gain": TWO_LOBE_GAIN,
                        "levels": stats}}
    return channels, meta


def build_pyramid(btf_dir: str | os.PathLike, *, levels: int | None = None, order: int = DEFAULT_ORDER,
                  iterations: int = DEFAULT_ITERATIONS, progress: Callable[[int], object] | None = None) -> Path:
    """Rebuild levels 1.. of the BTF directory `btf_dir` from its level 0 by EM; returns the directory.

    `levels` is the total number of levels afterwards, level 0 included (default: down to 1x1);
    existing coarser levels are replaced. `progress(1)` is called after each level (e.g. a tqdm
    bar's `update`). `btf.json` is rewritten last with a `pyramid` entry (method and per-level
    statistics); raises InputError for an incomplete or malformed directory, `OutputBusy` when
    another process writes it.
    """
    btf_dir = Path(btf_dir)
    if levels is not None and levels < 1:
        raise InputError(btf_dir, f"levels must be >= 1, got {levels}")
    _, existing = read_btf(btf_dir)
    if not np.all(np.isfinite(existing[0]["weight"])):
        raise InputError(btf_dir / "level_00.exr", "non-finite weight channel")
    with output_lock(btf_dir):
        channels, meta = pyramid_channels(existing[0], levels=levels, order=order, iterations=iterations,
                                          progress=progress)
        return write_btf_levels(btf_dir, channels, start=1, meta=meta)

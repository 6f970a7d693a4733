"""Fit every texel of a capture: chunks of texels, split over the local devices, checkpointed, resumable.

The machinery of both paths: observations in memory (`fit_maps`, `fit_observations`) and the
observation store fitted tile by tile (`fitting.tiles`: `fit_store`, `fit_capture`). Every texel
is fitted with `fitting.lm.fit_texels` in chunks of `chunk` texels (each chunk split over all
local JAX devices, each device fitting its share in tiles whose size does not depend on the device
count: the maps are bit-identical on 1 or N devices), and `write_fit` writes the BTF directory:
level 0 through `jaxrender.io.write_btf` (`btf.json` last), PNG previews, then the EM pyramid
(`fitting.pyramid.build_pyramid`, which rewrites `btf.json` last).

Finished chunks are checkpointed in `BTF_DIR/.partial/` (one `.npz` per chunk, each written
atomically, plus `config.json` naming the capture and settings). Rerunning on the same output
resumes: chunks already there are loaded, the others fitted. Every chunk is fitted with the same
padded shape whatever happened before, so a run killed with SIGKILL and resumed gives maps
bit-identical to an uninterrupted one. `.partial/` is removed once the BTF is complete, with the
temporaries a killed run left behind.

A robust fit (`METHODS`, the default) first estimates the capture's materials from a sample of its
texels (`fit_materials`, `fitting.materials`; saved in `.partial/materials.json`): each texel's lobe
then gets the prior of its material, and robust geometry rounds and an appearance round follow
(`fitting.lm.fit_texel`). Reasoning: docs/fitting.md, "Real captures: the robust method".
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import json
import os
import shutil
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import jax
import numpy as np

from jaxrender.io import (
    InputError,
    atomic_path,
    complete_level,
    output_lock,
    remove_temporaries,
    write_btf,
    write_btf_previews,
)

from .checkpoint import Checkpoint, fingerprint
from .hdr import ObservationCounts, Observations
from .lm import DEFAULT_MAX_STEPS, DEFAULT_SOLVER, SOLVERS, MaterialTable, TexelFit, default_tolerances, fit_texels
from .materials import estimate_materials, no_materials, sample_indices
from .pyramid import pyramid_channels

__all__ = ["fit_observations", "fit_maps", "ChunkPlan", "plan_chunks", "read_chunk", "read_texels", "fit_chunk",
           "empty_fit", "run_chunks", "fit_in_process", "assemble_maps", "observation_summary", "level0_channels",
           "write_fit", "begin_output", "check_settings", "progress_bar", "fit_materials", "table_to_numpy",
           "table_from_numpy", "DEFAULT_CHUNK", "TILE", "PARTIAL", "MIN_VALID", "METHODS", "DEFAULT_METHOD"]

DEFAULT_CHUNK = 4096
# texels per vmapped solve: the solver loop runs until the slowest texel of a tile is done; small tiles stay in cache
TILE = 32
PARTIAL = ".partial"
MIN_VALID = 4  # lights a texel needs for a determined fit (4 nonlinear + 2 linear parameters per channel)
# "robust" (default, every capture): materials shared by the texels (`fitting.materials`, one global
# pass over a sample) give each texel's lobe a prior; ROBUST_ROUNDS reweighted geometry solves and
# an appearance solve per texel (`fitting.lm.fit_texel`). "plain": per-texel least squares (paper 004).
METHODS = ("robust", "plain")
DEFAULT_METHOD = "robust"
ROBUST_ROUNDS = 2
MATERIAL_MIN_VALID = 8  # valid lights a sampled texel needs to take part in the material pass
_METHOD_TEXT = {"robust": "levenberg-marquardt, variable projection of rho_d, rho_s; material priors, "
                          "robust geometry rounds with an ambient term, appearance round",
                "plain": "levenberg-marquardt, variable projection of rho_d, rho_s"}


def _layout(chunk: int, n_devices: int) -> tuple[int, int]:
    """(tile, texels per device) of a chunk: every device fits whole tiles of `tile` texels.

    The tile size depends on the chunk only, never on the device count, so each texel is fitted
    by the same compiled tile program (same vector shapes, same rounding) on 1 or N devices.
    """
    tile = min(TILE, chunk)
    per_device = -(-chunk // (n_devices * tile)) * tile
    return tile, per_device


@functools.lru_cache(maxsize=None)
def _tile_fit(tile: int, model: str, solver: str, max_steps: int):
    """One device's share: `lax.map` over tiles of `tile` texels, each one vmapped solve.

    Every device runs this same program on a contiguous share of the chunk (inputs committed to
    the device; JAX dispatches asynchronously, so the devices work at once). A texel keeps its
    place in a tile of the same size on 1 or N devices and meets the same compiled program, so
    the maps are bit-identical whatever the device count. (Partitioning one program over a mesh
    rounds differently per device count; `vmap` over a device axis batches the solver loop a
    second time, 5-10x slower on CPU; `jax.shard_map`/`pmap` meet lineax's structure checks.)
    """

    def fn(ratio, weight, light_dirs, view_dir, materials):
        out = jax.lax.map(lambda rw: fit_texels(rw[0], rw[1], light_dirs, view_dir, model=model, solver=solver,
                                                max_steps=max_steps, materials=materials,
                                                robust_rounds=ROBUST_ROUNDS if materials is not None else 0),
                          (ratio, weight))
        return jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:]), out)

    return jax.jit(fn)


def _chunk_fit(ratio, weight, light_dirs, view_dir, *, tile, model, solver, max_steps,
               materials: MaterialTable | None = None) -> TexelFit:
    """Fit `n_devices * per_device` texels (already padded) over the local devices; flat numpy leaves.
    `materials`: the robust method's table (None: the plain method).

    Float32 observations are fitted by a float32 program even where a notebook or test switched on
    x64 (optimistix's damping constants would otherwise turn into float64 and its structure check fails)."""
    devices = jax.local_devices()
    fn = _tile_fit(tile, model, solver, max_steps)
    per_device = ratio.shape[0] // len(devices)
    dtype = np.asarray(ratio).dtype
    outs = []
    with jax.enable_x64(dtype == np.float64):
        for d, dev in enumerate(devices):   # dispatched asynchronously: the devices run at once
            share = slice(d * per_device, (d + 1) * per_device)
            place = jax.sharding.SingleDeviceSharding(dev)
            r = jax.device_put(ratio[share].reshape((-1, tile) + ratio.shape[1:]), place)
            w = jax.device_put(weight[share].reshape((-1, tile) + weight.shape[1:]), place)
            dirs = jax.device_put(np.asarray(light_dirs, dtype), place)
            view = jax.device_put(np.asarray(view_dir, dtype), place)
            table = None if materials is None else jax.device_put(
                jax.tree.map(lambda x: np.asarray(x, dtype), materials), place)
            outs.append(fn(r, w, dirs, view, table))
    return jax.tree.map(lambda *shares: np.concatenate([np.asarray(x) for x in shares]), *outs)


@dataclasses.dataclass(frozen=True)
class ChunkPlan:
    """The work units of a fit of `size` texels: the texels to fit, `texels` (flat row-major
    indices, ascending: every texel, or a mask's), taken `chunk` at a time; chunk i is
    `texels[starts[i] : starts[i] + counts[i]]`, fitted padded to `padded` texels in tiles of `tile`.

    Every chunk has the same padded shape (one compilation), the last one padded with its last
    texel: the same units whether the observations are in memory or in a store, fitted here or on
    a Dask worker, so a texel always meets the same compiled program."""

    size: tuple[int, int]
    texels: np.ndarray = dataclasses.field(repr=False)
    starts: tuple[int, ...]
    counts: tuple[int, ...]
    tile: int
    padded: int

    def chunk_texels(self, index: int) -> np.ndarray:
        return self.texels[self.starts[index]:self.starts[index] + self.counts[index]]

    @property
    def n_fitted(self) -> int:
        return int(self.texels.size)


def plan_chunks(size: tuple[int, int], chunk: int, mask: np.ndarray | None = None) -> ChunkPlan:
    """The chunks of the texels of `size` inside `mask` (`H W` bool; None: all) for this process's
    local devices."""
    total = size[0] * size[1]
    texels = np.arange(total) if mask is None else np.flatnonzero(np.asarray(mask, bool).reshape(-1))
    n = max(int(texels.size), 1)
    tile, per_device = _layout(min(chunk, n), jax.local_device_count())
    starts = tuple(range(0, texels.size, chunk))
    return ChunkPlan(tuple(size), texels, starts, tuple(min(chunk, texels.size - s) for s in starts), tile,
                     per_device * jax.local_device_count())


def read_texels(read: Callable[[int, int], tuple[np.ndarray, np.ndarray]], texels: np.ndarray,
                window: int) -> tuple[np.ndarray, np.ndarray]:
    """(ratio, weight) of the ascending flat indices `texels` through `read(start, count)` of
    contiguous ranges, at most `window` texels read at a time (a sparse mask never reads a whole
    image at once)."""
    if texels[-1] - texels[0] + 1 == texels.size:
        return read(int(texels[0]), int(texels.size))
    ratios, weights, i = [], [], 0
    while i < texels.size:
        start = int(texels[i])
        j = int(np.searchsorted(texels, start + window))
        ratio, weight = read(start, int(texels[j - 1]) - start + 1)
        ratios.append(ratio[texels[i:j] - start])
        weights.append(weight[texels[i:j] - start])
        i = j
    return np.concatenate(ratios), np.concatenate(weights)


def read_chunk(read: Callable[[int, int], tuple[np.ndarray, np.ndarray]], plan: ChunkPlan,
               index: int) -> tuple[np.ndarray, np.ndarray]:
    """(ratio `n L 3`, weight `n L`) of chunk `index`'s texels; `read(start, count)` gives those of a
    contiguous range of texels."""
    return read_texels(read, plan.chunk_texels(index), window=max(plan.padded, 1))


def fit_chunk(ratio: np.ndarray, weight: np.ndarray, plan: ChunkPlan, index: int, light_dirs, view_dir, *,
              model: str, solver: str, max_steps: int, materials: MaterialTable | None = None) -> TexelFit:
    """Fit chunk `index` of `plan` from its observations (`read_chunk`); a `TexelFit` of flat numpy
    leaves (the chunk's texels). `materials`: the robust method's table (None: plain)."""
    count = plan.counts[index]
    if count != plan.padded:
        idx = np.minimum(np.arange(plan.padded), count - 1)  # pad with the last texel
        ratio, weight = ratio[idx], weight[idx]
    out = _chunk_fit(ratio, weight, light_dirs, view_dir, tile=plan.tile, model=model, solver=solver,
                     max_steps=max_steps, materials=materials)
    return jax.tree.map(lambda v: v[:count], out)


def empty_fit(n: int) -> TexelFit:
    """The fit of `n` texels outside a capture's mask: nothing reflected (rho 0), normal +z."""
    zeros = np.zeros(n, np.float32)
    return TexelFit(rho_d=np.zeros((n, 3), np.float32), rho_s=np.zeros((n, 3), np.float32),
                    normal=np.tile(np.float32([0.0, 0.0, 1.0]), (n, 1)), sigma_x=zeros + np.float32(0.1),
                    sigma_y=zeros + np.float32(0.1), residual=zeros, cost=zeros, converged=np.zeros(n, bool),
                    num_steps=np.zeros(n, np.int32), n_valid=np.zeros(n, np.int32),
                    material=np.full(n, -1, np.int32))


def check_settings(solver: str, chunk: int, max_steps: int, method: str = DEFAULT_METHOD) -> None:
    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}: use one of {SOLVERS}")
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}: use one of {METHODS}")
    if chunk < 1 or max_steps < 1:
        raise ValueError("chunk and max_steps must be >= 1")


def progress_bar(total: int, progress: bool | None):
    """tqdm bar of texels: done / total, rate and time left (None: on a terminal only)."""
    from tqdm.auto import tqdm

    return tqdm(total=total, unit="texel", desc="fit", disable=None if progress is None else not progress,
                smoothing=0.1)


def assemble_maps(results: list[TexelFit], plan: ChunkPlan) -> TexelFit:
    """Per-chunk flat fits (in `plan.texels` order) -> one `TexelFit` of `H W ...` maps (`empty_fit`
    outside the mask)."""
    total = plan.size[0] * plan.size[1]

    def place(empty, *chunks):
        out = np.array(empty, dtype=chunks[0].dtype) if chunks else np.asarray(empty)
        if chunks:
            out[plan.texels] = np.concatenate(chunks)
        return out.reshape(tuple(plan.size) + out.shape[1:])

    return jax.tree.map(place, empty_fit(total), *results)


def run_chunks(plan: ChunkPlan, checkpoint: Checkpoint | None,
               fit_todo: Callable[[list[int]], Iterable[tuple[int, TexelFit]]], *, progress: bool | None,
               on_chunk: Callable[[int], object] | None = None) -> TexelFit:
    """The resume loop of every path: chunks already in `checkpoint` are loaded, the others fitted by
    `fit_todo(indices)`, which yields (index, fit) as each is done (and saved); `H W` maps."""
    results = [checkpoint.load(i, count) if checkpoint is not None else None for i, count in enumerate(plan.counts)]
    todo = [i for i, r in enumerate(results) if r is None]
    bar = progress_bar(plan.n_fitted, progress)
    bar.update(plan.n_fitted - sum(plan.counts[i] for i in todo))
    try:
        for i, fit in fit_todo(todo):
            results[i] = fit
            bar.update(plan.counts[i])
            if on_chunk is not None:
                on_chunk(i)
    finally:
        bar.close()
    return assemble_maps(results, plan)


_TABLE_FIELDS = ("rho_s", "s", "log_share", "colour", "colour_spread", "noise")
MATERIALS_FILE = "materials.json"   # the robust fit's material table in the checkpoint directory


def table_to_numpy(table: MaterialTable) -> dict[str, np.ndarray]:
    """A material table as numpy arrays (saved in `.partial/`, sent to Dask workers)."""
    return {name: np.asarray(getattr(table, name)) for name in _TABLE_FIELDS}


def table_from_numpy(arrays) -> MaterialTable:
    return MaterialTable(*(jax.numpy.asarray(arrays[name]) for name in _TABLE_FIELDS))


def fit_materials(read: Callable[[int, int], tuple[np.ndarray, np.ndarray]], plan: ChunkPlan, n_valid: np.ndarray,
                  light_dirs, view_dir, *, solver: str, max_steps: int, model: str,
                  checkpoint: Checkpoint | None) -> tuple[MaterialTable, dict]:
    """The global pass of a robust fit: the material table of a sample of the plan's texels with
    at least MATERIAL_MIN_VALID valid observations (`fitting.materials`; the sample fitted by the
    tiles' compiled program, with a table of no priors). Saved in the checkpoint and reloaded from
    there on a resumed fit."""
    saved = checkpoint.directory / MATERIALS_FILE if checkpoint is not None else None
    if saved is not None and saved.is_file():
        try:
            data = json.loads(saved.read_text())
            return table_from_numpy({k: np.asarray(data["table"][k], np.float32) for k in _TABLE_FIELDS}), data["info"]
        except (OSError, ValueError, KeyError, TypeError):
            pass   # unreadable: estimate again
    flat = np.asarray(n_valid).reshape(-1)
    texels = sample_indices(plan.texels[flat[plan.texels] >= MATERIAL_MIN_VALID])
    if texels.size:
        ratio, weight = read_texels(read, texels, window=max(plan.padded, 1))
        n = int(texels.size)
        starts = tuple(range(0, n, plan.padded))
        sample = ChunkPlan((1, n), np.arange(n), starts, tuple(min(plan.padded, n - s) for s in starts), plan.tile,
                           plan.padded)
        parts = [fit_chunk(ratio[s:s + c], weight[s:s + c], sample, i, light_dirs, view_dir, model=model,
                           solver=solver, max_steps=max_steps, materials=no_materials())
                 for i, (s, c) in enumerate(zip(sample.starts, sample.counts))]
        fits = jax.tree.map(lambda *p: np.concatenate(p), *parts)
        table, info = estimate_materials(ratio, weight, light_dirs, view_dir, model=model, fits=fits)
    else:
        table, info = no_materials(), {"materials": 0, "sample": 0}
    if saved is not None:   # a few rows as JSON (float32 values round-trip exactly; -inf as -Infinity)
        table_json = {k: np.asarray(v, np.float32).tolist() for k, v in table_to_numpy(table).items()}
        with atomic_path(saved) as tmp:
            tmp.write_text(json.dumps({"table": table_json, "info": info}))
    return table, info


def fit_in_process(read: Callable[[int, int], tuple[np.ndarray, np.ndarray]], plan: ChunkPlan,
                   checkpoint: Checkpoint | None, light_dirs, view_dir, *, solver: str, max_steps: int, model: str,
                   prefetch: bool = False, materials: MaterialTable | None = None):
    """`fit_todo` of `run_chunks` for this process: each chunk read (the next one read by a thread
    meanwhile when `prefetch`), fitted and saved in turn."""

    def fit_todo(todo: list[int]):
        def load(i):
            return read_chunk(read, plan, i)

        reader = concurrent.futures.ThreadPoolExecutor(max_workers=1) if prefetch and todo else None
        try:
            future = reader.submit(load, todo[0]) if reader is not None else None
            for k, i in enumerate(todo):
                data = future.result() if reader is not None else load(i)
                if reader is not None and k + 1 < len(todo):
                    future = reader.submit(load, todo[k + 1])
                fit = fit_chunk(*data, plan, i, light_dirs, view_dir, model=model, solver=solver,
                                max_steps=max_steps, materials=materials)
                if checkpoint is not None:
                    checkpoint.save(i, fit)
                yield i, fit
        finally:
            if reader is not None:
                reader.shutdown(wait=True, cancel_futures=True)

    return fit_todo


def fit_maps(obs: Observations, *, solver: str = DEFAULT_SOLVER, chunk: int = DEFAULT_CHUNK,
             max_steps: int = DEFAULT_MAX_STEPS, model: str = "reciprocal",
             partial_dir: str | os.PathLike | None = None, progress: bool | None = None,
             on_chunk: Callable[[int], object] | None = None, method: str = DEFAULT_METHOD) -> TexelFit:
    """Fit every texel of `Observations`; a `TexelFit` of `H W ...` numpy maps.

    `method`: "robust" (default; materials shared by the texels, robust geometry and appearance
    rounds: `METHODS`) or "plain" (per-texel least squares).
    `partial_dir`: checkpoint finished chunks there and reuse the ones already present.
    `progress`: None = a tqdm bar on a terminal only, False = never, True = always.
    """
    return _fit_maps(obs, solver=solver, chunk=chunk, max_steps=max_steps, model=model, partial_dir=partial_dir,
                     progress=progress, on_chunk=on_chunk, method=method)[0]


def _fit_maps(obs: Observations, *, solver, chunk, max_steps, model, partial_dir, progress, on_chunk=None,
              method=DEFAULT_METHOD) -> tuple[TexelFit, dict]:
    """`fit_maps` and the material pass's info (empty for the plain method)."""
    check_settings(solver, chunk, max_steps, method)
    h, w = obs.size
    ratio = np.asarray(obs.ratio).reshape(h * w, obs.n_lights, 3)
    weight = np.asarray(obs.weight).reshape(h * w, obs.n_lights)
    settings = {"solver": solver, "chunk": chunk, "max_steps": max_steps, "model": model, "dtype": str(ratio.dtype),
                "method": method}
    mask = None if obs.mask is None else np.asarray(obs.mask, bool)
    checkpoint = None
    if partial_dir is not None:  # the inputs' identity: directions, the first light of every texel, the mask
        checkpoint = Checkpoint(partial_dir).prepare(fingerprint(
            settings, np.asarray(obs.light_dirs), np.asarray(obs.view_dir), np.asarray(ratio[:, :1]), str(ratio.shape),
            np.ones((h, w), bool) if mask is None else mask))
    plan = plan_chunks((h, w), chunk, mask)

    def read(s, c):
        return ratio[s:s + c], weight[s:s + c]

    table, info = None, {}
    if method == "robust":
        table, info = fit_materials(read, plan, np.sum(weight > 0, axis=1), obs.light_dirs, obs.view_dir,
                                    solver=solver, max_steps=max_steps, model=model, checkpoint=checkpoint)
    fit_todo = fit_in_process(read, plan, checkpoint, obs.light_dirs, obs.view_dir, solver=solver,
                              max_steps=max_steps, model=model, materials=table)
    return run_chunks(plan, checkpoint, fit_todo, progress=progress, on_chunk=on_chunk), info


def observation_summary(counts: ObservationCounts, mask: np.ndarray | None, source) -> dict:
    """Texels with too few valid observations, counted (inside the mask); `InputError` naming the
    likely cause when most texels have none (a saturated or dark white board, a wrong exposure or
    response): a fit of nothing must not look like a BTF."""
    inside = np.ones(np.shape(counts.n_valid), bool) if mask is None else np.asarray(mask, bool)
    n_valid = np.asarray(counts.n_valid)[inside]
    n_texels = int(n_valid.size)
    none, few = int(np.sum(n_valid == 0)), int(np.sum(n_valid < MIN_VALID))
    summary = {"texels": n_texels, "texels_without_observations": none,
               f"texels_with_fewer_than_{MIN_VALID}_observations": few}
    if n_texels and none > 0.5 * n_texels:
        saturated = int(np.asarray(counts.n_saturated)[inside].sum())
        dark = int(np.asarray(counts.n_dark)[inside].sum())
        if saturated >= dark and saturated > 0:
            cause = "most observations are saturated (exposures too long, or an EXR capture clipped below its values?)"
        elif dark > 0:
            cause = "most observations are dark (exposures too short, or a wrong response?)"
        else:
            cause = ("the white board is saturated, dark or zero at these texels (is its exposure bracket right; "
                     "for EXR radiance give no saturation level below the board's values)")
        raise InputError(source, f"{none} of {n_texels} texels have no valid observation: {cause}")
    return summary


def level0_channels(maps: TexelFit, counts: ObservationCounts, mask: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """BTF level-0 channels (design.md names, and `mask`: 1 for fitted texels) of `fit_maps` output
    and the observation counts."""
    c: dict[str, np.ndarray] = {}
    for i, ch in enumerate("RGB"):
        c[f"rho_d.{ch}"] = maps.rho_d[..., i]
        c[f"rho_s.{ch}"] = maps.rho_s[..., i]
    for i, ax in enumerate("XYZ"):
        c[f"normal.{ax}"] = maps.normal[..., i]
    c["sigma_x"], c["sigma_y"] = maps.sigma_x, maps.sigma_y
    c["residual"] = maps.residual
    c["converged"] = np.asarray(maps.converged).astype(np.float32)
    c["n_valid"], c["n_saturated"], c["n_dark"] = counts.n_valid, counts.n_saturated, counts.n_dark
    c["mask"] = np.ones(np.shape(maps.sigma_x), np.float32) if mask is None else mask
    return {k: np.asarray(v, np.float32) for k, v in c.items()}


def begin_output(btf_dir: Path) -> None:
    """A fit starts writing `btf_dir` (its lock held): an older `btf.json` goes, so the directory is
    incomplete until this fit's last step, and so do the temporaries a killed run left."""
    (btf_dir / "btf.json").unlink(missing_ok=True)
    for directory in (btf_dir, btf_dir / "previews", btf_dir / PARTIAL):
        remove_temporaries(directory)


def write_fit(btf_dir: Path, maps: TexelFit, counts: ObservationCounts, *, solver: str, chunk: int, max_steps: int,
              model: str, pyramid: bool, seconds: float, cpu_seconds: float | None = None,
              meta: dict | None = None, mask: np.ndarray | None = None, method: str = DEFAULT_METHOD,
              materials: dict | None = None) -> Path:
    """Previews of level 0, then level 0 and the EM pyramid of fitted maps with `btf.json` last (it
    appears only once every level is written); removes `.partial/` and any temporaries."""
    level0 = level0_channels(maps, counts, mask)
    inside = np.ones(np.shape(maps.sigma_x), bool) if mask is None else np.asarray(mask, bool)
    rtol, atol = default_tolerances(np.float32)  # the fit always sees float32 observations
    info = {"fit": {"solver": solver, "method": _METHOD_TEXT[method],
                    "chunk": chunk, "max_steps": max_steps, "rtol": rtol, "atol": atol,
                    "devices": jax.local_device_count(),
                    "converged_fraction": float(np.mean(maps.converged[inside])) if inside.any() else 0.0,
                    "median_residual": float(np.median(maps.residual[inside])) if inside.any() else 0.0,
                    "median_steps": float(np.median(maps.num_steps[inside])) if inside.any() else 0.0,
                    "seconds": round(seconds, 3), "observations": observation_summary(counts, mask, btf_dir)}}
    if cpu_seconds is not None:  # this process's CPU time (robust to a shared machine's load)
        info["fit"]["cpu_seconds"] = round(cpu_seconds, 3)
    if materials:
        info["fit"]["materials"] = materials
    info.update(meta or {})
    with output_lock(btf_dir):
        write_btf_previews(btf_dir, level0)
        level0 = complete_level(level0, level0=True)
        levels = [level0]
        if pyramid:
            coarse, pyramid_meta = pyramid_channels(level0)
            levels += coarse
            info.update(pyramid_meta)
        write_btf(btf_dir, levels, model=model, meta=info)
        del levels, level0
        shutil.rmtree(btf_dir / PARTIAL, ignore_errors=True)
        for directory in (btf_dir, btf_dir / "previews"):
            remove_temporaries(directory)
    return btf_dir


def fit_observations(obs: Observations, btf_dir: str | os.PathLike, *, solver: str = DEFAULT_SOLVER,
                     chunk: int = DEFAULT_CHUNK, max_steps: int = DEFAULT_MAX_STEPS, model: str = "reciprocal",
                     pyramid: bool = True, progress: bool | None = None, meta: dict | None = None,
                     method: str = DEFAULT_METHOD) -> Path:
    """Fit in-memory `Observations` into the BTF directory `btf_dir` (checkpointed and resumable; its
    lock held throughout)."""
    btf_dir = Path(btf_dir)
    if np.asarray(obs.ratio).dtype != np.float32:
        raise ValueError("fit_observations fits float32 observations")
    mask = None if obs.mask is None else np.asarray(obs.mask, bool)
    observation_summary(obs.counts, mask, btf_dir)  # before any work: a fit of nothing is an error
    with output_lock(btf_dir):
        begin_output(btf_dir)
        t0, c0 = time.perf_counter(), time.process_time()
        maps, materials = _fit_maps(obs, solver=solver, chunk=chunk, max_steps=max_steps, model=model,
                                    partial_dir=btf_dir / PARTIAL, progress=progress, method=method)
        return write_fit(btf_dir, maps, obs.counts, solver=solver, chunk=chunk, max_steps=max_steps, model=model,
                         pyramid=pyramid, seconds=time.perf_counter() - t0, cpu_seconds=time.process_time() - c0,
                         meta=dict(meta or {}), mask=mask, method=method, materials=materials)

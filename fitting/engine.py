"""The chunk engine: every texel of a `TexelSource` fitted in chunks, split over the local devices,
checkpointed, resumable. Both paths drive it: observations in memory (`TexelSource.of_observations`,
`fitting.fit_maps`) and an observation store (`TexelSource.of_store`, `fitting.fit_store`), the
chunks fitted in this process or as Dask tasks (`fitting.cluster.DaskChunks`).

A chunk is `settings.chunk` texels (flat row-major indices inside the mask): the unit that is read
(`read(start, count)` of contiguous ranges), fitted (each device fitting its share in 32-texel
vmapped solves, `fitting.lm.fit_texels`) and checkpointed (`fitting.checkpoint`, one `.npz` each,
atomically). Every chunk is fitted with the same padded shape by the same compiled program
wherever and whenever it runs, so the maps are bit-identical on 1 or N devices, in memory or from
a float32 store, in one process or on a Dask cluster, uninterrupted or resumed after SIGKILL.

Every fit first measures the capture's level on a sample of its texels (`capture_level`): the
factor that brings their median RMS observation to `REFERENCE_RMS`. The solvers see the
observations times that factor and the maps are given back in the capture's units, so a fit does
not depend on the units of its capture (its damping start and tolerances are absolute numbers,
docs/fitting.md, "The capture's level"). A robust fit then estimates the capture's materials from
the same sample (`estimate_table`; saved beside the chunks as `materials.json`). The level and that
`MaterialTable` are the only global state, and every chunk gets both.

Memory: one chunk of observations being fitted and the next being read (`chunk` x L x 16 bytes)
plus the output maps (60 bytes per texel).
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import json
import os
from collections.abc import Callable, Iterable, Iterator
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from jaxrender.io import InputError, atomic_path

from .checkpoint import Checkpoint, fingerprint
from .hdr import ObservationCounts, Observations
from .lm import STEPPING, TexelFit, fit_texels
from .materials import MaterialTable, estimate_materials, no_materials
from .settings import FitSettings
from .store import ObservationStore

__all__ = ["TexelSource", "FitResult", "ChunkPlan", "plan_chunks", "read_chunk", "fit_chunk", "fit_source",
           "local_chunks", "estimate_table", "sample_indices", "sample_size", "empty_fit", "observation_summary",
           "TILE", "LANES_TILE", "MIN_VALID", "MATERIAL_MIN_VALID", "SAMPLE_OBSERVATIONS", "SAMPLE_TEXELS",
           "MATERIALS_FILE", "REFERENCE_RMS", "capture_level", "in_units"]

# texels per compiled tile program: every device runs whole tiles, so a texel meets the same program
# on 1 or N devices. A backend that steps solves a tile in lanes (`fitting.lanes`; a large tile keeps
# the lanes busy: their drain at its end costs ~1/30 of it); the others vmap a tile's solves, whose
# loop runs until its slowest texel is done (small tiles waste little and stay in cache).
TILE = 32
LANES_TILE = 2048
MIN_VALID = 4  # lights a texel needs for a determined fit (4 nonlinear + 2 linear parameters per channel)
MATERIAL_MIN_VALID = 8  # valid lights a sampled texel needs to take part in the material pass
# texels sampled for the material pass: as many observations whatever the light count (2048 texels
# at DiLiGenT's 96 lights), between 512 and 2048 texels
SAMPLE_OBSERVATIONS = 2048 * 96
SAMPLE_TEXELS = (512, 2048)
MATERIALS_FILE = "materials.json"   # the robust fit's material table in the checkpoint directory
# the median RMS observation of a texel that every capture is brought to before its solves: the
# level of the development captures (DiLiGenT's objects: 0.04-0.09), where the solvers' absolute
# damping start and tolerances were chosen (docs/fitting.md, "The capture's level")
REFERENCE_RMS = 0.05

Read = Callable[[int, int], tuple[np.ndarray, np.ndarray]]


@dataclasses.dataclass(frozen=True)
class TexelSource:
    """What the engine fits: `size` (H, W), the texels to fit (`mask`, H W bool; None: all), each
    texel's light counts (`counts`, H W maps), the light and view directions, `read(start, count)`
    -> (ratio `count L 3`, weight `count L`) of a contiguous range of flat texels, `name` (the
    file an input error names), `identity` (what a checkpoint's fingerprint covers besides the
    settings) and `store` (the observation store it reads, for Dask workers; None in memory)."""

    size: tuple[int, int]
    mask: np.ndarray | None
    counts: ObservationCounts
    light_dirs: np.ndarray
    view_dir: np.ndarray
    read: Read
    name: str
    identity: tuple
    store: ObservationStore | None = None

    @classmethod
    def of_observations(cls, obs: Observations, name: str | os.PathLike | None = None) -> "TexelSource":
        h, w = obs.size
        ratio = np.asarray(obs.ratio).reshape(h * w, obs.n_lights, 3)
        weight = np.asarray(obs.weight).reshape(h * w, obs.n_lights)
        mask = None if obs.mask is None else np.asarray(obs.mask, bool)
        dirs, view = np.asarray(obs.light_dirs), np.asarray(obs.view_dir)

        def read(start, count):
            return ratio[start:start + count], weight[start:start + count]

        # the inputs' identity: dtype, directions, the first light of every texel, the shape, the mask
        identity = (str(ratio.dtype), dirs, view, np.asarray(ratio[:, :1]), str(ratio.shape),
                    np.ones((h, w), bool) if mask is None else mask)
        return cls((h, w), mask, obs.counts, dirs, view, read, os.fspath(name or "observations"), identity)

    @classmethod
    def of_store(cls, store: ObservationStore) -> "TexelSource":
        return cls(tuple(store.size), store.mask(), store.counts(), store.light_dirs.astype(np.float32),
                   store.view_dir.astype(np.float32), store.read, os.fspath(store.info.get("capture") or store.path),
                   ("store", store.fingerprint), store)


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


def _layout(chunk: int, n_devices: int, tile: int) -> tuple[int, int]:
    """(tile, texels per device) of a chunk: every device fits whole tiles of `tile` texels.

    The tile size depends on the chunk and the backend only, never on the device count, so each
    texel is fitted by the same compiled tile program (same vector shapes, same rounding) on 1 or N
    devices.
    """
    tile = min(tile, chunk)
    per_device = -(-chunk // (n_devices * tile)) * tile
    return tile, per_device


def plan_chunks(size: tuple[int, int], settings: FitSettings, mask: np.ndarray | None = None) -> ChunkPlan:
    """The chunks of the texels of `size` inside `mask` (`H W` bool; None: all) for this process's
    local devices, `settings.chunk` texels each."""
    chunk = settings.chunk
    total = size[0] * size[1]
    texels = np.arange(total) if mask is None else np.flatnonzero(np.asarray(mask, bool).reshape(-1))
    n = max(int(texels.size), 1)
    tile, per_device = _layout(min(chunk, n), jax.local_device_count(),
                               LANES_TILE if settings.solver in STEPPING else TILE)
    starts = tuple(range(0, texels.size, chunk))
    return ChunkPlan(tuple(size), texels, starts, tuple(min(chunk, texels.size - s) for s in starts), tile,
                     per_device * jax.local_device_count())


def read_texels(read: Read, texels: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
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


def read_chunk(read: Read, plan: ChunkPlan, index: int) -> tuple[np.ndarray, np.ndarray]:
    """(ratio `n L 3`, weight `n L`) of chunk `index`'s texels."""
    return read_texels(read, plan.chunk_texels(index), window=max(plan.padded, 1))


@functools.lru_cache(maxsize=None)
def _tile_program(tile: int, settings: FitSettings):
    """One device's share: `lax.map` over tiles of `tile` texels (`fitting.lm.fit_texels` each).

    Every device runs this same program on a contiguous share of the chunk (inputs committed to
    the device; JAX dispatches asynchronously, so the devices work at once). A texel keeps its
    place in a tile of the same size on 1 or N devices and meets the same compiled program, so
    the maps are bit-identical whatever the device count. (Partitioning one program over a mesh
    rounds differently per device count; `vmap` over a device axis batches the solver loop a
    second time, 5-10x slower on CPU; `jax.shard_map`/`pmap` meet lineax's structure checks.)
    `active` (one count per tile): the tile's texels that are not padding; only those are solved
    (`fitting.lm.fit_texels`), and a tile of padding only is skipped.
    """

    def fn(ratio, weight, active, light_dirs, view_dir, materials):
        def fit(tile_data):
            r, w, n = tile_data
            return fit_texels(r, w, light_dirs, view_dir, settings, materials=materials, active=n)

        def skip(tile_data):   # a tile of padding only: nothing to fit
            return jax.tree_util.tree_map(lambda x: jnp.zeros(x.shape, x.dtype), jax.eval_shape(fit, tile_data))

        out = jax.lax.map(lambda tile_data: jax.lax.cond(tile_data[2] > 0, fit, skip, tile_data),
                          (ratio, weight, active))
        return jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:]), out)

    return jax.jit(fn)


def fit_chunk(ratio: np.ndarray, weight: np.ndarray, plan: ChunkPlan, index: int, light_dirs, view_dir,
              settings: FitSettings, table: MaterialTable | None, level: float = 1.0) -> TexelFit:
    """Fit chunk `index` of `plan` from its observations (`read_chunk`) over the local devices; a
    `TexelFit` of flat numpy leaves (the chunk's texels), in the observations' units. `table`: the
    robust method's materials; `level`: the capture's (`capture_level`), the factor the solvers see
    the observations multiplied by (the table is in those units).

    Float32 observations are fitted by a float32 program even where a notebook or test switched on
    x64 (optimistix's damping constants would otherwise turn into float64 and its structure check fails)."""
    count = plan.counts[index]
    ratio = np.asarray(ratio) * np.asarray(level, np.asarray(ratio).dtype)
    if count != plan.padded:
        idx = np.minimum(np.arange(plan.padded), count - 1)  # pad with the last texel
        ratio, weight = ratio[idx], weight[idx]
    devices = jax.local_devices()
    fn = _tile_program(plan.tile, settings.program())
    per_device = ratio.shape[0] // len(devices)
    dtype = np.asarray(ratio).dtype
    tile = plan.tile
    outs = []
    with jax.enable_x64(dtype == np.float64):
        for d, dev in enumerate(devices):   # dispatched asynchronously: the devices run at once
            share = slice(d * per_device, (d + 1) * per_device)
            place = jax.sharding.SingleDeviceSharding(dev)
            r = jax.device_put(ratio[share].reshape((-1, tile) + ratio.shape[1:]), place)
            w = jax.device_put(weight[share].reshape((-1, tile) + weight.shape[1:]), place)
            # the tiles' texels that are not padding (the last chunk's, or a material sample's)
            first = d * per_device + np.arange(0, per_device, tile)
            active = jax.device_put(np.clip(count - first, 0, tile).astype(np.int32), place)
            dirs = jax.device_put(np.asarray(light_dirs, dtype), place)
            view = jax.device_put(np.asarray(view_dir, dtype), place)
            materials = None if table is None else jax.device_put(jax.tree.map(
                lambda x: np.asarray(x, dtype) if np.issubdtype(np.asarray(x).dtype, np.floating) else np.asarray(x),
                table), place)
            outs.append(fn(r, w, active, dirs, view, materials))
    out = jax.tree.map(lambda *shares: np.concatenate([np.asarray(x) for x in shares]), *outs)
    return in_units(jax.tree.map(lambda v: v[:count], out), 1.0 / level)


def in_units(fit: TexelFit, factor: float) -> TexelFit:
    """`fit` of observations multiplied by `factor`: the reflectances and residuals scale with the
    observations (the costs with their square); the geometry does not."""
    if factor == 1.0:
        return fit
    dtype = np.asarray(fit.rho_d).dtype
    k = np.asarray(factor, dtype)
    return dataclasses.replace(fit, rho_d=fit.rho_d * k, rho_s=fit.rho_s * k, residual=fit.residual * k,
                               cost=fit.cost * k * k)


def empty_fit(n: int) -> TexelFit:
    """The fit of `n` texels outside a capture's mask: nothing reflected (rho 0), normal +z."""
    zeros = np.zeros(n, np.float32)
    return TexelFit(rho_d=np.zeros((n, 3), np.float32), rho_s=np.zeros((n, 3), np.float32),
                    normal=np.tile(np.float32([0.0, 0.0, 1.0]), (n, 1)), sigma_x=zeros + np.float32(0.1),
                    sigma_y=zeros + np.float32(0.1), residual=zeros, cost=zeros, converged=np.zeros(n, bool),
                    num_steps=np.zeros(n, np.int32), n_valid=np.zeros(n, np.int32),
                    material=np.full(n, -1, np.int32))


def _progress_bar(total: int, progress: bool | None):
    """tqdm bar of texels: done / total, rate and time left (None: on a terminal only)."""
    return tqdm(total=total, unit="texel", desc="fit", disable=None if progress is None else not progress,
                smoothing=0.1)


def _assemble_maps(results: list[TexelFit], plan: ChunkPlan) -> TexelFit:
    """Per-chunk flat fits (in `plan.texels` order) -> one `TexelFit` of `H W ...` maps (`empty_fit`
    outside the mask)."""
    total = plan.size[0] * plan.size[1]

    def place(empty, *chunks):
        out = np.array(empty, dtype=chunks[0].dtype) if chunks else np.asarray(empty)
        if chunks:
            out[plan.texels] = np.concatenate(chunks)
        return out.reshape(tuple(plan.size) + out.shape[1:])

    return jax.tree.map(place, empty_fit(total), *results)


def sample_size(n_lights: int) -> int:
    """Texels the material pass samples from a capture of `n_lights` lights."""
    return int(np.clip(SAMPLE_OBSERVATIONS // max(n_lights, 1), *SAMPLE_TEXELS))


def sample_indices(valid_texels: np.ndarray, count: int) -> np.ndarray:
    """Up to `count` indices of `valid_texels` (flat texel indices), evenly strided (deterministic)."""
    valid_texels = np.asarray(valid_texels)
    if valid_texels.size <= count:
        return valid_texels
    pick = np.linspace(0, valid_texels.size - 1, count).round().astype(np.int64)
    return valid_texels[pick]


def _sample(source: TexelSource, plan: ChunkPlan) -> np.ndarray:
    """The global pass's texels: up to `sample_size` of the plan's texels with at least
    MATERIAL_MIN_VALID valid observations, evenly strided."""
    n_valid = np.asarray(source.counts.n_valid).reshape(-1)
    return sample_indices(plan.texels[n_valid[plan.texels] >= MATERIAL_MIN_VALID],
                          sample_size(np.shape(source.light_dirs)[0]))


def capture_level(source: TexelSource, plan: ChunkPlan) -> float:
    """The factor that brings the median, over the sampled texels, of a texel's RMS valid
    observation to REFERENCE_RMS (1 where nothing is sampled or the sample is black)."""
    texels = _sample(source, plan)
    if not texels.size:
        return 1.0
    ratio, weight = read_texels(source.read, texels, window=max(plan.padded, 1))
    valid = (np.asarray(weight) > 0) & np.all(np.isfinite(ratio), axis=-1)
    sq = np.where(valid[..., None], np.asarray(ratio, np.float64), 0.0) ** 2
    rms = np.sqrt(sq.sum(axis=(1, 2)) / np.maximum(3 * valid.sum(axis=1), 1))
    median = float(np.median(rms[valid.any(axis=1)])) if valid.any() else 0.0
    if not np.isfinite(median) or median <= 0:
        return 1.0
    return float(np.float32(REFERENCE_RMS / median))


def estimate_table(source: TexelSource, plan: ChunkPlan, settings: FitSettings,
                   checkpoint: Checkpoint | None, level: float = 1.0) -> MaterialTable:
    """The global pass of a robust fit: the material table of the sample (`_sample`; fitted by the
    chunks' compiled program, with a table of no priors), in the units of the observations times
    `level` (what the solvers see). Saved in the checkpoint and reloaded from there on a resumed fit."""
    saved = checkpoint.directory / MATERIALS_FILE if checkpoint is not None else None
    if saved is not None and saved.is_file():
        try:
            return MaterialTable.from_json(json.loads(saved.read_text()))
        except (OSError, ValueError, KeyError, TypeError):
            pass   # unreadable: estimate again
    texels = _sample(source, plan)
    if texels.size:
        ratio, weight = read_texels(source.read, texels, window=max(plan.padded, 1))
        ratio = ratio * np.asarray(level, ratio.dtype)
        n = int(texels.size)
        starts = tuple(range(0, n, plan.padded))
        sample = ChunkPlan((1, n), np.arange(n), starts, tuple(min(plan.padded, n - s) for s in starts), plan.tile,
                           plan.padded)
        parts = [fit_chunk(ratio[s:s + c], weight[s:s + c], sample, i, source.light_dirs, source.view_dir, settings,
                           no_materials())
                 for i, (s, c) in enumerate(zip(sample.starts, sample.counts))]
        fits = jax.tree.map(lambda *p: np.concatenate(p), *parts)
        table = estimate_materials(ratio, weight, source.light_dirs, source.view_dir, fits, model=settings.model)
    else:
        table = no_materials()
    if saved is not None:
        with atomic_path(saved) as tmp:
            tmp.write_text(json.dumps(table.to_json()))
    return table


Chunks = Callable[[list[int]], Iterable[tuple[int, TexelFit]]]


def local_chunks(source: TexelSource, plan: ChunkPlan, checkpoint: Checkpoint | None, settings: FitSettings,
                 table: MaterialTable | None, level: float) -> Chunks:
    """The chunks fitted in this process: each read (the next one by a thread meanwhile), fitted
    and saved in turn; yields (index, fit) as each is done."""

    def fit_todo(todo: list[int]) -> Iterator[tuple[int, TexelFit]]:
        reader = concurrent.futures.ThreadPoolExecutor(max_workers=1)
        try:
            future = reader.submit(read_chunk, source.read, plan, todo[0]) if todo else None
            for k, i in enumerate(todo):
                data = future.result()
                if k + 1 < len(todo):
                    future = reader.submit(read_chunk, source.read, plan, todo[k + 1])
                fit = fit_chunk(*data, plan, i, source.light_dirs, source.view_dir, settings, table, level)
                if checkpoint is not None:
                    checkpoint.save(i, fit)
                yield i, fit
        finally:
            reader.shutdown(wait=True, cancel_futures=True)

    return fit_todo


class FitResult(NamedTuple):
    """A source's fit: what the BTF writer writes (`fitting.writer.write_fit`)."""

    maps: TexelFit                 # `H W ...` maps (`empty_fit` outside the mask)
    table: MaterialTable | None    # the robust method's materials (None: plain), at the capture's level
    level: float                   # the factor the solvers saw the observations multiplied by (`capture_level`)
    counts: ObservationCounts      # the source's light counts
    mask: np.ndarray | None        # the texels fitted (None: all)
    observations: dict             # `observation_summary` of the counts


def fit_source(source: TexelSource, settings: FitSettings, *, partial_dir: str | os.PathLike | None = None,
               executor=local_chunks, progress: bool | None = None,
               on_chunk: Callable[[int], object] | None = None) -> FitResult:
    """Every texel of `source` fitted as `settings` say. First its counts are checked
    (`observation_summary`: `InputError` when most texels have no valid observation).

    `partial_dir`: checkpoint finished chunks there and reuse those already present (a directory
    written for other inputs or settings is emptied first). `executor(source, plan, checkpoint,
    settings, table, level)` gives the function that fits a list of chunks (`local_chunks`, or
    `fitting.cluster.DaskChunks`). `progress`: None = a tqdm bar on a terminal only.
    """
    summary = observation_summary(source.counts, source.mask, source.name)   # before any work
    plan = plan_chunks(source.size, settings, source.mask)
    level = capture_level(source, plan)
    checkpoint = None
    if partial_dir is not None:
        checkpoint = Checkpoint(partial_dir).prepare(fingerprint({**settings.key(), "level": level}, *source.identity))
    table = estimate_table(source, plan, settings, checkpoint, level) if settings.robust else None
    fit_todo = executor(source, plan, checkpoint, settings, table, level)
    results = [checkpoint.load(i, count) if checkpoint is not None else None for i, count in enumerate(plan.counts)]
    todo = [i for i, r in enumerate(results) if r is None]
    bar = _progress_bar(plan.n_fitted, progress)
    bar.update(plan.n_fitted - sum(plan.counts[i] for i in todo))
    try:
        for i, fit in fit_todo(todo):
            results[i] = fit
            bar.update(plan.counts[i])
            if on_chunk is not None:
                on_chunk(i)
    finally:
        bar.close()
    return FitResult(_assemble_maps(results, plan), table, level, source.counts, source.mask, summary)


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

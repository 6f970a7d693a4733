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
bit-identical to an uninterrupted one. `.partial/` is removed once the BTF is complete.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import jax
import numpy as np

from jaxrender.io import atomic_path, write_btf, write_btf_previews

from .lm import DEFAULT_MAX_STEPS, DEFAULT_SOLVER, SOLVERS, MaterialTable, default_tolerances, fit_texels
from .materials import estimate_materials, no_materials, sample_indices
from .pyramid import build_pyramid

__all__ = ["fit_observations", "fit_maps", "fit_chunks", "fit_chunk", "chunk_plan", "level0_channels", "write_fit",
           "fit_materials", "DEFAULT_CHUNK", "TILE", "PARTIAL", "METHODS", "DEFAULT_METHOD"]

DEFAULT_CHUNK = 4096
# texels per vmapped solve: the solver loop runs until the slowest texel of a tile is done; small tiles stay in cache
TILE = 32
PARTIAL = ".partial"
# "robust" (default, every capture): materials shared by the texels (`fitting.materials`, one global
# pass over a sample) give each texel's lobe a prior; ROBUST_ROUNDS reweighted geometry solves and
# an appearance solve per texel (`fitting.lm.fit_texel`). "plain": per-texel least squares (paper 004).
METHODS = ("robust", "plain")
DEFAULT_METHOD = "robust"
ROBUST_ROUNDS = 2
_METHOD_TEXT = {"robust": "levenberg-marquardt, variable projection of rho_d, rho_s; material priors, "
                          "robust geometry rounds with an ambient term, appearance round",
                "plain": "levenberg-marquardt, variable projection of rho_d, rho_s"}
_FIELDS = ("rho_d", "rho_s", "normal", "sigma_x", "sigma_y", "residual", "cost", "converged", "num_steps", "n_valid",
           "material")


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
               materials=None) -> dict[str, np.ndarray]:
    """Fit `n_devices * per_device` texels (already padded) over the local devices; flat numpy fields."""
    devices = jax.local_devices()
    fn = _tile_fit(tile, model, solver, max_steps)
    per_device = ratio.shape[0] // len(devices)
    outs = []
    for d, dev in enumerate(devices):   # dispatched asynchronously: the devices run at once
        share = slice(d * per_device, (d + 1) * per_device)
        place = jax.sharding.SingleDeviceSharding(dev)
        r = jax.device_put(ratio[share].reshape((-1, tile) + ratio.shape[1:]), place)
        w = jax.device_put(weight[share].reshape((-1, tile) + weight.shape[1:]), place)
        dirs, view = jax.device_put(np.asarray(light_dirs), place), jax.device_put(np.asarray(view_dir), place)
        outs.append(fn(r, w, dirs, view, jax.device_put(materials, place) if materials is not None else None))
    return {name: np.concatenate([np.asarray(getattr(o, name)) for o in outs]) for name in _FIELDS}


def _fingerprint(obs, settings: dict) -> str:
    h = hashlib.sha256(json.dumps(settings, sort_keys=True).encode())
    for x in (obs.light_dirs, obs.view_dir):
        h.update(np.ascontiguousarray(np.asarray(x)).tobytes())
    h.update(np.ascontiguousarray(np.asarray(obs.ratio)[..., :1, :]).tobytes())  # first light of every texel
    h.update(str(tuple(obs.ratio.shape)).encode())
    return h.hexdigest()


def _prepare_partial(partial: Path, fingerprint: str) -> None:
    config = partial / "config.json"
    if partial.is_dir():
        try:
            same = json.loads(config.read_text()).get("fingerprint") == fingerprint
        except (OSError, ValueError):
            same = False
        if not same:  # another capture or other settings: start again
            shutil.rmtree(partial)
    partial.mkdir(parents=True, exist_ok=True)
    if not config.is_file():
        with atomic_path(config) as tmp:
            tmp.write_text(json.dumps({"fingerprint": fingerprint}))


def _save_chunk(path: Path, result: dict[str, np.ndarray]) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **result)


def _load_chunk(path: Path, count: int) -> dict[str, np.ndarray] | None:
    try:
        with np.load(path) as data:
            out = {name: data[name] for name in _FIELDS}
    except (OSError, ValueError, KeyError, EOFError):
        return None  # unreadable: fit it again
    if any(v.shape[0] != count for v in out.values()):
        return None
    return out


def chunk_plan(total: int, chunk: int) -> tuple[list[int], int, int]:
    """(first texel of every chunk, tile, padded chunk size): the work units of a fit.

    Every chunk is fitted with the same padded shape (one compilation), the last one padded with
    its last texel: the same units whether the observations are in memory or in a store, fitted
    here or on a Dask worker, so a texel always meets the same compiled program."""
    n_dev = jax.local_device_count()
    tile, per_device = _layout(min(chunk, total), n_dev)
    return list(range(0, total, chunk)), tile, per_device * n_dev


def fit_chunk(read: Callable[[int, int], tuple[np.ndarray, np.ndarray]], start: int, count: int, padded: int,
              light_dirs, view_dir, *, tile: int, model: str, solver: str, max_steps: int,
              materials=None) -> dict[str, np.ndarray]:
    """Fit texels `start .. start + count - 1`: `read(start, count)` gives their (ratio `count L 3`,
    weight `count L`); padded to `padded` texels with the last one; flat numpy `TexelFit` fields."""
    ratio, weight = read(start, count)
    if count != padded:
        idx = np.minimum(np.arange(padded), count - 1)  # pad with the last texel
        ratio, weight = ratio[idx], weight[idx]
    out = _chunk_fit(ratio, weight, light_dirs, view_dir, tile=tile, model=model, solver=solver, max_steps=max_steps,
                     materials=materials)
    return {k: v[:count] for k, v in out.items()}


def chunk_path(partial: Path, index: int) -> Path:
    return partial / f"chunk_{index:06d}.npz"


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


def assemble_maps(results: list[dict[str, np.ndarray]], size: tuple[int, int]) -> dict[str, np.ndarray]:
    """Per-chunk flat results (in texel order) -> `H W ...` maps."""
    maps = {name: np.concatenate([r[name] for r in results]) for name in _FIELDS}
    return {name: v.reshape(tuple(size) + v.shape[1:]) for name, v in maps.items()}


def read_texels(read: Callable[[int, int], tuple[np.ndarray, np.ndarray]], indices: np.ndarray,
                chunk: int) -> tuple[np.ndarray, np.ndarray]:
    """(ratio, weight) of the texels `indices` (sorted flat indices), read chunk by chunk."""
    ratios, weights = [], []
    for first in np.unique(indices // chunk) * chunk:
        pick = indices[(indices >= first) & (indices < first + chunk)]
        r, w = read(int(pick[0]), int(pick[-1] - pick[0] + 1))
        ratios.append(np.asarray(r)[pick - pick[0]])
        weights.append(np.asarray(w)[pick - pick[0]])
    return np.concatenate(ratios), np.concatenate(weights)


_TABLE_FIELDS = ("rho_s", "s", "log_share", "colour", "colour_spread", "noise")


def table_to_numpy(table: MaterialTable) -> dict[str, np.ndarray]:
    return {name: np.asarray(getattr(table, name)) for name in _TABLE_FIELDS}


def table_from_numpy(arrays) -> MaterialTable:
    return MaterialTable(*(jax.numpy.asarray(arrays[name]) for name in _TABLE_FIELDS))


def fit_materials(read: Callable[[int, int], tuple[np.ndarray, np.ndarray]], n_valid: np.ndarray, light_dirs,
                  view_dir, *, solver: str, chunk: int, max_steps: int, model: str,
                  partial: Path | None) -> tuple[MaterialTable, dict]:
    """The global pass of a robust fit: the material table of a sample of the texels with valid
    observations (`fitting.materials`; the sample fitted by the same compiled program as the
    tiles, with no priors). Saved in `partial` and reloaded from there on a resumed fit."""
    saved = partial / "materials.npz" if partial is not None else None
    if saved is not None and saved.is_file():
        try:
            with np.load(saved) as data:
                return table_from_numpy(data), json.loads(str(data["info"]))
        except (OSError, ValueError, KeyError):
            pass   # unreadable: estimate again
    flat = np.asarray(n_valid).reshape(-1)
    indices = sample_indices(np.flatnonzero(flat >= 8))
    total = flat.size
    _, tile, padded = chunk_plan(total, chunk)
    if indices.size:
        ratio, weight = read_texels(read, indices, chunk)
        parts = []
        for start in range(0, indices.size, padded):
            count = min(padded, indices.size - start)
            parts.append(fit_chunk(lambda s, c: (ratio[s:s + c], weight[s:s + c]), start, count, padded, light_dirs,
                                   view_dir, tile=tile, model=model, solver=solver, max_steps=max_steps,
                                   materials=no_materials()))
        fits = {k: np.concatenate([p[k] for p in parts]) for k in _FIELDS}
        table, info = estimate_materials(ratio, weight, light_dirs, view_dir, model=model, fits=fits)
    else:
        table, info = no_materials(), {"materials": 0, "sample": 0}
    if saved is not None:
        with atomic_path(saved) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, info=json.dumps(info), **table_to_numpy(table))
    return table, info


def fit_chunks(read: Callable[[int, int], tuple[np.ndarray, np.ndarray]], size: tuple[int, int], light_dirs,
               view_dir, *, solver: str, chunk: int, max_steps: int, model: str, partial: Path | None,
               progress: bool | None, on_chunk: Callable[[int], object] | None = None,
               prefetch: bool = False, materials=None) -> dict[str, np.ndarray]:
    """Fit every chunk of `read`'s texels in this process, checkpointing each into `partial`
    (chunks already there are loaded). `prefetch`: read the next chunk (a thread) while this one
    is fitted. `on_chunk(i)` is called after chunk i is fitted and saved."""
    import concurrent.futures

    total = size[0] * size[1]
    starts, tile, padded = chunk_plan(total, chunk)
    counts = [min(chunk, total - start) for start in starts]
    results: list[dict[str, np.ndarray] | None] = [
        _load_chunk(chunk_path(partial, i), counts[i]) if partial is not None and chunk_path(partial, i).is_file()
        else None for i in range(len(starts))]
    todo = [i for i, r in enumerate(results) if r is None]
    bar = progress_bar(total, progress)
    bar.update(total - sum(counts[i] for i in todo))

    def load(i):
        return read(starts[i], counts[i])

    reader = concurrent.futures.ThreadPoolExecutor(max_workers=1) if prefetch and todo else None
    try:
        future = reader.submit(load, todo[0]) if reader is not None else None
        for k, i in enumerate(todo):
            data = future.result() if reader is not None else load(i)
            if reader is not None and k + 1 < len(todo):
                future = reader.submit(load, todo[k + 1])
            result = fit_chunk(lambda s, c, data=data: data, starts[i], counts[i], padded, light_dirs, view_dir,
                               tile=tile, model=model, solver=solver, max_steps=max_steps, materials=materials)
            if partial is not None:
                _save_chunk(chunk_path(partial, i), result)
            results[i] = result
            bar.update(counts[i])
            if on_chunk is not None:
                on_chunk(i)
    finally:
        bar.close()
        if reader is not None:
            reader.shutdown(wait=True, cancel_futures=True)
    return assemble_maps(results, size)


def fit_maps(obs, *, solver: str = DEFAULT_SOLVER, chunk: int = DEFAULT_CHUNK, max_steps: int = DEFAULT_MAX_STEPS,
             model: str = "reciprocal", partial_dir: str | os.PathLike | None = None,
             progress: bool | None = None, on_chunk: Callable[[int], object] | None = None,
             method: str = DEFAULT_METHOD) -> dict[str, np.ndarray]:
    """Fit every texel of `Observations`; returns `H W ...` numpy maps of the `TexelFit` fields.

    `method`: "robust" (default; materials shared by the texels, robust geometry and appearance
    rounds: `METHODS`) or "plain" (per-texel least squares).
    `partial_dir`: checkpoint finished chunks there and reuse the ones already present.
    `progress`: None = a tqdm bar on a terminal only, False = never, True = always.
    """
    return _fit_maps(obs, solver=solver, chunk=chunk, max_steps=max_steps, model=model, partial_dir=partial_dir,
                     progress=progress, on_chunk=on_chunk, method=method)[0]


def _fit_maps(obs, *, solver, chunk, max_steps, model, partial_dir, progress, on_chunk=None,
              method=DEFAULT_METHOD) -> tuple[dict[str, np.ndarray], dict]:
    """`fit_maps` and the material pass's info (empty for the plain method)."""
    check_settings(solver, chunk, max_steps, method)
    h, w = obs.size
    total = h * w
    ratio = np.asarray(obs.ratio).reshape(total, obs.n_lights, 3)
    weight = np.asarray(obs.weight).reshape(total, obs.n_lights)
    settings = {"solver": solver, "chunk": chunk, "max_steps": max_steps, "model": model,
                "dtype": str(ratio.dtype), "method": method}
    partial = None
    if partial_dir is not None:
        partial = Path(partial_dir)
        _prepare_partial(partial, _fingerprint(obs, settings))

    def read(s, c):
        return ratio[s:s + c], weight[s:s + c]

    table, info = None, {}
    if method == "robust":
        table, info = fit_materials(read, np.sum(weight > 0, axis=1), obs.light_dirs, obs.view_dir, solver=solver,
                                    chunk=chunk, max_steps=max_steps, model=model, partial=partial)
    maps = fit_chunks(read, (h, w), obs.light_dirs, obs.view_dir, solver=solver, chunk=chunk, max_steps=max_steps,
                      model=model, partial=partial, progress=progress, on_chunk=on_chunk, materials=table)
    return maps, info


def level0_channels(maps: dict[str, np.ndarray], obs) -> dict[str, np.ndarray]:
    """BTF level-0 channels (design.md names) of `fit_maps` output and the observation counts
    (`Observations` or a dict `n_valid`, `n_saturated`, `n_dark` of `H W` maps)."""
    c: dict[str, np.ndarray] = {}
    for i, ch in enumerate("RGB"):
        c[f"rho_d.{ch}"] = maps["rho_d"][..., i]
        c[f"rho_s.{ch}"] = maps["rho_s"][..., i]
    for i, ax in enumerate("XYZ"):
        c[f"normal.{ax}"] = maps["normal"][..., i]
    c["sigma_x"], c["sigma_y"] = maps["sigma_x"], maps["sigma_y"]
    c["residual"] = maps["residual"]
    c["converged"] = maps["converged"].astype(np.float32)
    for name in ("n_valid", "n_saturated", "n_dark"):  # `Observations` or a dict of counts (a store's)
        c[name] = np.asarray(obs[name] if isinstance(obs, dict) else getattr(obs, name))
    return {k: np.asarray(v, np.float32) for k, v in c.items()}


def write_fit(btf_dir: Path, maps: dict[str, np.ndarray], counts, *, solver: str, chunk: int, max_steps: int,
              model: str, pyramid: bool, seconds: float, cpu_seconds: float | None = None,
              meta: dict | None = None, method: str = DEFAULT_METHOD, materials: dict | None = None) -> Path:
    """Level 0 (`btf.json` last), its previews and the EM pyramid of fitted maps; removes `.partial/`.
    `counts`: `Observations` or a dict of `n_valid`, `n_saturated`, `n_dark` maps."""
    level0 = level0_channels(maps, counts)
    rtol, atol = default_tolerances(np.float32)  # the fit always sees float32 observations
    info = {"fit": {"solver": solver, "method": _METHOD_TEXT[method],
                    "chunk": chunk, "max_steps": max_steps, "rtol": rtol, "atol": atol,
                    "devices": jax.local_device_count(),
                    "converged_fraction": float(np.mean(maps["converged"])),
                    "median_residual": float(np.median(maps["residual"])),
                    "median_steps": float(np.median(maps["num_steps"])), "seconds": round(seconds, 3)}}
    if cpu_seconds is not None:  # this process's CPU time (robust to a shared machine's load)
        info["fit"]["cpu_seconds"] = round(cpu_seconds, 3)
    if materials:
        info["fit"]["materials"] = materials
    info.update(meta or {})
    write_btf(btf_dir, [level0], model=model, meta=info)
    write_btf_previews(btf_dir, level0)
    del level0
    if pyramid:
        build_pyramid(btf_dir)
    shutil.rmtree(btf_dir / PARTIAL, ignore_errors=True)
    return btf_dir


def fit_observations(obs, btf_dir: str | os.PathLike, *, solver: str = DEFAULT_SOLVER, chunk: int = DEFAULT_CHUNK,
                     max_steps: int = DEFAULT_MAX_STEPS, model: str = "reciprocal", pyramid: bool = True,
                     progress: bool | None = None, meta: dict | None = None, method: str = DEFAULT_METHOD) -> Path:
    """Fit in-memory `Observations` into the BTF directory `btf_dir` (checkpointed and resumable)."""
    btf_dir = Path(btf_dir)
    if np.asarray(obs.ratio).dtype != np.float32:
        raise ValueError("fit_observations fits float32 observations")
    t0, c0 = time.perf_counter(), time.process_time()
    maps, materials = _fit_maps(obs, solver=solver, chunk=chunk, max_steps=max_steps, model=model,
                                partial_dir=btf_dir / PARTIAL, progress=progress, method=method)
    return write_fit(btf_dir, maps, obs, solver=solver, chunk=chunk, max_steps=max_steps, model=model,
                     pyramid=pyramid, seconds=time.perf_counter() - t0, cpu_seconds=time.process_time() - c0,
                     meta=dict(meta or {}), method=method, materials=materials)

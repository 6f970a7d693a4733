"""Fit a whole capture: chunks of texels, split over the local devices, checkpointed, resumable.

`fit_capture(CAPTURE_DIR, BTF_DIR)` loads and validates the capture (nothing is written when it is
malformed), merges the exposure brackets, fits every texel with `fitting.lm.fit_texels` in chunks
of `chunk` texels (each chunk split over all local JAX devices, each device fitting its share in
tiles whose size does not depend on the device count: the maps are bit-identical on 1 or N devices),
and writes the BTF directory: level 0 through `jaxrender.io.write_btf` (`btf.json` last), PNG
previews, then the EM pyramid (`fitting.pyramid.build_pyramid`, which rewrites `btf.json` last).

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

from .lm import DEFAULT_MAX_STEPS, DEFAULT_SOLVER, SOLVERS, default_tolerances, fit_texels

__all__ = ["fit_capture", "fit_observations", "fit_maps", "level0_channels", "DEFAULT_CHUNK", "TILE"]

DEFAULT_CHUNK = 4096
TILE = 32  # texels per vmapped solve: the solver loop runs until the slowest texel of a tile is done; small tiles stay in cache
PARTIAL = ".partial"
_FIELDS = ("rho_d", "rho_s", "normal", "sigma_x", "sigma_y", "residual", "cost", "converged", "num_steps", "n_valid")


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

    def fn(ratio, weight, light_dirs, view_dir):
        out = jax.lax.map(lambda rw: fit_texels(rw[0], rw[1], light_dirs, view_dir, model=model, solver=solver,
                                                max_steps=max_steps), (ratio, weight))
        return jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:]), out)

    return jax.jit(fn)


def _chunk_fit(ratio, weight, light_dirs, view_dir, *, tile, model, solver, max_steps) -> dict[str, np.ndarray]:
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
        outs.append(fn(r, w, jax.device_put(np.asarray(light_dirs), place), jax.device_put(np.asarray(view_dir), place)))
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


def fit_maps(obs, *, solver: str = DEFAULT_SOLVER, chunk: int = DEFAULT_CHUNK, max_steps: int = DEFAULT_MAX_STEPS,
             model: str = "reciprocal", partial_dir: str | os.PathLike | None = None,
             progress: bool | None = None, on_chunk: Callable[[int], object] | None = None) -> dict[str, np.ndarray]:
    """Fit every texel of `Observations`; returns `H W ...` numpy maps of the `TexelFit` fields.

    `partial_dir`: checkpoint finished chunks there and reuse the ones already present.
    `progress`: None = a tqdm bar on a terminal only, False = never, True = always.
    """
    from tqdm.auto import tqdm

    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}: use one of {SOLVERS}")
    if chunk < 1 or max_steps < 1:
        raise ValueError("chunk and max_steps must be >= 1")
    h, w = obs.size
    n_lights = obs.n_lights
    total = h * w
    ratio = np.asarray(obs.ratio).reshape(total, n_lights, 3)
    weight = np.asarray(obs.weight).reshape(total, n_lights)
    n_dev = jax.local_device_count()
    tile, per_device = _layout(min(chunk, total), n_dev)
    padded = per_device * n_dev  # one shape for every chunk: one compilation
    starts = list(range(0, total, chunk))
    settings = {"solver": solver, "chunk": chunk, "max_steps": max_steps, "model": model,
                "dtype": str(ratio.dtype)}
    partial = None
    if partial_dir is not None:
        partial = Path(partial_dir)
        _prepare_partial(partial, _fingerprint(obs, settings))
    results: list[dict[str, np.ndarray]] = []
    bar = tqdm(total=total, unit="texel", desc="fit", disable=None if progress is None else not progress,
               smoothing=0.1)
    converged = 0
    for i, start in enumerate(starts):
        count = min(chunk, total - start)
        path = partial / f"chunk_{i:06d}.npz" if partial is not None else None
        result = _load_chunk(path, count) if path is not None and path.is_file() else None
        if result is None:
            if count == padded:   # a view: no copy of the chunk's observations
                chunk_ratio, chunk_weight = ratio[start:start + count], weight[start:start + count]
            else:
                idx = np.minimum(np.arange(start, start + padded), start + count - 1)  # pad with the last texel
                chunk_ratio, chunk_weight = ratio[idx], weight[idx]
            out = _chunk_fit(chunk_ratio, chunk_weight, obs.light_dirs, obs.view_dir, tile=tile, model=model, solver=solver,
                             max_steps=max_steps)
            result = {k: v[:count] for k, v in out.items()}
            if path is not None:
                _save_chunk(path, result)
        results.append(result)
        converged += int(np.sum(result["converged"]))
        bar.update(count)
        bar.set_postfix(converged=f"{converged / (start + count):.1%}", refresh=False)
        if on_chunk is not None:
            on_chunk(i)
    bar.close()
    maps = {name: np.concatenate([r[name] for r in results]) for name in _FIELDS}
    return {name: v.reshape((h, w) + v.shape[1:]) for name, v in maps.items()}


def level0_channels(maps: dict[str, np.ndarray], obs) -> dict[str, np.ndarray]:
    """BTF level-0 channels (design.md names) of `fit_maps` output and the observation counts."""
    c: dict[str, np.ndarray] = {}
    for i, ch in enumerate("RGB"):
        c[f"rho_d.{ch}"] = maps["rho_d"][..., i]
        c[f"rho_s.{ch}"] = maps["rho_s"][..., i]
    for i, ax in enumerate("XYZ"):
        c[f"normal.{ax}"] = maps["normal"][..., i]
    c["sigma_x"], c["sigma_y"] = maps["sigma_x"], maps["sigma_y"]
    c["residual"] = maps["residual"]
    c["converged"] = maps["converged"].astype(np.float32)
    for name in ("n_valid", "n_saturated", "n_dark"):
        c[name] = np.asarray(getattr(obs, name))
    return {k: np.asarray(v, np.float32) for k, v in c.items()}


def fit_observations(obs, btf_dir: str | os.PathLike, *, solver: str = DEFAULT_SOLVER, chunk: int = DEFAULT_CHUNK,
                     max_steps: int = DEFAULT_MAX_STEPS, model: str = "reciprocal", pyramid: bool = True,
                     progress: bool | None = None, meta: dict | None = None) -> Path:
    """Fit `Observations` into the BTF directory `btf_dir` (checkpointed and resumable)."""
    btf_dir = Path(btf_dir)
    partial = btf_dir / PARTIAL
    t0 = time.perf_counter()
    maps = fit_maps(obs, solver=solver, chunk=chunk, max_steps=max_steps, model=model, partial_dir=partial,
                    progress=progress)
    fit_s = time.perf_counter() - t0
    level0 = level0_channels(maps, obs)
    rtol, atol = default_tolerances(np.asarray(obs.ratio).dtype)
    info = {"fit": {"solver": solver, "method": "levenberg-marquardt, variable projection of rho_d, rho_s",
                    "chunk": chunk, "max_steps": max_steps, "rtol": rtol, "atol": atol,
                    "devices": jax.local_device_count(),
                    "converged_fraction": float(np.mean(maps["converged"])),
                    "median_residual": float(np.median(maps["residual"])),
                    "median_steps": float(np.median(maps["num_steps"])), "seconds": round(fit_s, 3)}}
    info.update(meta or {})
    write_btf(btf_dir, [level0], model=model, meta=info)
    write_btf_previews(btf_dir, level0)
    if pyramid:
        from .pyramid import build_pyramid

        build_pyramid(btf_dir)
    shutil.rmtree(partial, ignore_errors=True)
    return btf_dir


def fit_capture(capture_dir: str | os.PathLike, btf_dir: str | os.PathLike, *, solver: str = DEFAULT_SOLVER,
                chunk: int = DEFAULT_CHUNK, max_steps: int = DEFAULT_MAX_STEPS, model: str = "reciprocal",
                pyramid: bool = True, progress: bool | None = None) -> Path:
    """Capture directory -> BTF directory (see the module docstring). Raises `InputError`
    (`CaptureError`) for a malformed capture before anything is written."""
    from .capture import load_capture
    from .hdr import merge_capture

    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}: use one of {SOLVERS}")
    t0 = time.perf_counter()
    capture = load_capture(capture_dir)
    obs = merge_capture(capture, progress=progress)
    merge_s = time.perf_counter() - t0
    meta = {"capture": str(Path(capture_dir).resolve()), "merge_seconds": round(merge_s, 3)}
    return fit_observations(obs, btf_dir, solver=solver, chunk=chunk, max_steps=max_steps, model=model,
                            pyramid=pyramid, progress=progress, meta=meta)

"""Fit an observation store tile by tile, in this process or as Dask tasks; `fit_capture`.

A tile is one chunk of `chunk` texels (`--chunk`, flat row-major texel order): the unit that is
read from the store (every light of those texels, L / light_block chunks of each array), fitted
(split over the process's local XLA devices, each device fitting 32-texel vmapped solves) and
written to `BTF_DIR/.partial/chunk_NNNNNN.npz` atomically. In this process the next tile is read
while one is fitted; with a Dask scheduler (`fitting.cluster`) every tile not yet in `.partial/`
is one task, run by a worker (one thread: XLA's threads do the work) that reads the store and
writes the tile's file itself, so the store and BTF_DIR must be on a path every worker shares. A
worker that dies loses only its running tile, which the scheduler gives to another; a rerun after
the whole cluster died loads the tiles already written. Every tile is fitted with the same padded
shape and program wherever it runs: the maps equal a single-process run's bit for bit.

A robust fit (the default method) first estimates the capture's materials from a sample of its
texels (`fitting.fit.fit_materials`: read chunk by chunk, fitted, clustered; saved in
`.partial/materials.npz`): that table of a few rows is the only global state, and every tile
(every Dask task) gets it.

Memory: a process holds one or two tiles of observations (`chunk` x L x 16 bytes) plus the output
maps (60 bytes per texel while fitting; level 0 as EXR channels, 100 bytes per texel, while the BTF
and its pyramid are written).
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

import numpy as np

from jaxrender.io import InputError

from .capture import CaptureError
from .cluster import dask_client, describe_scheduler
from .fit import (
    DEFAULT_CHUNK,
    DEFAULT_METHOD,
    PARTIAL,
    _load_chunk,
    _prepare_partial,
    _save_chunk,
    assemble_maps,
    check_settings,
    chunk_path,
    chunk_plan,
    fit_chunk,
    fit_chunks,
    fit_materials,
    progress_bar,
    table_from_numpy,
    table_to_numpy,
    write_fit,
)
from .ingest import DEFAULT_MEMORY_GB, ingest_capture
from .lm import DEFAULT_MAX_STEPS, DEFAULT_SOLVER
from .store import DEFAULT_STORE_DTYPE, ObservationStore, is_store, open_store

__all__ = ["fit_store", "fit_store_maps", "fit_capture", "STORE_SUBDIR"]

STORE_SUBDIR = ".store"  # where `fit_capture` ingests a capture inside BTF_DIR


def _partial_fingerprint(store: ObservationStore, settings: dict) -> str:
    h = hashlib.sha256(json.dumps(settings, sort_keys=True).encode())
    h.update(store.fingerprint.encode())
    return h.hexdigest()


@functools.lru_cache(maxsize=4)
def _worker_store(store_dir: str, fingerprint: str) -> ObservationStore:
    """A worker opens each store once (the fingerprint keys the cache: a rewritten store is reopened)."""
    store = open_store(store_dir)
    if store.fingerprint != fingerprint:
        raise InputError(store_dir, "the observation store changed during the fit")
    return store


def fit_tile(store_dir: str, fingerprint: str, partial: str, index: int, chunk: int, *, solver: str, model: str,
             max_steps: int, materials: dict | None = None) -> int:
    """Fit tile `index` of a store and write it to `partial` (atomically); a Dask task. Returns `index`.
    `materials`: the material table as numpy arrays (`fitting.fit.table_to_numpy`; the global state
    every tile of a robust fit gets), None for the plain method."""
    store = _worker_store(store_dir, fingerprint)
    starts, tile, padded = chunk_plan(store.n_texels, chunk)  # this process's devices
    start = starts[index]
    count = min(chunk, store.n_texels - start)
    table = table_from_numpy(materials) if materials is not None else None
    result = fit_chunk(store.read, start, count, padded, store.light_dirs.astype(np.float32),
                       store.view_dir.astype(np.float32), tile=tile, model=model, solver=solver, max_steps=max_steps,
                       materials=table)
    _save_chunk(chunk_path(Path(partial), index), result)
    return index


def _fit_dask(store: ObservationStore, partial: Path, client, *, chunk, solver, model, max_steps, progress,
              on_chunk, materials=None) -> dict[str, np.ndarray]:
    import distributed

    total = store.n_texels
    starts = list(range(0, total, chunk))
    counts = [min(chunk, total - s) for s in starts]
    results = [_load_chunk(chunk_path(partial, i), counts[i]) if chunk_path(partial, i).is_file() else None
               for i in range(len(starts))]
    todo = [i for i, r in enumerate(results) if r is None]
    bar = progress_bar(total, progress)
    bar.update(total - sum(counts[i] for i in todo))
    try:
        futures = [client.submit(fit_tile, str(store.path.resolve()), store.fingerprint, str(partial.resolve()), i,
                                 chunk, solver=solver, model=model, max_steps=max_steps, pure=False, retries=2,
                                 materials=None if materials is None else table_to_numpy(materials))
                   for i in todo]
        for future in distributed.as_completed(futures):
            i = future.result()
            results[i] = _load_chunk(chunk_path(partial, i), counts[i])
            if results[i] is None:
                raise OSError(f"{chunk_path(partial, i)}: a worker's tile is missing or unreadable "
                              "(is BTF_DIR on a path the workers share?)")
            bar.update(counts[i])
            if on_chunk is not None:
                on_chunk(i)
    finally:
        bar.close()
    return assemble_maps(results, store.size)


def fit_store_maps(store: ObservationStore, *, partial_dir: str | os.PathLike, solver: str = DEFAULT_SOLVER,
                   chunk: int = DEFAULT_CHUNK, max_steps: int = DEFAULT_MAX_STEPS, model: str = "reciprocal",
                   scheduler=None, progress: bool | None = None,
                   on_chunk: Callable[[int], object] | None = None,
                   method: str = DEFAULT_METHOD) -> dict[str, np.ndarray]:
    """`H W ...` maps of the `TexelFit` fields of every texel of `store`, tiles checkpointed in
    `partial_dir` (resumed when present). `scheduler`: see `fitting.cluster`. `method`: see
    `fitting.fit.METHODS` (robust: the material pass runs here, over a sample read from the store)."""
    return _fit_store_maps(store, partial_dir=partial_dir, solver=solver, chunk=chunk, max_steps=max_steps,
                           model=model, scheduler=scheduler, progress=progress, on_chunk=on_chunk, method=method)[0]


def _fit_store_maps(store: ObservationStore, *, partial_dir, solver, chunk, max_steps, model, scheduler, progress,
                    on_chunk=None, method=DEFAULT_METHOD) -> tuple[dict[str, np.ndarray], dict]:
    check_settings(solver, chunk, max_steps, method)
    partial = Path(partial_dir)
    settings = {"solver": solver, "chunk": chunk, "max_steps": max_steps, "model": model, "source": "store",
                "method": method}
    _prepare_partial(partial, _partial_fingerprint(store, settings))
    dirs, view = store.light_dirs.astype(np.float32), store.view_dir.astype(np.float32)
    table, info = None, {}
    if method == "robust":   # the global pass: a sample of the store's texels, read chunk by chunk
        table, info = fit_materials(store.read, store.counts()["n_valid"], dirs, view, solver=solver, chunk=chunk,
                                    max_steps=max_steps, model=model, partial=partial)
    if scheduler is None:
        maps = fit_chunks(store.read, store.size, dirs, view, solver=solver, chunk=chunk, max_steps=max_steps,
                          model=model, partial=partial, progress=progress, on_chunk=on_chunk, prefetch=True,
                          materials=table)
        return maps, info
    with dask_client(scheduler) as client:
        maps = _fit_dask(store, partial, client, chunk=chunk, solver=solver, model=model, max_steps=max_steps,
                         progress=progress, on_chunk=on_chunk, materials=table)
    return maps, info


def fit_store(store_dir: str | os.PathLike, btf_dir: str | os.PathLike, *, solver: str = DEFAULT_SOLVER,
              chunk: int = DEFAULT_CHUNK, max_steps: int = DEFAULT_MAX_STEPS, model: str = "reciprocal",
              pyramid: bool = True, scheduler=None, progress: bool | None = None,
              meta: dict | None = None, method: str = DEFAULT_METHOD) -> Path:
    """Observation store -> BTF directory (tiles checkpointed in `BTF_DIR/.partial/`, resumable).
    Raises `InputError` for a missing, unfinished or foreign store before anything is written."""
    check_settings(solver, chunk, max_steps, method)
    store = open_store(store_dir)
    btf_dir = Path(btf_dir)
    t0, c0 = time.perf_counter(), time.process_time()
    maps, materials = _fit_store_maps(store, partial_dir=btf_dir / PARTIAL, solver=solver, chunk=chunk,
                                      max_steps=max_steps, model=model, scheduler=scheduler, progress=progress,
                                      method=method)
    seconds, cpu_seconds = time.perf_counter() - t0, time.process_time() - c0
    info = {"capture": store.info.get("capture"), "store": {"dtype": store.dtype, "fingerprint": store.fingerprint},
            "scheduler": describe_scheduler(scheduler)}
    info.update(meta or {})
    return write_fit(btf_dir, maps, store.counts(), solver=solver, chunk=chunk, max_steps=max_steps, model=model,
                     pyramid=pyramid, seconds=seconds, cpu_seconds=None if scheduler is not None else cpu_seconds,
                     meta=info, method=method, materials=materials)


def fit_capture(source: str | os.PathLike, btf_dir: str | os.PathLike, *, solver: str = DEFAULT_SOLVER,
                chunk: int = DEFAULT_CHUNK, max_steps: int = DEFAULT_MAX_STEPS, model: str = "reciprocal",
                pyramid: bool = True, scheduler=None, keep_store: bool = False,
                store_dtype: str = DEFAULT_STORE_DTYPE, memory_gb: float = DEFAULT_MEMORY_GB,
                progress: bool | None = None, method: str = DEFAULT_METHOD) -> Path:
    """Capture directory or observation store -> BTF directory.

    A capture is first ingested into `BTF_DIR/.store/` (`fitting.ingest.ingest_capture`,
    resumable), which is removed with `.partial/` once the BTF is complete unless `keep_store`;
    a store is fitted directly. Raises `InputError` (`CaptureError`) for a malformed capture and
    leaves no BTF_DIR it created (the manifest and the headers are checked before anything is
    written). `scheduler`: None (this process), a `distributed.Client`, an address or a local
    worker count (`fitting.cluster`).
    """
    check_settings(solver, chunk, max_steps, method)
    source, btf_dir = Path(source), Path(btf_dir)
    if is_store(source):
        return fit_store(source, btf_dir, solver=solver, chunk=chunk, max_steps=max_steps, model=model,
                         pyramid=pyramid, scheduler=scheduler, progress=progress, method=method)
    created = not btf_dir.exists()
    store_dir = btf_dir / STORE_SUBDIR
    t0 = time.perf_counter()
    try:
        # chunks of `chunk` texels: a tile of the fit reads whole chunks
        ingest_capture(source, store_dir, dtype=store_dtype, memory_gb=memory_gb, tile=chunk, progress=progress)
    except CaptureError:
        if created:
            shutil.rmtree(btf_dir, ignore_errors=True)
        raise
    meta = {"ingest_seconds": round(time.perf_counter() - t0, 3)}
    out = fit_store(store_dir, btf_dir, solver=solver, chunk=chunk, max_steps=max_steps, model=model,
                    pyramid=pyramid, scheduler=scheduler, progress=progress, meta=meta, method=method)
    if not keep_store:
        shutil.rmtree(store_dir, ignore_errors=True)
    return out

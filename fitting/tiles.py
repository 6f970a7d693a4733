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
A chunk of the store found damaged before or during the fit is written again from the capture
(`fitting.ingest.repair_store`) and the fit resumes from its checkpoint; one fit writes a
BTF_DIR at a time (its `.lock`).

A robust fit (the default method) first estimates the capture's materials from a sample of its
texels (`fitting.fit.fit_materials`: read from the store, fitted, clustered; saved in
`.partial/materials.json`): that table of a few rows is the only global state, and every tile
(every Dask task) gets it.

Memory: a process holds one or two tiles of observations (`chunk` x L x 16 bytes) plus the output
maps (60 bytes per texel while fitting; level 0 as EXR channels, 100 bytes per texel, while the BTF
and its pyramid are written).
"""

from __future__ import annotations

import functools
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from jaxrender.io import InputError, output_lock

from .capture import CaptureError
from .checkpoint import Checkpoint, fingerprint
from .cluster import dask_client, describe_scheduler
from .fit import (
    DEFAULT_CHUNK,
    DEFAULT_METHOD,
    PARTIAL,
    ChunkPlan,
    begin_output,
    check_settings,
    fit_chunk,
    fit_in_process,
    fit_materials,
    observation_summary,
    plan_chunks,
    read_chunk,
    run_chunks,
    table_from_numpy,
    table_to_numpy,
    write_fit,
)
from .ingest import DEFAULT_MEMORY_GB, ingest_capture, repair_store
from .lm import DEFAULT_MAX_STEPS, DEFAULT_SOLVER, TexelFit
from .store import DEFAULT_STORE_DTYPE, ObservationStore, StoreDamaged, is_store, open_store

__all__ = ["fit_store", "fit_store_maps", "fit_capture", "STORE_SUBDIR"]

STORE_SUBDIR = ".store"  # where `fit_capture` ingests a capture inside BTF_DIR
MAX_REPAIRS = 3   # rounds of damage found while fitting and written again before the fit gives up


@functools.lru_cache(maxsize=4)
def _worker_store(store_dir: str, fingerprint_: str) -> ObservationStore:
    """A worker opens each store once (the fingerprint keys the cache: a rewritten store is reopened)."""
    store = open_store(store_dir)
    if store.fingerprint != fingerprint_:
        raise InputError(store_dir, "the observation store changed during the fit")
    return store


def fit_tile(store_dir: str, fingerprint_: str, partial: str, index: int, chunk: int, *, solver: str, model: str,
             max_steps: int, materials: dict | None = None) -> int | StoreDamaged:
    """Fit tile `index` of a store and write it to the checkpoint `partial` (atomically); a Dask task.
    Returns `index`, or the `StoreDamaged` its read raised (returned, not raised: the driver repairs
    the store, and Dask neither retries the task nor logs an error). `materials`: the material
    table as numpy arrays (`fitting.fit.table_to_numpy`; the global state every tile of a robust
    fit gets), None for the plain method."""
    store = _worker_store(store_dir, fingerprint_)
    try:
        plan = plan_chunks(store.size, chunk, store.mask())  # this process's devices
        data = read_chunk(store.read, plan, index)
    except StoreDamaged as damaged:
        return damaged
    table = table_from_numpy(materials) if materials is not None else None
    fit = fit_chunk(*data, plan, index, store.light_dirs.astype(np.float32), store.view_dir.astype(np.float32),
                    model=model, solver=solver, max_steps=max_steps, materials=table)
    Checkpoint(partial).save(index, fit)
    return index


def fit_on_dask(store: ObservationStore, plan: ChunkPlan, checkpoint: Checkpoint, client, *, chunk: int, solver: str,
                model: str, max_steps: int, materials=None):
    """`fit_todo` of `fitting.fit.run_chunks` on a Dask cluster: one task per tile, which writes its own
    checkpoint file; each is loaded back as it completes."""
    import distributed

    table = None if materials is None else table_to_numpy(materials)

    def fit_todo(todo: list[int]):
        futures = [client.submit(fit_tile, str(store.path.resolve()), store.fingerprint,
                                 str(checkpoint.directory.resolve()), i, chunk, solver=solver, model=model,
                                 max_steps=max_steps, materials=table, pure=False, retries=2) for i in todo]
        for future in distributed.as_completed(futures):
            i = future.result()
            if isinstance(i, StoreDamaged):
                raise i
            fit = checkpoint.load(i, plan.counts[i])
            if fit is None:
                raise OSError(f"{checkpoint.path(i)}: a worker's tile is missing or unreadable "
                              "(is BTF_DIR on a path the workers share?)")
            yield i, fit

    return fit_todo


def fit_store_maps(store: ObservationStore, *, partial_dir: str | os.PathLike, solver: str = DEFAULT_SOLVER,
                   chunk: int = DEFAULT_CHUNK, max_steps: int = DEFAULT_MAX_STEPS, model: str = "reciprocal",
                   scheduler=None, progress: bool | None = None,
                   on_chunk: Callable[[int], object] | None = None, method: str = DEFAULT_METHOD) -> TexelFit:
    """`TexelFit` of `H W ...` maps of every texel of `store`, tiles checkpointed in `partial_dir`
    (resumed when present). `scheduler`: see `fitting.cluster`. `method`: see `fitting.fit.METHODS`
    (robust: the material pass runs here, over a sample read from the store)."""
    return _fit_store_maps(store, partial_dir=partial_dir, solver=solver, chunk=chunk, max_steps=max_steps,
                           model=model, scheduler=scheduler, progress=progress, on_chunk=on_chunk, method=method)[0]


def _fit_store_maps(store: ObservationStore, *, partial_dir, solver, chunk, max_steps, model, scheduler, progress,
                    on_chunk=None, method=DEFAULT_METHOD) -> tuple[TexelFit, dict]:
    """`fit_store_maps` and the material pass's info (empty for the plain method)."""
    check_settings(solver, chunk, max_steps, method)
    settings = {"solver": solver, "chunk": chunk, "max_steps": max_steps, "model": model, "source": "store",
                "method": method}
    checkpoint = Checkpoint(partial_dir).prepare(fingerprint(settings, store.fingerprint))
    plan = plan_chunks(store.size, chunk, store.mask())
    dirs, view = store.light_dirs.astype(np.float32), store.view_dir.astype(np.float32)
    table, info = None, {}
    if method == "robust":   # the global pass: a sample of the store's texels
        table, info = fit_materials(store.read, plan, store.counts().n_valid, dirs, view, solver=solver,
                                    max_steps=max_steps, model=model, checkpoint=checkpoint)
    if scheduler is None:
        fit_todo = fit_in_process(store.read, plan, checkpoint, dirs, view, solver=solver, max_steps=max_steps,
                                  model=model, prefetch=True, materials=table)
        return run_chunks(plan, checkpoint, fit_todo, progress=progress, on_chunk=on_chunk), info
    with dask_client(scheduler) as client:
        fit_todo = fit_on_dask(store, plan, checkpoint, client, chunk=chunk, solver=solver, model=model,
                               max_steps=max_steps, materials=table)
        return run_chunks(plan, checkpoint, fit_todo, progress=progress, on_chunk=on_chunk), info


def fit_store(store_dir: str | os.PathLike, btf_dir: str | os.PathLike, *, solver: str = DEFAULT_SOLVER,
              chunk: int = DEFAULT_CHUNK, max_steps: int = DEFAULT_MAX_STEPS, model: str = "reciprocal",
              pyramid: bool = True, scheduler=None, progress: bool | None = None,
              meta: dict | None = None, method: str = DEFAULT_METHOD) -> Path:
    """Observation store -> BTF directory (tiles checkpointed in `BTF_DIR/.partial/`, resumable).

    Raises `InputError` for a missing, unfinished, foreign or inconsistent store before anything is
    written. Damaged chunks (missing, truncated, corrupt: `fitting.store.StoreDamaged`), found from the
    file listing before the fit or when a tile reads them, are written again from the store's capture
    when it is at hand (`fitting.ingest.repair_store`) and the fit goes on; otherwise it stops naming
    the chunk. Holds `BTF_DIR/.lock` (`OutputBusy` when another process writes BTF_DIR); `btf.json`,
    the completion marker, is removed at the start and written once every level is.
    """
    check_settings(solver, chunk, max_steps, method)
    store = open_store(store_dir)
    btf_dir = Path(btf_dir)
    with output_lock(btf_dir):
        begin_output(btf_dir)
        damage = store.scan()
        if damage:
            repair_store(store, damage, progress=progress)
        counts, mask = store.counts(), store.mask()
        observation_summary(counts, mask, store.info.get("capture") or store_dir)  # before any work
        t0, c0 = time.perf_counter(), time.process_time()
        for attempt in range(MAX_REPAIRS + 1):
            try:
                maps, materials = _fit_store_maps(store, partial_dir=btf_dir / PARTIAL, solver=solver, chunk=chunk,
                                                  max_steps=max_steps, model=model, scheduler=scheduler,
                                                  progress=progress, method=method)
                break
            except StoreDamaged as damaged:   # found by a tile's read: write it again, resume from the checkpoint
                if attempt == MAX_REPAIRS:
                    raise
                repair_store(store, damaged.damage, progress=progress)
        seconds, cpu_seconds = time.perf_counter() - t0, time.process_time() - c0
        info = {"capture": store.info.get("capture"), "store": {"dtype": store.dtype, "fingerprint": store.fingerprint},
                "scheduler": describe_scheduler(scheduler)}
        info.update(meta or {})
        return write_fit(btf_dir, maps, counts, mask=mask, solver=solver, chunk=chunk, max_steps=max_steps,
                         model=model, pyramid=pyramid, seconds=seconds,
                         cpu_seconds=None if scheduler is not None else cpu_seconds, meta=info, method=method,
                         materials=materials)


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
    with output_lock(btf_dir):
        begin_output(btf_dir)
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

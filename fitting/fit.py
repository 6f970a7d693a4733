"""Fit every texel of a capture: the entry points.

    fit_maps(obs, settings)                    in-memory `Observations` -> `H W` maps
    fit_observations(obs, btf_dir, settings)   in-memory `Observations` -> BTF directory
    fit_store(store_dir, btf_dir, settings)    observation store -> BTF directory (here or on Dask)
    fit_capture(source, btf_dir, settings)     capture directory (ingested first) or store -> BTF directory

Each takes one `FitSettings` (checked when it is made), takes the output's lock once, drives the
chunk engine (`fitting.engine.fit_source`: chunks checkpointed in `BTF_DIR/.partial/`, resumable)
and hands the maps to the BTF writer (`fitting.writer.write_fit`). A chunk of the store found
damaged before or during the fit is written again from the capture (`fitting.ingest.repair_store`)
and the fit resumes from its checkpoint. The robust method (the default) and its reasoning:
docs/fitting.md, "Real captures: the robust method".
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from jaxrender.io import output_lock

from .capture import CaptureError
from .cluster import DaskChunks, dask_client, describe_scheduler
from .engine import FitResult, TexelSource, fit_source, local_chunks
from .hdr import Observations
from .ingest import DEFAULT_MEMORY_GB, ingest_capture, repair_store
from .lm import TexelFit
from .pyramid import compile_pyramid_ahead
from .settings import FitSettings
from .store import DEFAULT_STORE_DTYPE, ObservationStore, StoreDamaged, is_store, open_store
from .writer import PARTIAL, begin_output, write_fit

__all__ = ["fit_maps", "fit_observations", "fit_store", "fit_store_maps", "fit_capture", "STORE_SUBDIR"]

STORE_SUBDIR = ".store"  # where `fit_capture` ingests a capture inside BTF_DIR
MAX_REPAIRS = 3   # rounds of damage found while fitting and written again before the fit gives up


def fit_maps(obs: Observations, settings: FitSettings | None = None, *,
             partial_dir: str | os.PathLike | None = None, progress: bool | None = None,
             on_chunk: Callable[[int], object] | None = None) -> TexelFit:
    """Fit every texel of `Observations` (inside its mask) as `settings` say (default
    `FitSettings()`: the robust method); a `TexelFit` of `H W ...` numpy maps.

    `partial_dir`: checkpoint finished chunks there and reuse the ones already present.
    `progress`: None = a tqdm bar on a terminal only, False = never, True = always.
    """
    return fit_source(TexelSource.of_observations(obs), settings or FitSettings(), partial_dir=partial_dir,
                      progress=progress, on_chunk=on_chunk).maps


def fit_observations(obs: Observations, btf_dir: str | os.PathLike, settings: FitSettings | None = None, *,
                     pyramid: bool = True, progress: bool | None = None, meta: dict | None = None) -> Path:
    """Fit in-memory float32 `Observations` into the BTF directory `btf_dir` (checkpointed and
    resumable; its lock held throughout)."""
    settings = settings or FitSettings()
    btf_dir = Path(btf_dir)
    if np.asarray(obs.ratio).dtype != np.float32:
        raise ValueError("fit_observations fits float32 observations")
    source = TexelSource.of_observations(obs, btf_dir)
    with output_lock(btf_dir):
        begin_output(btf_dir)
        if pyramid:
            compile_pyramid_ahead()   # while the fit runs
        t0, c0 = time.perf_counter(), time.process_time()
        result = fit_source(source, settings, partial_dir=btf_dir / PARTIAL, progress=progress)
        return write_fit(btf_dir, result, settings, pyramid=pyramid, seconds=time.perf_counter() - t0,
                         cpu_seconds=time.process_time() - c0, meta=meta)


def fit_store_maps(store: ObservationStore, settings: FitSettings | None = None, *,
                   partial_dir: str | os.PathLike, scheduler=None, progress: bool | None = None,
                   on_chunk: Callable[[int], object] | None = None) -> TexelFit:
    """`TexelFit` of `H W ...` maps of every texel of `store`, chunks checkpointed in `partial_dir`
    (resumed when present). `scheduler`: see `fitting.cluster`."""
    return _fit_store(store, settings or FitSettings(), Path(partial_dir), scheduler, progress, on_chunk).maps


def _fit_store(store: ObservationStore, settings: FitSettings, partial_dir: Path, scheduler, progress,
               on_chunk=None) -> FitResult:
    """A store's fit, in this process or on the cluster `scheduler`."""
    source = TexelSource.of_store(store)
    if scheduler is None:
        return fit_source(source, settings, partial_dir=partial_dir, executor=local_chunks, progress=progress,
                          on_chunk=on_chunk)
    with dask_client(scheduler) as client:
        return fit_source(source, settings, partial_dir=partial_dir, executor=DaskChunks(client), progress=progress,
                          on_chunk=on_chunk)


def fit_store(store_dir: str | os.PathLike, btf_dir: str | os.PathLike, settings: FitSettings | None = None, *,
              pyramid: bool = True, scheduler=None, progress: bool | None = None) -> Path:
    """Observation store -> BTF directory (chunks checkpointed in `BTF_DIR/.partial/`, resumable).

    Raises `InputError` for a missing, unfinished, foreign or inconsistent store before anything is
    written. Damaged chunks (missing, truncated, corrupt: `fitting.store.StoreDamaged`), found from the
    file listing before the fit or when a chunk reads them, are written again from the store's capture
    when it is at hand (`fitting.ingest.repair_store`) and the fit goes on; otherwise it stops naming
    the chunk. Holds `BTF_DIR/.lock` (`OutputBusy` when another process writes BTF_DIR); `btf.json`,
    the completion marker, is removed at the start and written once every level is.
    """
    settings = settings or FitSettings()
    store = open_store(store_dir)
    btf_dir = Path(btf_dir)
    with output_lock(btf_dir):
        begin_output(btf_dir)
        return _store_to_btf(store, btf_dir, settings, pyramid=pyramid, scheduler=scheduler, progress=progress)


def _store_to_btf(store: ObservationStore, btf_dir: Path, settings: FitSettings, *, pyramid: bool, scheduler,
                  progress, meta: dict | None = None) -> Path:
    """`fit_store` with BTF_DIR's lock held: repair what the file listing shows damaged, fit (and
    repair what the chunks' reads find, resuming from the checkpoint), write."""
    if pyramid:
        compile_pyramid_ahead()   # while the fit runs
    t0, c0 = time.perf_counter(), time.process_time()
    damage = None   # first: what the file listing shows
    for attempt in range(MAX_REPAIRS + 1):
        repair_store(store, damage, progress=progress)
        try:
            result = _fit_store(store, settings, btf_dir / PARTIAL, scheduler, progress)
            break
        except StoreDamaged as damaged:   # found by a chunk's read
            if attempt == MAX_REPAIRS:
                raise
            damage = damaged.damage
    seconds, cpu_seconds = time.perf_counter() - t0, time.process_time() - c0
    info = {"capture": store.info.get("capture"), "store": {"dtype": store.dtype, "fingerprint": store.fingerprint},
            "scheduler": describe_scheduler(scheduler), **(meta or {})}
    return write_fit(btf_dir, result, settings, pyramid=pyramid, seconds=seconds,
                     cpu_seconds=None if scheduler is not None else cpu_seconds, meta=info)


def fit_capture(source: str | os.PathLike, btf_dir: str | os.PathLike, settings: FitSettings | None = None, *,
                pyramid: bool = True, scheduler=None, keep_store: bool = False,
                store_dtype: str = DEFAULT_STORE_DTYPE, memory_gb: float = DEFAULT_MEMORY_GB,
                progress: bool | None = None) -> Path:
    """Capture directory or observation store -> BTF directory.

    A capture is first ingested into `BTF_DIR/.store/` (`fitting.ingest.ingest_capture`,
    resumable), which is removed with `.partial/` once the BTF is complete unless `keep_store`;
    a store is fitted directly. Raises `InputError` (`CaptureError`) for a malformed capture and
    leaves no BTF_DIR it created (the manifest and the headers are checked before anything is
    written). `scheduler`: None (this process), a `distributed.Client`, an address or a local
    worker count (`fitting.cluster`).
    """
    settings = settings or FitSettings()
    source, btf_dir = Path(source), Path(btf_dir)
    if is_store(source):
        return fit_store(source, btf_dir, settings, pyramid=pyramid, scheduler=scheduler, progress=progress)
    created = not btf_dir.exists()
    store_dir = btf_dir / STORE_SUBDIR
    with output_lock(btf_dir):
        begin_output(btf_dir)
        t0 = time.perf_counter()
        try:
            # chunks of the store as the fit's: a chunk of the fit reads whole store chunks
            ingest_capture(source, store_dir, dtype=store_dtype, memory_gb=memory_gb, tile=settings.chunk,
                           progress=progress)
        except CaptureError:
            if created:
                shutil.rmtree(btf_dir, ignore_errors=True)
            raise
        meta = {"ingest_seconds": round(time.perf_counter() - t0, 3)}
        out = _store_to_btf(open_store(store_dir), btf_dir, settings, pyramid=pyramid, scheduler=scheduler,
                            progress=progress, meta=meta)
        if not keep_store:
            shutil.rmtree(store_dir, ignore_errors=True)
        return out

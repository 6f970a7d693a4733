"""The scheduler choice of a fit: this process, or a Dask distributed cluster.

`scheduler` everywhere in `fitting` is one of
- `None`: fit in this process (no cluster, no Dask import);
- a `distributed.Client`: use it (it is not closed);
- an address such as "tcp://HOST:PORT": connect to a cluster started with Dask's own commands
  (`dask scheduler`; `dask worker tcp://HOST:PORT --nthreads 1` on every machine);
- an int N >= 1: start a `distributed.LocalCluster` of N worker processes of one thread each,
  closed at the end.
A worker runs one chunk (one `--chunk` of texels) at a time, with XLA's own threads inside it:
hence one Dask thread per worker.

`DaskChunks(client)` is the chunk engine's executor on a cluster (`fitting.engine.fit_source`):
every chunk not yet checkpointed is one task (`fit_chunk_task`), run by a worker that reads the
observation store and writes the chunk's checkpoint file itself, so the store and BTF_DIR must be
on a path every worker shares. A worker that dies loses only its running chunk, which the
scheduler gives to another; a rerun after the whole cluster died loads the chunks already written.
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator

import jax
import numpy as np

from jaxrender.io import InputError

from .checkpoint import Checkpoint
from .engine import ChunkPlan, TexelSource, fit_chunk, plan_chunks, read_chunk
from .materials import MaterialTable
from .settings import FitSettings
from .store import ObservationStore, StoreDamaged, open_store

__all__ = ["dask_client", "describe_scheduler", "DaskChunks", "fit_chunk_task"]


def describe_scheduler(scheduler) -> str:
    if scheduler is None:
        return "local process"
    if isinstance(scheduler, bool):
        raise TypeError("scheduler must be None, a distributed.Client, an address or a worker count")
    if isinstance(scheduler, int):
        return f"dask LocalCluster of {scheduler} workers"
    if isinstance(scheduler, str):
        return f"dask cluster at {scheduler}"
    return f"dask client {getattr(scheduler, 'scheduler', None) and scheduler.scheduler.address}"


@contextlib.contextmanager
def dask_client(scheduler) -> Iterator[object]:
    """A `distributed.Client` for a scheduler choice that is not None (module docstring)."""
    import distributed

    if isinstance(scheduler, distributed.Client):
        yield scheduler
        return
    if isinstance(scheduler, bool) or not isinstance(scheduler, (int, str)):
        raise TypeError("scheduler must be None, a distributed.Client, an address or a worker count")
    if isinstance(scheduler, int):
        if scheduler < 1:
            raise ValueError("a local Dask cluster needs >= 1 worker")
        with distributed.LocalCluster(n_workers=scheduler, threads_per_worker=1, processes=True,
                                      dashboard_address=None) as cluster, distributed.Client(cluster) as client:
            yield client
        return
    with distributed.Client(scheduler) as client:
        yield client


@functools.lru_cache(maxsize=4)
def _worker_store(store_dir: str, fingerprint_: str) -> ObservationStore:
    """A worker opens each store once (the fingerprint keys the cache: a rewritten store is reopened)."""
    store = open_store(store_dir)
    if store.fingerprint != fingerprint_:
        raise InputError(store_dir, "the observation store changed during the fit")
    return store


def fit_chunk_task(store_dir: str, fingerprint_: str, partial: str, index: int, settings: FitSettings,
                   table: MaterialTable | None, level: float) -> int | StoreDamaged:
    """Fit chunk `index` of a store and write it to the checkpoint `partial` (atomically); a Dask task.
    Returns `index`, or the `StoreDamaged` its read raised (returned, not raised: the driver repairs
    the store, and Dask neither retries the task nor logs an error)."""
    store = _worker_store(store_dir, fingerprint_)
    source = TexelSource.of_store(store)
    try:
        plan = plan_chunks(source.size, settings, source.mask)  # this process's devices
        data = read_chunk(source.read, plan, index)
    except StoreDamaged as damaged:
        return damaged
    Checkpoint(partial).save(index, fit_chunk(*data, plan, index, source.light_dirs, source.view_dir, settings, table,
                                              level))
    return index


class DaskChunks:
    """The chunk engine's executor on a Dask cluster (`fitting.engine.fit_source`'s `executor`):
    one task per chunk, which writes its own checkpoint file; each is loaded back as it completes.
    The source must be an observation store (workers read it from its path)."""

    def __init__(self, client):
        self.client = client

    def __call__(self, source: TexelSource, plan: ChunkPlan, checkpoint: Checkpoint, settings: FitSettings,
                 table: MaterialTable | None, level: float):
        import distributed

        store, client = source.store, self.client
        table = None if table is None else jax.tree.map(np.asarray, table)   # plain arrays to the workers

        def fit_todo(todo: list[int]):
            futures = [client.submit(fit_chunk_task, str(store.path.resolve()), store.fingerprint,
                                     str(checkpoint.directory.resolve()), i, settings, table, level, pure=False,
                                     retries=2)
                       for i in todo]
            for future in distributed.as_completed(futures):
                i = future.result()
                if isinstance(i, StoreDamaged):
                    raise i
                fit = checkpoint.load(i, plan.counts[i])
                if fit is None:
                    raise OSError(f"{checkpoint.path(i)}: a worker's chunk is missing or unreadable "
                                  "(is BTF_DIR on a path the workers share?)")
                yield i, fit

        return fit_todo

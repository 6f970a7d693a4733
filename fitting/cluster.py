"""The scheduler choice of a fit: this process, or a Dask distributed cluster.

`scheduler` everywhere in `fitting` is one of
- `None`: fit in this process (no cluster, no Dask import);
- a `distributed.Client`: use it (it is not closed);
- an address such as "tcp://HOST:PORT": connect to a cluster started with Dask's own commands
  (`dask scheduler`; `dask worker tcp://HOST:PORT --nthreads 1` on every machine);
- an int N >= 1: start a `distributed.LocalCluster` of N worker processes of one thread each,
  closed at the end.
A worker runs one tile (one `--chunk` of texels) at a time, with XLA's own threads inside it:
hence one Dask thread per worker.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

__all__ = ["dask_client", "describe_scheduler"]


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

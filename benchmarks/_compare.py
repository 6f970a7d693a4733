"""Fair timing of our kernels against their peers: the same cores on both sides, runs interleaved so
that the load of a shared machine falls on both, wall and CPU time, min / median / max.

    from _compare import equal_cores          # FIRST, before numpy / jax / numba are imported
    cores = equal_cores()                     # reads --cores 1|2 from sys.argv (default 2)
    ...
    from _compare import compare, fmt
    stats = compare({"ours": lambda: f(x), "numba": lambda: g(x)}, repeats=7)
    print(fmt(stats["ours"]))

`--cores 1`: the process re-executes itself pinned to core 0 (`taskset -c 0`) with XLA's CPU
thread pools at one thread (`--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1`)
and numba / OpenMP / BLAS at one thread. `--cores 2`: nothing pinned, XLA's default pools (both
cores), numba `parallel=True` kernels on 2 threads, BLAS free.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import statistics
import sys
import time
from collections.abc import Callable

_PINNED = "BENCH_PINNED_CORES"


def equal_cores(default: int = 2) -> int:
    """Parse --cores from sys.argv (removing it) and set the thread counts of every library to it;
    for 1 core re-execute under `taskset -c 0`. Call before numpy, jax or numba is imported."""
    import multiprocessing

    cores = default
    if multiprocessing.parent_process() is not None or "--multiprocessing-fork" in sys.orig_argv:
        # a pool worker re-importing the script: its parent set its thread counts (a spawned worker imports
        # the script before parent_process() is set, hence the interpreter's own argument as well)
        return cores
    if "--cores" in sys.argv:
        i = sys.argv.index("--cores")
        cores = int(sys.argv[i + 1])
    if cores not in (1, 2):
        raise SystemExit("--cores must be 1 or 2")
    threads = str(cores)
    for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = threads
    if cores == 1 and os.environ.get(_PINNED) != "1":
        flags = os.environ.get("XLA_FLAGS", "")
        os.environ["XLA_FLAGS"] = (flags + " --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1").strip()
        os.environ[_PINNED] = "1"
        if shutil.which("taskset") is None:
            raise SystemExit("--cores 1 needs taskset (util-linux)")
        os.execvp("taskset", ["taskset", "-c", "0", sys.executable, *sys.argv])
    return cores


def load() -> float:
    """The 1-minute load average (the machine is shared: every timing is reported with it)."""
    return os.getloadavg()[0]


@dataclasses.dataclass
class Stats:
    compile_s: float
    wall: list[float]
    cpu: list[float]

    def summary(self, which: str = "wall") -> tuple[float, float, float]:
        xs = getattr(self, which)
        return min(xs), statistics.median(xs), max(xs)


def _block(x):
    if hasattr(x, "block_until_ready") or isinstance(x, (tuple, list, dict)):
        import jax

        return jax.block_until_ready(x)
    return x


def compare(fns: dict[str, Callable[[], object]], repeats: int) -> dict[str, Stats]:
    """Call each function once (compilation apart), then `repeats` rounds calling each once in turn;
    per call the wall time (perf_counter) and this process's CPU time (all its threads)."""
    stats = {}
    for name, fn in fns.items():
        start = time.perf_counter()
        _block(fn())
        stats[name] = Stats(time.perf_counter() - start, [], [])
    for _ in range(repeats):
        for name, fn in fns.items():
            w, c = time.perf_counter(), time.process_time()
            _block(fn())
            stats[name].wall.append(time.perf_counter() - w)
            stats[name].cpu.append(time.process_time() - c)
    return stats


def fmt(s: Stats, scale: float = 1.0, unit: str = "s") -> str:
    """'wall a / b / c, CPU d / e / f (min / median / max)'."""
    w = "/".join(f"{x * scale:.4g}" for x in s.summary("wall"))
    c = "/".join(f"{x * scale:.4g}" for x in s.summary("cpu"))
    return f"wall {w} {unit}, CPU {c} {unit}"


def ratio(peer: Stats, ours: Stats, which: str = "wall") -> tuple[float, float, float]:
    """peer / ours: (at the medians, worst case = peer min / our max, best case = peer max / our min)."""
    pmin, pmed, pmax = peer.summary(which)
    omin, omed, omax = ours.summary(which)
    return pmed / omed, pmin / omax, pmax / omin

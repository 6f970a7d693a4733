"""Headline rows of a benchmark as JSON, for `run_all.py` to rebuild RESULTS.md's summary table.

API (one function):

    from _results import write_results   # benchmarks/ is on sys.path when a script runs
    write_results("desert_shadows", [
        dict(area="desert", target="horizon maps 256x256x8 >= 10x numpy",
             measured="12.5x wall (10.7-12.9x) ...", status="met",
             notes="peer: numba sweep, both pinned to core 0", figures={"ratio_median": 12.5}),
    ], quick=args.quick)

Each row needs `area` (one of AREAS: the table of RESULTS.md it belongs to), `target` (together
they name the row: keep them stable), `measured` (the figure) and `status` (the verdict: "met",
"missed", ...); `notes` (text, shown after the figure) and `figures` (numbers, for machines) are
optional. The file
`benchmarks/results/<name>.json` gets the rows plus the date, the command line, the CPU
(`cpu_description`: model and vector extension) and the machine load (`os.getloadavg`, the
machine is shared) at the time of writing. A script that ran on an accelerator (JAX's default backend
not the CPU, e.g. `benchmarks/gpu_check.sh`) writes results/<name>_<backend>.json instead, each row's
target marked with the device and the device named before the host CPU: a GPU figure never replaces
a CPU one. With `quick=True`, or when
the environment variable BENCH_NO_RESULTS is set (`run_all.py --quick` sets it), nothing is
written: smoke runs never overwrite measured figures, unless BENCH_RESULTS_DIR names another
directory (`run_all.py --quick` sets it to a scratch directory and checks what lands there), where
the rows are written whatever `quick` says. Returns the path written, or None.
"""

from __future__ import annotations

import datetime
import json
import os
import sys
from pathlib import Path

RESULTS_DIR = Path(__file__).parent / "results"
_REQUIRED = ("area", "target", "measured", "status")
AREAS = {  # area -> heading of its table in RESULTS.md
    "shafts": "Light shafts (paper 000)",
    "desert": "Desert (paper 001)",
    "fitting": "Fitting woven fabric (paper 004)",
    "noh": "Takigi Noh (paper 004)",
    "tools": "Formats and tools",
}
_VECTOR_FLAGS = ("avx512f", "avx2", "avx", "sse4_2", "asimd", "sve")  # widest first


def cpu_description() -> str:
    """The CPU a figure came from: model and widest vector extension, e.g. 'AMD EPYC 9B14 (AVX-512)'
    (machines of one kind differ; JAX's and the peers' code paths differ with the vector width)."""
    import platform

    model, flags = platform.processor() or platform.machine(), set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and model in ("", platform.machine(), platform.processor()):
                model = value.strip()
            elif key.strip() in ("flags", "Features") and not flags:
                flags = set(value.split())
    except OSError:
        pass
    widest = next((f for f in _VECTOR_FLAGS if f in flags), None)
    names = {"avx512f": "AVX-512", "avx2": "AVX2", "avx": "AVX", "sse4_2": "SSE4.2", "asimd": "NEON", "sve": "SVE"}
    return f"{model} ({names[widest]})" if widest else model


def accelerator() -> tuple[str, str] | None:
    """(device, backend) the script's JAX computes on, e.g. ('NVIDIA H200', 'gpu'); None on the CPU
    backend or when the script has not imported JAX."""
    jax = sys.modules.get("jax")
    if jax is None or jax.default_backend() == "cpu":
        return None
    return jax.devices()[0].device_kind, jax.default_backend()


def write_results(name: str, rows: list[dict], *, quick: bool = False, update: bool = False) -> Path | None:
    """Write `rows` (the script's headline rows, see the module docstring) to results/<name>.json;
    `update`: replace only the rows of the same targets in an existing file (a script's rerun of
    some sections), each marked with the run that measured it."""
    for row in rows:
        missing = [k for k in _REQUIRED if not isinstance(row.get(k), str) or not row[k]]
        if missing:
            raise ValueError(f"{name}: result row {row!r} lacks text for {missing}")
        if row["area"] not in AREAS:
            raise ValueError(f"{name}: result row area {row['area']!r} is not one of {list(AREAS)}")
    redirect = os.environ.get("BENCH_RESULTS_DIR")  # `run_all.py --quick`: a scratch directory, checked there
    if not redirect and (quick or os.environ.get("BENCH_NO_RESULTS")):
        return None
    directory = Path(redirect) if redirect else RESULTS_DIR
    cpu, on = cpu_description(), accelerator()
    if on:  # its own file and marked rows: the targets are stated for 2 CPU cores
        device, backend = on
        name, cpu = f"{name}_{backend}", f"{device} (JAX {backend}), host {cpu}"
        rows = [{**row, "target": f"{row['target']} [on {device}]"} for row in rows]
    script = f"benchmarks/{Path(sys.argv[0]).name}"  # the one that ran: noh_frame.py --moving writes noh_frame_moving
    record = {
        "script": script,
        "command": "python " + " ".join([script, *sys.argv[1:]]),
        "date_utc": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M"),
        "load_average_1_5_15": [round(x, 2) for x in os.getloadavg()],
        "cpu_count": os.cpu_count(),
        "cpu": cpu,
        "rows": rows,
    }
    directory.mkdir(exist_ok=True)
    path = directory / f"{name}.json"
    if update and path.exists():  # a rerun of some rows: they carry this run, the others keep theirs
        previous = json.loads(path.read_text())
        run = {k: record[k] for k in ("command", "date_utc", "load_average_1_5_15", "cpu")}
        fresh = {row["target"]: {**row, "run": run} for row in rows}
        kept = [fresh.pop(row["target"], row) for row in previous["rows"]]
        record = {**previous, "rows": kept + list(fresh.values())}
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(record, indent=1, ensure_ascii=False) + "\n")
    tmp.replace(path)  # never a half-written file
    return path

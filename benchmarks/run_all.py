"""Run every benchmark and rebuild the tables of benchmarks/RESULTS.md from their results.

    python benchmarks/run_all.py --quick        # every script with --quick (small sizes): do they
                                                # still run? writes nothing into RESULTS.md or results/:
                                                # their result rows go to a scratch directory, checked;
                                                # compiles cached in ~/.cache/jaxrender-bench-quick
    python benchmarks/run_all.py                # every script at full size (long), then the tables
    python benchmarks/run_all.py --table-only   # rebuild the tables from benchmarks/results/*.json
    python benchmarks/run_all.py --only horizon_speed,fit_speed   # a subset, then the tables

The scripts are the `benchmarks/*.py` not starting with `_` (this one excepted), so new scripts are
included without registering them. Each writes its headline rows with `_results.write_results` to
results/NAME.json; each area's table in RESULTS.md (between its `<!-- table:AREA -->` and
`<!-- /table:AREA -->` markers) is rebuilt from every row of that area: target, figure, status, CPU,
date and command all come from the JSON, so every row of the tables has a script that remakes it.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from _results import AREAS

HERE = Path(__file__).resolve().parent
RESULTS_MD = HERE / "RESULTS.md"
RESULTS_DIR = HERE / "results"
HEADER = ["target", "figure", "status", "CPU", "date (UTC)", "command"]


# The longest --quick runs (CPU seconds, empty compile cache, two at once, 2026-11-24 02:40: em_pyramid 24,
# fit_speed 22, noh_frame 22, shafts_interactive 21, capture_scale 19; the others 3-15 s) start first, so that
# with two at once the run does not end on one long script while the other core idles; the rest follow in
# name order.
LONGEST_FIRST = ("em_pyramid", "fit_speed", "noh_frame", "shafts_interactive", "capture_scale")


def scripts() -> list[Path]:
    found = sorted(p for p in HERE.glob("*.py") if not p.name.startswith("_") and p.name != Path(__file__).name)
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    return sorted(found, key=lambda p: (rank.get(p.stem, len(rank)), p.name))


def _fingerprint() -> dict[str, str]:
    """Hash of RESULTS.md and of each file in results/: --quick must leave all of them untouched."""
    paths = [RESULTS_MD] + (sorted(RESULTS_DIR.glob("*")) if RESULTS_DIR.exists() else [])
    return {str(p.relative_to(HERE)): hashlib.sha256(p.read_bytes()).hexdigest() for p in paths if p.is_file()}


def quick_compile_cache() -> str:
    """JAX's persistent compilation cache for --quick runs: $JAX_COMPILATION_CACHE_DIR if set, else
    ~/.cache/jaxrender-bench-quick. Compiles are most of a smoke run's time; a warm cache halved the CPU time
    of the whole run (290 -> 156 s, 2026-11-24). Keyed by JAX on the program, the options and the versions."""
    return os.environ.get("JAX_COMPILATION_CACHE_DIR") or str(
        Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "jaxrender-bench-quick")


def run_script(path: Path, quick: bool, timeout: float | None, results_dir: Path | None = None,
               compile_cache: str | None = None) -> tuple[str, int, float, float, str]:
    """(name, exit code, wall seconds, CPU seconds of the script and every process it started, output tail)."""
    env = dict(os.environ)
    if quick:
        env["BENCH_NO_RESULTS"] = "1"
    if compile_cache:
        env["JAX_COMPILATION_CACHE_DIR"] = compile_cache
    if results_dir is not None:  # the scripts' result rows go there instead (`_results.write_results`)
        env["BENCH_RESULTS_DIR"] = str(results_dir)
    cmd = [sys.executable, str(path)] + (["--quick"] if quick else [])
    start = time.perf_counter()
    with tempfile.TemporaryFile("w+") as out:
        # its own session, so that a timeout ends the script's children too; os.wait4 gives the CPU time of the
        # script and of its waited-for descendants (JAX's threads, child processes, pool workers)
        proc = subprocess.Popen(cmd, cwd=HERE.parent, env=env, stdout=out, stderr=subprocess.STDOUT, text=True,
                                start_new_session=True)
        fired = threading.Event()

        def kill():
            fired.set()
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)

        timer = threading.Timer(timeout, kill) if timeout else None
        if timer:
            timer.start()
        _, status, usage = os.wait4(proc.pid, 0)
        if timer:
            timer.cancel()
        proc.returncode = code = 124 if fired.is_set() else os.waitstatus_to_exitcode(status)
        out.seek(0)
        tail = out.read()[-2000:] + (f"\ntimed out after {timeout:.0f} s" if fired.is_set() else "")
    return path.name, code, time.perf_counter() - start, usage.ru_utime + usage.ru_stime, tail


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def markers(area: str) -> tuple[str, str]:
    return f"<!-- table:{area} -->", f"<!-- /table:{area} -->"


def area_tables(results: list[dict]) -> dict[str, list[str]]:
    """Markdown table lines per area, one row per result row, in the order of the result files."""
    rows: dict[str, list[str]] = {}
    for rec in results:
        for res in rec["rows"]:
            run = {**rec, **res.get("run", {})}  # a row rerun alone (a script's --sections) carries its own run
            load = run.get("load_average_1_5_15", [float("nan")])[0]
            figure = res["measured"] + (f" ({res['notes']})" if res.get("notes") else "")
            cells = [res["target"], figure, res["status"], f"{run.get('cpu', 'not recorded')}, load {load:.1f}",
                     run["date_utc"], f"`{run['command']}`"]
            rows.setdefault(res["area"], []).append("| " + " | ".join(_cell(c) for c in cells) + " |")
    head = ["| " + " | ".join(HEADER) + " |", "|" + "---|" * len(HEADER)]
    return {area: head + lines for area, lines in rows.items()}


def check_results(directory: Path) -> list[str]:
    """Problems with the result files a --quick run wrote into `directory` (each must load, name its script and
    carry rows with a known area, target, measured and status), and the tables must build from them."""
    problems, records = [], []
    for path in sorted(directory.glob("*.json")):
        try:
            rec = json.loads(path.read_text())
            assert (HERE.parent / rec["script"]).is_file(), f"script {rec['script']!r} not found"
            assert rec["rows"], "no rows"
            for row in rec["rows"]:
                missing = [k for k in ("area", "target", "measured", "status") if not row.get(k)]
                assert not missing, f"a row lacks {missing}"
                assert row["area"] in AREAS, f"unknown area {row['area']!r}"
            records.append(rec)
        except (ValueError, KeyError, AssertionError) as err:
            problems.append(f"{path.name}: {err}")
    tables = area_tables(records)
    if sum(len(t) - 2 for t in tables.values()) != sum(len(rec["rows"]) for rec in records):
        problems.append("the tables do not have one row per result row")
    return problems


def rebuild_tables() -> None:
    """Replace each area's table in RESULTS.md by the one built from results/*.json."""
    text = RESULTS_MD.read_text()
    results = [json.loads(p.read_text()) for p in sorted(RESULTS_DIR.glob("*.json"))]
    tables = area_tables(results)
    for area in AREAS:
        begin, end = markers(area)
        if begin not in text or end not in text:
            raise SystemExit(f"{RESULTS_MD}: no {begin} ... {end} markers for the {area} table")
        head, rest = text.split(begin, 1)
        tail = rest.split(end, 1)[1]
        text = head + begin + "\n" + "\n".join(tables.get(area, ["(no results yet)"])) + "\n" + end + tail
    RESULTS_MD.write_text(text)
    print(f"{RESULTS_MD}: tables rebuilt from {len(results)} result files")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke run: every script with --quick, nothing written")
    parser.add_argument("--table-only", action="store_true", help="only rebuild the tables")
    parser.add_argument("--only", default=None, help="comma-separated script names (without .py)")
    parser.add_argument("--jobs", type=int, default=2 if "--quick" in (argv or sys.argv) else 1,
                        help="scripts at once (default 2 with --quick, else 1 so timings do not compete)")
    parser.add_argument("--timeout", type=float, default=None, help="seconds per script (default 170 quick, none)")
    parser.add_argument("--no-compile-cache", action="store_true",
                        help="--quick: without JAX's persistent compilation cache (see quick_compile_cache)")
    parser.add_argument("--results-dir", type=Path, default=None,
                        help="--quick: where the scripts write their result rows (default: a temporary directory)")
    args = parser.parse_args(argv)
    if args.table_only:
        rebuild_tables()
        return 0
    todo = scripts()
    if args.only:
        names = {n.strip().removesuffix(".py") for n in args.only.split(",")}
        todo = [p for p in todo if p.stem in names]
        missing = names - {p.stem for p in todo}
        if missing:
            print(f"run_all: no benchmark script named {sorted(missing)}", file=sys.stderr)
            return 2
    before = _fingerprint() if args.quick else None
    timeout = args.timeout or (170.0 if args.quick else None)
    start = time.perf_counter()
    scratch = tempfile.TemporaryDirectory() if args.quick and args.results_dir is None else None
    results_dir = Path(scratch.name) if scratch else args.results_dir
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        cache = quick_compile_cache() if args.quick and not args.no_compile_cache else None
        outcomes = list(pool.map(lambda p: run_script(p, args.quick, timeout, results_dir, cache), todo))
    failed = [o for o in outcomes if o[1] != 0]
    for name, code, secs, cpu, _ in sorted(outcomes):
        print(f"{'ok  ' if code == 0 else 'FAIL'} {name:28s} {secs:6.1f} s wall {cpu:6.1f} s CPU"
              + (f" (exit {code})" if code else ""))
    for name, code, _, _, tail in failed:
        print(f"\n--- {name} (exit {code}) ---\n{tail}", file=sys.stderr)
    print(f"{len(outcomes)} scripts in {time.perf_counter() - start:.0f} s ({sum(o[3] for o in outcomes):.0f} s CPU, "
          f"load {os.getloadavg()[0]:.1f}), {len(failed)} failed")
    if args.quick:
        written = sorted(p.stem for p in results_dir.glob("*.json"))
        problems = check_results(results_dir)
        if scratch:
            scratch.cleanup()
        print(f"result rows written (to {'a scratch directory' if scratch else results_dir}) by: {', '.join(written)}")
        if problems:
            print("run_all --quick: " + "; ".join(problems), file=sys.stderr)
            return 1
        after = _fingerprint()
        changed = sorted(k for k in set(before) | set(after) if before.get(k) != after.get(k))
        if changed:  # (in a shared checkout, someone else's edit meanwhile shows up here too)
            print(f"run_all --quick: {', '.join(changed)} changed during the run (a --quick run must write "
                  "neither RESULTS.md nor results/)", file=sys.stderr)
            return 1
    elif not failed or args.only:
        rebuild_tables()
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

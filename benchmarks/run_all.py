"""Run every benchmark and rebuild the summary table of benchmarks/RESULTS.md from their results.

    python benchmarks/run_all.py --quick        # every script with --quick (small sizes): do they
                                                # still run? writes nothing into RESULTS.md or results/:
                                                # their result rows go to a scratch directory, checked;
                                                # compiles cached in ~/.cache/jaxrender-bench-quick
    python benchmarks/run_all.py                # every script at full size (long), then the table
    python benchmarks/run_all.py --table-only   # rebuild the table from benchmarks/results/*.json
    python benchmarks/run_all.py --only horizon_speed,fit_speed   # a subset, then the table

The scripts are the `benchmarks/*.py` not starting with `_` (this one excepted), so new scripts are
included without registering them. Each writes its headline rows with `_results.write_results` to
results/NAME.json; the table between the `summary:begin/end` markers of RESULTS.md gets one row
per result row, matched by (issue, target): the measured text and verdict come from the JSON, and
table rows no script writes are kept as they are (their verdict and notes included).
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

HERE = Path(__file__).resolve().parent
RESULTS_MD = HERE / "RESULTS.md"
RESULTS_DIR = HERE / "results"
BEGIN, END = "<!-- summary:begin -->", "<!-- summary:end -->"
HEADER = ["issue", "target", "measured", "status", "notes"]


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


def _split_row(line: str) -> list[str]:
    cells, cur, escaped = [], "", False
    for ch in line.strip()[1:-1]:
        if ch == "|" and not escaped:
            cells.append(cur.strip())
            cur = ""
        else:
            cur += ch
        escaped = ch == "\\"
    return cells + [cur.strip()]


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def summary_table(old_rows: list[list[str]], results: list[dict]) -> list[str]:
    """The new table: old rows in their order, updated from `results` where (issue, target)
    match; result rows with no old row appended."""
    rows = [r + [""] * (len(HEADER) - len(r)) for r in old_rows]
    index = {(r[0], r[1]): i for i, r in enumerate(rows)}
    for rec in results:
        for res in rec["rows"]:
            load = rec.get("load_average_1_5_15", [float("nan")])[0]
            cpu = rec.get("cpu", "CPU not recorded")
            measured = f"{res['measured']} [{rec['date_utc']} UTC, {cpu}, load {load:.1f}, `{rec['command']}`]"
            cells = [res["issue"], res["target"], measured, res["status"], res.get("notes", "")]
            key = (_cell(res["issue"]), _cell(res["target"]))
            if key in index:
                old = rows[index[key]]
                rows[index[key]] = [_cell(c) for c in cells[:4]] + [_cell(cells[4]) or old[4]]
            else:
                index[key] = len(rows)
                rows.append([_cell(c) for c in cells])
    lines = ["| " + " | ".join(HEADER) + " |", "|" + "---|" * len(HEADER)]
    return lines + ["| " + " | ".join(r) + " |" for r in rows]


def check_results(directory: Path) -> list[str]:
    """Problems with the result files a --quick run wrote into `directory` (each must load, name its script and
    carry rows with issue, target, measured and status), and the summary table must build from them."""
    problems, records = [], []
    for path in sorted(directory.glob("*.json")):
        try:
            rec = json.loads(path.read_text())
            assert (HERE.parent / rec["script"]).is_file(), f"script {rec['script']!r} not found"
            assert rec["rows"], "no rows"
            for row in rec["rows"]:
                missing = [k for k in ("issue", "target", "measured", "status") if not row.get(k)]
                assert not missing, f"a row lacks {missing}"
            records.append(rec)
        except (ValueError, KeyError, AssertionError) as err:
            problems.append(f"{path.name}: {err}")
    table = summary_table([], records)
    if len(table) != 2 + len({(_cell(r["issue"]), _cell(r["target"])) for rec in records for r in rec["rows"]}):
        problems.append("the summary table does not have one row per result row")
    return problems


def rebuild_table() -> None:
    text = RESULTS_MD.read_text()
    if BEGIN not in text or END not in text:
        raise SystemExit(f"{RESULTS_MD}: no {BEGIN} ... {END} markers around the summary table")
    head, rest = text.split(BEGIN, 1)
    body, tail = rest.split(END, 1)
    old = [_split_row(ln) for ln in body.splitlines() if ln.startswith("|") and not ln.startswith("|---")]
    old = [r for r in old if [c.lower() for c in r[:2]] != ["issue", "target"]]
    results = [json.loads(p.read_text()) for p in sorted(RESULTS_DIR.glob("*.json"))]
    table = summary_table(old, results)
    RESULTS_MD.write_text(head + BEGIN + "\n" + "\n".join(table) + "\n" + END + tail)
    print(f"{RESULTS_MD}: summary table rebuilt from {len(results)} result files")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke run: every script with --quick, nothing written")
    parser.add_argument("--table-only", action="store_true", help="only rebuild the summary table")
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
        rebuild_table()
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
        rebuild_table()
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

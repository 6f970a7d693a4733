"""Every benchmark script still runs: `benchmarks/run_all.py --quick` runs each `benchmarks/*.py`
(not starting with `_`) with --quick at a small size; none may write into benchmarks/RESULTS.md or
benchmarks/results/, and the result rows they write go to a scratch directory where they are
checked (complete rows, a summary table built from them). Also the summary-table rebuild on a
scratch copy of RESULTS.md."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# Not a speed claim (no timed asserts): CI's budget for the smoke run is 3 minutes; this only stops a hang,
# with room for a loaded machine (the run took 294 s inside a parallel pytest run before the --quick cuts).
HANG_GUARD_S = 600


def test_run_all_quick_runs_every_script_and_writes_nothing(tmp_path):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import run_all

    before = run_all._fingerprint()
    rows_dir = tmp_path / "rows"
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "run_all.py"), "--quick", "--results-dir",
                           str(rows_dir)], cwd=ROOT, capture_output=True, text=True, timeout=HANG_GUARD_S)
    print(proc.stdout)  # each script's wall and CPU seconds (shown with pytest -rA)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    names = {p.name for p in run_all.scripts()}
    ran = {line.split()[1] for line in proc.stdout.splitlines() if line.startswith("ok ")}
    assert ran == names  # every script ran to the end with exit code 0
    assert run_all._fingerprint() == before  # RESULTS.md and results/ untouched
    written = {p.stem for p in rows_dir.glob("*.json")}
    # the scripts whose quick run reaches write_results (their rows went to the scratch directory, not results/)
    assert {"fit_speed", "ripples_speed", "ripples_wavelength", "shafts_vs_mitsuba"} <= written, written
    assert run_all.check_results(rows_dir) == []  # each loads, has complete rows, and the table builds from them


def test_summary_table_keeps_rows_and_takes_measured_figures(tmp_path, monkeypatch):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import run_all

    md = tmp_path / "RESULTS.md"
    md.write_text("# x\n\n" + run_all.BEGIN + "\n| issue | target | measured | status |\n|---|---|---|---|\n"
                  "| 1 a | kept row | 3 s | met |\n| 2 b | updated row | old | met |\n" + run_all.END + "\n\nrest\n")
    results = tmp_path / "results"
    results.mkdir()
    rec = {"date_utc": "2026-11-23 21:00", "command": "python benchmarks/x.py", "load_average_1_5_15": [3.0, 2, 1],
           "cpu": "AMD EPYC 9B14 (AVX-512)",
           "rows": [{"issue": "2 b", "target": "updated row", "measured": "1.5x", "status": "missed"},
                    {"issue": "3 c", "target": "new row", "measured": "2x", "status": "met", "notes": "n"},
                    # a row rerun alone (write_results(update=True)) carries its own run
                    {"issue": "3 c", "target": "rerun row", "measured": "3x", "status": "met",
                     "run": {"date_utc": "2026-11-24 01:00", "command": "python benchmarks/x.py --sections y",
                             "load_average_1_5_15": [1.0, 1, 1], "cpu": "Intel Xeon (AVX-512)"}}]}
    (results / "x.json").write_text(json.dumps(rec))
    monkeypatch.setattr(run_all, "RESULTS_MD", md)
    monkeypatch.setattr(run_all, "RESULTS_DIR", results)
    run_all.rebuild_table()
    text = md.read_text()
    assert "| 1 a | kept row | 3 s | met |  |" in text
    assert ("| 2 b | updated row | 1.5x [2026-11-23 21:00 UTC, AMD EPYC 9B14 (AVX-512), load 3.0, "
            "`python benchmarks/x.py`] | missed |  |") in text
    assert "| 3 c | new row | 2x" in text and text.endswith(run_all.END + "\n\nrest\n")
    assert ("| 3 c | rerun row | 3x [2026-11-24 01:00 UTC, Intel Xeon (AVX-512), load 1.0, "
            "`python benchmarks/x.py --sections y`] | met |") in text


def test_write_results_update_replaces_only_the_rerun_rows(tmp_path, monkeypatch):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import _results

    monkeypatch.setenv("BENCH_RESULTS_DIR", str(tmp_path))
    rows = [{"issue": "9 x", "target": t, "measured": m, "status": "met"} for t, m in (("a", "1"), ("b", "2"))]
    _results.write_results("x", rows)
    _results.write_results("x", [{"issue": "9 x", "target": "b", "measured": "3", "status": "missed"}], update=True)
    rec = json.loads((tmp_path / "x.json").read_text())
    assert [(r["target"], r["measured"], "run" in r) for r in rec["rows"]] == [("a", "1", False), ("b", "3", True)]

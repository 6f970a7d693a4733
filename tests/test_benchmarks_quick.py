"""Every benchmark script still runs: `benchmarks/run_all.py --quick` runs each `benchmarks/*.py`
(not starting with `_`) with --quick at a small size, and checks that none writes into
benchmarks/RESULTS.md or benchmarks/results/. Also the summary-table rebuild on a scratch copy."""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HANG_GUARD_S = 900  # not a speed claim: CI's budget for the smoke run is 3 minutes; this only stops a hang


def test_run_all_quick_runs_every_script_and_writes_nothing():
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "run_all.py"), "--quick"], cwd=ROOT,
                          capture_output=True, text=True, timeout=HANG_GUARD_S)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    names = {p.name for p in (ROOT / "benchmarks").glob("*.py") if not p.name.startswith("_")} - {"run_all.py"}
    ran = {line.split()[1] for line in proc.stdout.splitlines() if line.startswith("ok ")}
    assert ran == names


def test_summary_table_keeps_rows_and_takes_measured_figures(tmp_path, monkeypatch):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import run_all

    md = tmp_path / "RESULTS.md"
    md.write_text("# x\n\n" + run_all.BEGIN + "\n| issue | target | measured | status |\n|---|---|---|---|\n"
                  "| 1 a | kept row | 3 s | met |\n| 2 b | updated row | old | met |\n" + run_all.END + "\n\nrest\n")
    results = tmp_path / "results"
    results.mkdir()
    rec = {"date_utc": "2026-11-23 21:00", "command": "python benchmarks/x.py", "load_average_1_5_15": [3.0, 2, 1],
           "rows": [{"issue": "2 b", "target": "updated row", "measured": "1.5x", "status": "missed"},
                    {"issue": "3 c", "target": "new row", "measured": "2x", "status": "met", "notes": "n"}]}
    (results / "x.json").write_text(json.dumps(rec))
    monkeypatch.setattr(run_all, "RESULTS_MD", md)
    monkeypatch.setattr(run_all, "RESULTS_DIR", results)
    run_all.rebuild_table()
    text = md.read_text()
    assert "| 1 a | kept row | 3 s | met |  |" in text
    assert "| 2 b | updated row | 1.5x [2026-11-23 21:00 UTC, load 3.0, `python benchmarks/x.py`] | missed |  |" in text
    assert "| 3 c | new row | 2x" in text and text.endswith(run_all.END + "\n\nrest\n")

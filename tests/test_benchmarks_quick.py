"""Every benchmark script still runs: each `benchmarks/*.py` (not starting with `_`) with --quick at a
small size, one test per script (so that the test workers share them out), the way
`benchmarks/run_all.py --quick` runs them (`run_all.run_script`); none may write into
benchmarks/RESULTS.md or benchmarks/results/, and the result rows they write go to a scratch
directory where they are checked (complete rows, a summary table built from them). `run_all.py
--quick` itself, on one script; the summary-table rebuild on a scratch copy of RESULTS.md."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import run_all  # noqa: E402

# Not a speed claim (no timed asserts): only stops a hang, with room for a slow, loaded machine.
HANG_GUARD_S = 900
# the scripts whose quick run reaches write_results (their rows go to the scratch directory, not results/)
WRITE_ROWS = {"fit_speed", "ripples_speed", "ripples_wavelength", "shafts_vs_mitsuba"}


# The scripts by area, each area a class: under `--dist loadscope` the test workers share the classes out.
AREA_PREFIXES = {"noh": ("noh_",), "shafts": ("shafts_",), "fitting": ("fit_", "em_", "capture_", "real_"),
                 "desert": ("desert_", "dunes_", "ripples_", "horizon_")}


def scripts_of(area: str) -> list[Path]:
    """The benchmark scripts of `area`; "other": those of no area above (a new script is never left out)."""
    def area_of(path: Path) -> str:
        return next((a for a, prefixes in AREA_PREFIXES.items() if path.stem.startswith(prefixes)), "other")
    return [p for p in run_all.scripts() if area_of(p) == area]


def check_script(script: Path, tmp_path: Path) -> None:
    """`script --quick` exits 0, writes nothing into RESULTS.md or results/, and its result rows (in a
    scratch directory) are complete and build a table."""
    before = run_all._fingerprint()
    rows_dir = tmp_path / "rows"
    rows_dir.mkdir()
    name, code, wall, cpu, tail = run_all.run_script(script, True, HANG_GUARD_S, rows_dir,
                                                     os.environ.get("JAX_COMPILATION_CACHE_DIR"))
    print(f"{name}: {wall:.1f} s wall, {cpu:.1f} s CPU")  # (shown with pytest -rA)
    assert code == 0, tail
    assert run_all._fingerprint() == before  # RESULTS.md and results/ untouched
    written = {p.stem for p in rows_dir.glob("*.json")}
    assert written <= {script.stem}
    if script.stem in WRITE_ROWS:
        assert written == {script.stem}
    assert run_all.check_results(rows_dir) == []  # it loads, has complete rows, and the table builds from them


def pytest_generate_tests(metafunc):
    if "script" in metafunc.fixturenames:  # each area class runs its own scripts
        metafunc.parametrize("script", scripts_of(metafunc.cls.AREA), ids=lambda p: p.stem)


class _AreaScripts:
    AREA = ""

    def test_benchmark_script_runs_quick(self, script, tmp_path):
        check_script(script, tmp_path)


class TestNohScripts(_AreaScripts):
    AREA = "noh"


class TestShaftsScripts(_AreaScripts):
    AREA = "shafts"


class TestFittingScripts(_AreaScripts):
    AREA = "fitting"


class TestDesertScripts(_AreaScripts):
    AREA = "desert"


class TestOtherScripts(_AreaScripts):
    AREA = "other"


def test_run_all_quick_runs_the_scripts_asked_for(tmp_path):
    rows_dir = tmp_path / "rows"
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "run_all.py"), "--quick", "--only",
                           "ripples_wavelength", "--results-dir", str(rows_dir)], cwd=ROOT, capture_output=True,
                          text=True, timeout=HANG_GUARD_S)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert [line.split()[1] for line in proc.stdout.splitlines() if line.startswith("ok ")] == ["ripples_wavelength.py"]
    assert "1 scripts in" in proc.stdout and "0 failed" in proc.stdout
    assert {p.stem for p in rows_dir.glob("*.json")} == {"ripples_wavelength"}
    bad = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "run_all.py"), "--quick", "--only", "nothing"],
                         cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "no benchmark script named ['nothing']" in bad.stderr


def test_area_tables_rebuilt_from_the_result_rows(tmp_path, monkeypatch):
    md = tmp_path / "RESULTS.md"
    begin_end = {area: run_all.markers(area) for area in run_all.AREAS}
    sections = "".join(f"## {area}\n\n{begin}\n| old | row |\n{end}\n\nhow {area}\n\n"
                       for area, (begin, end) in begin_end.items())
    md.write_text("# x\n\n" + sections + "rest\n")
    results = tmp_path / "results"
    results.mkdir()
    rec = {"script": "benchmarks/run_all.py", "date_utc": "2026-11-23 21:00", "command": "python benchmarks/x.py",
           "load_average_1_5_15": [3.0, 2, 1],
           "cpu": "AMD EPYC 9B14 (AVX-512)",
           "rows": [{"area": "desert", "target": "a row", "measured": "1.5x", "status": "missed"},
                    {"area": "shafts", "target": "with notes", "measured": "2x", "status": "met", "notes": "n|m"},
                    # a row rerun alone (write_results(update=True)) carries its own run
                    {"area": "desert", "target": "rerun row", "measured": "3x", "status": "met",
                     "run": {"date_utc": "2026-11-24 01:00", "command": "python benchmarks/x.py --sections y",
                             "load_average_1_5_15": [1.0, 1, 1], "cpu": "Intel Xeon (AVX-512)"}}]}
    (results / "x.json").write_text(json.dumps(rec))
    monkeypatch.setattr(run_all, "RESULTS_MD", md)
    monkeypatch.setattr(run_all, "RESULTS_DIR", results)
    run_all.rebuild_tables()
    text = md.read_text()
    assert "| old | row |" not in text  # every row comes from a result file
    desert = text.split("## desert")[1].split("how desert")[0]
    assert ("| a row | 1.5x | missed | AMD EPYC 9B14 (AVX-512), load 3.0 | 2026-11-23 21:00 | "
            "`python benchmarks/x.py` |") in desert
    assert ("| rerun row | 3x | met | Intel Xeon (AVX-512), load 1.0 | 2026-11-24 01:00 | "
            "`python benchmarks/x.py --sections y` |") in desert
    assert "| with notes | 2x (n\\|m) | met |" in text.split("## shafts")[1].split("how shafts")[0]
    assert "(no results yet)" in text.split("## noh")[1].split("how noh")[0]
    assert text.endswith("how tools\n\nrest\n")
    assert run_all.check_results(results) == []


def test_write_results_update_replaces_only_the_rerun_rows(tmp_path, monkeypatch):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import _results

    monkeypatch.setenv("BENCH_RESULTS_DIR", str(tmp_path))
    rows = [{"area": "desert", "target": t, "measured": m, "status": "met"} for t, m in (("a", "1"), ("b", "2"))]
    _results.write_results("x", rows)
    _results.write_results("x", [{"area": "desert", "target": "b", "measured": "3", "status": "missed"}], update=True)
    with pytest.raises(ValueError, match="area 'nowhere'"):
        _results.write_results("x", [{"area": "nowhere", "target": "b", "measured": "3", "status": "met"}])
    rec = json.loads((tmp_path / "x.json").read_text())
    assert [(r["target"], r["measured"], "run" in r) for r in rec["rows"]] == [("a", "1", False), ("b", "3", True)]


def test_write_results_on_an_accelerator_keeps_the_cpu_rows(tmp_path, monkeypatch):
    """A run on a GPU writes its own file, each row marked with the device, the device named before the host."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import types

    import _results

    gpu = types.SimpleNamespace(default_backend=lambda: "gpu",
                                devices=lambda: [types.SimpleNamespace(device_kind="NVIDIA H200")])
    monkeypatch.setitem(sys.modules, "jax", gpu)
    monkeypatch.setenv("BENCH_RESULTS_DIR", str(tmp_path))
    path = _results.write_results("x", [{"area": "shafts", "target": "a frame <= 40 ms", "measured": "2 ms",
                                         "status": "met"}])
    assert path == tmp_path / "x_gpu.json" and not (tmp_path / "x.json").exists()
    rec = json.loads(path.read_text())
    assert rec["cpu"] == f"NVIDIA H200 (JAX gpu), host {_results.cpu_description()}"
    assert rec["rows"][0]["target"] == "a frame <= 40 ms [on NVIDIA H200]"

"""examples/real_capture.ipynb runs top to bottom on a DiLiGenT object and its numbers say the fit
generalizes: normals near the laser scan, held-out photographs predicted better than the
least-squares Lambertian fit of the same lights."""

import os
from pathlib import Path

import pytest
from notebook_helpers import assert_outputs_current, last_results, run_notebook

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOK = ROOT / "examples" / "real_capture.ipynb"
# cat, every 3rd row and column (5027 texels), 80 of 96 lights fitted: measured 5.16 deg mean angular
# error (ST14 publishes 6.12 on the whole object with every light; our Lambertian fit 7.41) and a
# held-out error 0.90 of the Lambertian's (5.14 % vs 5.68 %); bounds with margin for other CPUs.
NORMALS_TOL_DEG = 6.12
HELDOUT_RATIO_MAX = 0.95


def test_real_capture_notebook_runs():
    data = Path(os.environ.get("JAXRENDER_DILIGENT", ROOT.parent / "shared" / "data" / "diligent"))
    if not (data / "catPNG").is_dir():
        pytest.fail(f"DiLiGenT data not found at {data}: set JAXRENDER_DILIGENT (see README, 'Real captures')",
                    pytrace=False)
    nb = run_notebook(NOTEBOOK)
    assert_outputs_current(NOTEBOOK, nb, last_results)
    summary = last_results(nb)
    assert summary["normals_deg"] < NORMALS_TOL_DEG, summary
    assert summary["normals_deg"] < summary["lambertian_normals_deg"], summary
    assert summary["heldout"] < HELDOUT_RATIO_MAX * summary["heldout_lambertian"], summary

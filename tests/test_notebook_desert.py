"""Executes examples/desert.ipynb headless, checks the values it computes and that the outputs stored
with it come from its current code."""

from pathlib import Path

import numpy as np
from notebook_helpers import assert_outputs_current, run_notebook, tagged_results

NOTEBOOK = Path(__file__).resolve().parents[1] / "examples" / "desert.ipynb"
GRAD_REL_TOL = 1e-4  # float64, central step 1e-8 on a piecewise-linear function: agrees to ~1e-6


def test_desert_notebook_runs_and_computes():
    nb = run_notebook(NOTEBOOK)
    assert_outputs_current(NOTEBOOK, nb, tagged_results)
    r = tagged_results(nb)
    assert 3.0 < r["ripple_wavelength"] < 64.0
    assert r["sand_conserved"] < 1e-10  # float64 automaton conserves sand
    assert r["horizon_min"] >= 0.0 and r["horizon_max"] > 0.0
    assert 0.0 < r["ripple_shadow_fraction"] < 1.0  # a low sun shadows some texels, not all
    assert r["image_finite"] and r["image_mean"] > 0.0
    assert np.isfinite(r["grad"]) and np.isfinite(r["fd"]) and r["fd"] != 0.0
    assert r["grad_rel_err"] < GRAD_REL_TOL, (r["grad"], r["fd"])

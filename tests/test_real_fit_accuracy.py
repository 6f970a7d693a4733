"""Real-data accuracy of the default fit: two DiLiGenT objects, every 4th row and column,
every 6th light held out. Normals against the laser scan (mean angular error over the mask) and the
held-out photographs predicted against the least-squares Lambertian fit of the same lights
(`fitting.evaluate`, an independent closed form). One compilation: both objects are fitted in
chunks of the same padded shape."""

import os
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fitting
from fitting.evaluate import (
    angular_error_deg,
    heldout_split,
    lambertian_fit,
    read_normal_map,
    relative_rms,
    select_lights,
)

ROOT = Path(__file__).resolve().parents[1]
STRIDE = 4
CHUNK = 512   # both objects' chunks padded alike: one compiled program
# Measured at STRIDE 4 with 80 of 96 lights (2026-11-26, Intel Xeon AVX-512); bounds ~20 % above the
# measured figures, for other CPUs' rounding. Whole objects with every light: benchmarks/RESULTS.md.
TOLERANCES = {
    # normals: measured 1.42 deg (ST14 publishes 1.74 on the whole object); held-out: measured
    # 0.72 of the Lambertian fit's error (7.7 % vs 10.7 %)
    "ball": {"normals_deg": 1.74, "heldout_ratio": 0.85},
    # normals: measured 17.83 deg (ST14 25.44, PS-FCN 15.84); held-out: measured 0.59 of the
    # Lambertian fit's (26.0 % vs 43.8 %)
    "harvest": {"normals_deg": 20.0, "heldout_ratio": 0.7},
}


def _root() -> Path:
    root = Path(os.environ.get("JAXRENDER_DILIGENT", ROOT.parent / "shared" / "data" / "diligent"))
    if not all((root / f"{name}PNG").is_dir() for name in TOLERANCES):
        pytest.fail(f"DiLiGenT data not found at {root}: set JAXRENDER_DILIGENT (see README, 'Real captures')",
                    pytrace=False)
    return root


def _subsampled(obs: fitting.Observations) -> fitting.Observations:
    every = lambda x: x[::STRIDE, ::STRIDE]  # noqa: E731
    return fitting.Observations(ratio=every(obs.ratio), weight=every(obs.weight), light_dirs=obs.light_dirs,
                                view_dir=obs.view_dir, n_valid=every(obs.n_valid),
                                n_saturated=every(obs.n_saturated), n_dark=every(obs.n_dark), mask=every(obs.mask))


def _figures(folder: Path, tmp: Path) -> dict:
    fitting.write_folder_manifest(folder, tmp / "capture.json")
    obs = _subsampled(fitting.merge_capture(fitting.load_capture(tmp), progress=False))
    mask = np.asarray(obs.mask, bool)
    truth = read_normal_map(folder / "Normal_gt.mat")[::STRIDE, ::STRIDE]
    fitted, held = heldout_split(obs.n_lights, 6)
    train, test = select_lights(obs, fitted), select_lights(obs, held)
    maps = fitting.fit_maps(train, fitting.FitSettings(chunk=CHUNK), progress=False)
    texels = jax.tree.map(jnp.asarray, maps).texel()
    predicted = jnp.stack([fitting.relight(texels, d, obs.view_dir) for d in np.asarray(test.light_dirs)], axis=2)
    lambert = lambertian_fit(train)
    return {"normals_deg": angular_error_deg(maps.normal, truth, mask)[0],
            "lambertian_normals_deg": angular_error_deg(np.asarray(lambert.normal), truth, mask)[0],
            "heldout": relative_rms(predicted, test),
            "heldout_lambertian": relative_rms(lambert.predict(test.light_dirs), test)}


@pytest.mark.parametrize("name", sorted(TOLERANCES))
def test_real_object_normals_and_heldout_lights(name, tmp_path):
    figures = _figures(_root() / f"{name}PNG", tmp_path)
    tol = TOLERANCES[name]
    assert figures["normals_deg"] < tol["normals_deg"], figures
    assert figures["normals_deg"] < figures["lambertian_normals_deg"], figures
    assert figures["heldout"] < tol["heldout_ratio"] * figures["heldout_lambertian"], figures

"""`fitting evaluate` (K-fold light cross-validation, `fitting.crossval`): the folds, the figures
against an independent numpy computation, the command end to end on a tiny synthetic capture
(table, PNG, ground truth found), and its one-line errors (exit 2).

One small capture (8 x 8 texels, 24 lights, the plain method) is cross-validated once in process
and once by the command."""

import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fitting import FitSettings, fit_maps, load_capture, merge_capture, relight
from fitting.crossval import cross_validate, light_folds
from fitting.evaluate import read_normal_map, select_lights
from fitting.synth import synth_capture
from jaxrender.io import read_image

FOLDS = 3
PLAIN = FitSettings(method="plain", chunk=64)
FOLD_NORMALS_DEG = 5.0   # a fold's mean normal error: the fit's below (measured 0.17-0.40), Lambertian's above


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return synth_capture(tmp_path_factory.mktemp("evaluate") / "capture", key=jax.random.key(5), size=(8, 8),
                         lights=24, progress=False)


@pytest.fixture(scope="module")
def result(capture):
    obs = merge_capture(load_capture(capture), progress=False)
    truth = read_normal_map(capture / "truth" / "level_00.exr", obs.size)
    return obs, truth, cross_validate(obs, PLAIN, folds=FOLDS, normals=truth, progress=False)


def test_each_light_is_held_out_exactly_once():
    for n, k in ((24, 3), (96, 6), (7, 7), (10, 4)):
        folds = light_folds(n, k)
        assert len(folds) == k and np.array_equal(np.sort(np.concatenate(folds)), np.arange(n))
        assert max(f.size for f in folds) - min(f.size for f in folds) <= 1
    with pytest.raises(ValueError):
        light_folds(5, 6)


def _numpy_rms(maps, obs, lights):
    """||prediction - R|| / ||R|| over the held-out lights' valid observations, in float64 numpy."""
    test = select_lights(obs, lights)
    pred = np.stack([np.asarray(relight(jax.tree.map(jnp.asarray, maps).texel(), d, obs.view_dir), np.float64)
                     for d in np.asarray(test.light_dirs)], axis=2)
    valid = np.asarray(test.weight) > 0
    r = np.asarray(test.ratio, np.float64)
    return np.sqrt(np.sum((pred - r)[valid] ** 2) / np.sum(r[valid] ** 2))


def test_folds_against_numpy(result):
    """Each fold's held-out error is the fit of the other lights predicting that fold, computed
    again here from a refit; the normals of each fold are close to the truth (8-bit noise, 16
    lights per fit), the Lambertian fit's far from it. (The held-out ratio itself is not bounded
    here: with 16 lights the plain per-texel fit invents a lobe on some texels, and one fold
    predicts its lights 3.4x worse than the Lambertian fit, another at 0.07x.)"""
    obs, truth, cv = result
    assert len(cv.folds) == FOLDS
    held = light_folds(obs.n_lights, FOLDS)[1]
    maps = fit_maps(select_lights(obs, np.setdiff1d(np.arange(obs.n_lights), held)), PLAIN, progress=False)
    np.testing.assert_allclose(cv.folds[1]["heldout"], _numpy_rms(maps, obs, held), rtol=1e-5)
    for fold in cv.folds:
        assert fold["ratio"] == pytest.approx(fold["heldout"] / fold["lambertian"])
        assert fold["normals_deg"] < FOLD_NORMALS_DEG < fold["lambertian_normals_deg"], fold
    assert cv.mean_ratio == pytest.approx(np.mean([f["ratio"] for f in cv.folds]))
    assert cv.worst_ratio == max(f["ratio"] for f in cv.folds)
    # the maps cover every texel (every light predicted once)
    assert np.all(np.isfinite(cv.heldout_map)) and np.all(np.isfinite(cv.lambertian_map))
    assert "worst fold" in cv.table() and len(cv.table().splitlines()) == FOLDS + 3


def _evaluate(*args):
    return subprocess.run([sys.executable, "-m", "jaxrender.app.cli.programs", "fitting", "evaluate", *map(str, args)],
                          capture_output=True, text=True, timeout=600)


def test_command_table_figure_and_ground_truth(capture, result, tmp_path):
    out = tmp_path / "cv.png"
    proc = _evaluate(capture, "--folds", FOLDS, "--method", "plain", "--chunk", 64, "--out", out)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[0].split()[:5] == ["fold", "lights", "held-out", "Lambertian", "ratio"]
    assert any(line.startswith("ground truth:") and "truth" in line for line in lines)   # found in the capture
    mean = next(line for line in lines if line.strip().startswith("mean")).split()
    assert float(mean[3]) == pytest.approx(result[2].mean_ratio, abs=0.005)   # same fit, another process
    image = read_image(out, srgb=False)
    assert image.ndim == 3 and image.shape[1] > image.shape[0]


@pytest.mark.parametrize("case", ["missing", "not_a_capture", "folds", "suffix", "normals", "out_folder"])
def test_bad_input_is_one_line_exit_2(capture, tmp_path, case):
    args = {"missing": [tmp_path / "nothing"], "not_a_capture": [tmp_path],
            "folds": [capture, "--folds", 25], "suffix": [capture, "--out", tmp_path / "x.jpg"],
            "normals": [capture, "--normals", tmp_path / "n.npy"],
            "out_folder": [capture, "--out", tmp_path / "folder.png"]}[case]
    if case == "normals":
        np.save(tmp_path / "n.npy", np.zeros((3, 3, 3)))   # the wrong size
    if case == "out_folder":
        (tmp_path / "folder.png").mkdir()   # a folder named like the figure: refused, kept
    proc = _evaluate(*args, "--out", tmp_path / "e.png") if case not in ("suffix", "out_folder") else _evaluate(*args)
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    assert len(proc.stderr.strip().splitlines()) == 1 and "Traceback" not in proc.stderr
    assert not (tmp_path / "e.png").exists()
    assert case != "out_folder" or (tmp_path / "folder.png").is_dir()

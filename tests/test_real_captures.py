"""Measured captures: the capture format's extensions (unit-vector directions, per-light
intensities without a white board, masks, EXR radiance kept), the DiLiGenT-format importer on the
shared objects and on small malformed folders written here, the report on an irregular light
layout with held-out lights, and the evaluation helpers against independent references."""

import json
import os
from pathlib import Path

import numpy as np
import pytest

from fitting import CaptureError, load_capture, merge_capture, write_folder_manifest, write_manifest
from fitting.evaluate import angular_error_deg, heldout_split, lambertian_fit, read_normal_map
from jaxrender.io import read_mat, write_exr, write_png

ROOT = Path(__file__).resolve().parents[1]
SIZE = (4, 5)
HAT_VALID = (2.0 / 255.0, 0.98)  # design.md's code thresholds for integer images
TOL = 1e-6  # float32 division of codes by an intensity, relative


def diligent_root() -> Path:
    root = Path(os.environ.get("JAXRENDER_DILIGENT", ROOT.parent / "shared" / "data" / "diligent"))
    if not root.is_dir():
        pytest.fail(f"DiLiGenT data not found at {root}: set JAXRENDER_DILIGENT (see README, 'Real captures')",
                    pytrace=False)
    return root


def _png16(path: Path, codes: np.ndarray) -> None:
    write_png(path, codes, srgb=False, bits=16)


def _folder(root: Path, n: int = 3, *, size=SIZE, seed=0) -> Path:
    """A DiLiGenT-format folder of `n` lights with random 16-bit codes."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True)
    names = [f"{i + 1:03d}.png" for i in range(n)]
    for name in names:
        _png16(root / name, rng.uniform(0.05, 0.9, size + (3,)))
    dirs = rng.normal(size=(n, 3))
    dirs[:, 2] = np.abs(dirs[:, 2]) + 1.0
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    (root / "filenames.txt").write_text("\n".join(names) + "\n")
    (root / "light_directions.txt").write_text("\n".join(" ".join(f"{x:.6f}" for x in d) for d in dirs) + "\n")
    (root / "light_intensities.txt").write_text("\n".join(f"{1 + i:.4f} {2 + i:.4f} {3 + i:.4f}" for i in range(n)))
    mask = np.zeros(size)
    mask[1:3, 1:4] = 1
    write_png(root / "mask.png", mask, srgb=False)
    return root


def _edit_lines(path: Path, line: int, text: str) -> None:
    lines = path.read_text().splitlines()
    lines[line] = text
    path.write_text("\n".join(lines) + "\n")


def test_folder_importer_observation_is_code_over_65535_over_intensity(tmp_path):
    folder = _folder(tmp_path / "obj")
    out = write_folder_manifest(folder, tmp_path / "cap" / "capture.json")
    capture = load_capture(out.parent)
    assert capture.n_lights == 3 and not capture.has_white and capture.mask is not None
    obs = merge_capture(capture, progress=False)
    mask = np.zeros(SIZE, bool)
    mask[1:3, 1:4] = True
    import imagecodecs  # the reference decodes the PNGs itself

    intensities = np.loadtxt(folder / "light_intensities.txt")
    for i in range(3):
        codes = imagecodecs.png_decode((folder / f"{i + 1:03d}.png").read_bytes()).astype(np.float64) / 65535
        valid = mask & np.all((codes > HAT_VALID[0]) & (codes < HAT_VALID[1]), axis=-1)
        np.testing.assert_array_equal(np.asarray(obs.weight)[..., i] > 0, valid)
        np.testing.assert_allclose(np.asarray(obs.ratio)[..., i, :][valid], (codes / intensities[i])[valid], rtol=TOL)
    np.testing.assert_allclose(obs.light_dirs, np.loadtxt(folder / "light_directions.txt"), atol=2e-6)


MALFORMED = {
    "missing file": (lambda f: (f / "light_intensities.txt").unlink(), "light_intensities.txt: missing"),
    "row counts": (lambda f: (f / "filenames.txt").write_text("001.png\n002.png\n"), "row counts differ"),
    "non-unit direction": (lambda f: _edit_lines(f / "light_directions.txt", 1, "0.5 0.5 0.5"),
                           "light_directions.txt:2: [0.5, 0.5, 0.5] is not a unit vector"),
    "downward direction": (lambda f: _edit_lines(f / "light_directions.txt", 0, "0 0.6 -0.8"),
                           "light_directions.txt:1: [0.0, 0.6, -0.8] points downward"),
    "non-positive intensity": (lambda f: _edit_lines(f / "light_intensities.txt", 2, "1 0 1"),
                               "light_intensities.txt:3: [1.0, 0.0, 1.0] has a non-positive intensity"),
    "other size": (lambda f: _png16(f / "002.png", np.zeros((4, 6, 3))), "002.png: size 4x6 differs"),
    "missing image": (lambda f: (f / "003.png").unlink(), "003.png: missing image"),
    "not numbers": (lambda f: _edit_lines(f / "light_directions.txt", 0, "a b c"),
                    "light_directions.txt:1: expected 3 numbers"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_folder_one_line_per_problem_nothing_written(tmp_path, case):
    folder = _folder(tmp_path / "obj")
    breaker, fragment = MALFORMED[case]
    breaker(folder)
    out = tmp_path / "cap" / "capture.json"
    with pytest.raises(CaptureError) as info:
        write_folder_manifest(folder, out)
    assert len(info.value.problems) == 1 and fragment in info.value.problems[0], info.value.problems
    assert not out.parent.exists()


def test_cli_manifest_of_a_bad_folder_exits_2(tmp_path, capsys):
    from jaxrender.app.cli.programs import fitting_main

    folder = _folder(tmp_path / "obj")
    (folder / "filenames.txt").unlink()
    assert fitting_main(["manifest", str(folder), "--out", str(tmp_path / "cap" / "capture.json")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "filenames.txt: missing" in err[0] and "Traceback" not in err[0]


def _manifest(root: Path, lights: list[dict], **extra) -> Path:
    manifest = {"format": "jaxrender-capture", "version": 1, "size": list(SIZE), "response": "linear",
                "exposures_s": [1.0], "view": {"direction": [0, 0, 1]}, "lights": lights, **extra}
    (root / "capture.json").write_text(json.dumps(manifest))
    return root


def _exr_capture(root: Path, scale: float, *, saturation=None, white=True) -> Path:
    rng = np.random.default_rng(1)
    root.mkdir(parents=True)
    lights = []
    for i, d in enumerate([[0, 0, 1], [0.6, 0, 0.8], [0, -0.6, 0.8]]):
        write_exr(root / f"l{i}.exr", scale * rng.uniform(0.5, 1.0, SIZE + (3,)))
        lights.append({"direction": d, "images": [f"l{i}.exr"]})
    extra = {} if saturation is None else {"saturation": saturation}
    if white:
        write_exr(root / "white.exr", np.full(SIZE + (3,), scale))
        extra["white"] = {"reflectance": 0.5, "images": ["white.exr"]}
    else:
        for light in lights:
            light["intensity"] = 2.0
    return _manifest(root, lights, **extra)


def test_exr_radiance_above_one_is_kept(tmp_path):
    """EXR is linear radiance: a white board of 4.0 and lights up to 4.0 are valid observations
    (the 8-bit code thresholds used to drop every value >= 0.98)."""
    capture = load_capture(_exr_capture(tmp_path / "cap", 4.0))
    assert capture.encoding == "radiance"
    obs = merge_capture(capture, progress=False)
    assert np.all(np.asarray(obs.weight) == 1)
    from jaxrender.io import read_exr

    light = np.stack([read_exr(tmp_path / "cap" / "l1.exr")[c] for c in "RGB"], -1)
    np.testing.assert_allclose(np.asarray(obs.ratio)[:, :, 1], light / 4.0 * 0.5, rtol=TOL)


def test_exr_without_white_board_divides_by_intensity(tmp_path):
    obs = merge_capture(load_capture(_exr_capture(tmp_path / "cap", 3.0, white=False)), progress=False)
    from jaxrender.io import read_exr

    light = np.stack([read_exr(tmp_path / "cap" / "l0.exr")[c] for c in "RGB"], -1)
    np.testing.assert_allclose(np.asarray(obs.ratio)[:, :, 0], light / 2.0, rtol=TOL)


def test_an_all_invalid_capture_is_refused_with_its_cause(tmp_path, capsys):
    """A saturation level below every value: no valid observation. `fitting fit` exits 2 naming the
    likely cause, and leaves no BTF."""
    from jaxrender.app.cli.programs import fitting_main

    _exr_capture(tmp_path / "cap", 4.0, saturation=1.0)
    assert fitting_main(["fit", str(tmp_path / "cap"), "--out", str(tmp_path / "btf"), "--no-pyramid"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "20 of 20 texels have no valid observation" in err[0] and "saturated" in err[0], err
    assert not (tmp_path / "btf" / "btf.json").exists()


def test_manifest_problems_of_the_extensions(tmp_path):
    root = tmp_path / "cap"
    root.mkdir()
    write_png(root / "a.png", np.full(SIZE + (3,), 0.5), srgb=False)
    _manifest(root, [{"direction": [0, 0.6, 0.6], "intensity": 1, "images": ["a.png"]},
                     {"direction": [0, 0.6, -0.8], "intensity": [1, 2], "images": ["a.png"]},
                     {"theta_deg": 10, "phi_deg": 0, "images": ["a.png"]}], mask="nope.png", extra=1,
              encoding="raw")
    with pytest.raises(CaptureError) as info:
        load_capture(root)
    text = "\n".join(info.value.problems)
    for fragment in ("lights[0].direction: [0.0, 0.6, 0.6] is not a unit vector",
                     "lights[1].direction: [0.0, 0.6, -0.8] is at or below the horizon",
                     "lights[1].intensity: expected a positive number or RGB triple",
                     "lights: 2 of 3 lights carry an intensity", "nope.png: missing image",
                     "encoding: 'raw' is not 'codes' or 'radiance'"):
        assert fragment in text, text


def test_csv_with_light_vectors_and_intensities_needs_no_white_board(tmp_path):
    raw = tmp_path / "raw"
    raw.mkdir()
    for name in ("a", "b"):
        write_png(raw / f"{name}.png", np.full(SIZE + (3,), 0.5), srgb=False)
    (tmp_path / "IMAGES.csv").write_text("image,kind,light_x,light_y,light_z,intensity_r,intensity_g,intensity_b,"
                                         "exposure_s\nraw/a.png,light,0,0,1,1,2,3,0.5\n"
                                         "raw/b.png,light,0.6,0,0.8,2,2,2,0.5\n")
    out = write_manifest(tmp_path / "IMAGES.csv", tmp_path / "cap" / "capture.json")
    lights = json.loads(out.read_text())["lights"]
    assert lights == [{"direction": [0.0, 0.0, 1.0], "intensity": [1.0, 2.0, 3.0], "images": ["../raw/a.png"]},
                      {"direction": [0.6, 0.0, 0.8], "intensity": 2.0, "images": ["../raw/b.png"]}]
    obs = merge_capture(load_capture(out.parent), progress=False)
    radiance = np.round(0.5 * 255) / 255 / 0.5  # the 8-bit code of 0.5 over 0.5 s
    np.testing.assert_allclose(np.asarray(obs.ratio)[0, 0], radiance / np.array([[1.0, 2.0, 3.0], [2.0, 2.0, 2.0]]),
                               rtol=TOL)


def test_importer_on_the_shared_objects():
    """Every object in the shared DiLiGenT folder imports; its capture has 96 lights, the mask, the
    intensities of light_intensities.txt; one light's observation against the PNG decoded here."""
    import imagecodecs

    for folder in sorted(p for p in diligent_root().iterdir() if (p / "filenames.txt").is_file()):
        out = Path(os.environ.get("TMPDIR", "/tmp")) / f"diligent-import-{os.getpid()}" / folder.name / "capture.json"
        write_folder_manifest(folder, out)
        manifest = json.loads(out.read_text())
        manifest["lights"] = manifest["lights"][40:41]  # an ordinary capture: drop lights by editing the list
        out.write_text(json.dumps(manifest))
        capture = load_capture(out.parent, headers_only=True)
        assert capture.n_lights == 1 and capture.mask is not None
        intensity = np.loadtxt(folder / "light_intensities.txt")[40]
        np.testing.assert_allclose(capture.light_intensities[0], intensity)
        obs = merge_capture(capture, progress=False)
        name = (folder / "filenames.txt").read_text().split()[40]
        codes = imagecodecs.png_decode((folder / name).read_bytes()).astype(np.float64) / 65535
        w = np.asarray(obs.weight)[..., 0] > 0
        assert w.sum() > 0.05 * w.size, folder.name
        np.testing.assert_allclose(np.asarray(obs.ratio)[..., 0, :][w], (codes / intensity)[w], rtol=TOL)


def test_read_mat_matches_scipy(tmp_path):
    import scipy.io

    rng = np.random.default_rng(3)
    arrays = {"Normal_gt": rng.normal(size=(5, 4, 3)), "small": np.arange(6.0).reshape(2, 3)}
    for compress in (False, True):
        path = tmp_path / f"x{compress}.mat"
        scipy.io.savemat(path, arrays, do_compression=compress)
        got = read_mat(path)
        for name, value in arrays.items():
            np.testing.assert_array_equal(got[name], value)


def test_lambertian_fit_matches_numpy_least_squares():
    import jax.numpy as jnp

    from fitting import Observations

    rng = np.random.default_rng(4)
    dirs = rng.normal(size=(9, 3))
    dirs[:, 2] = np.abs(dirs[:, 2]) + 0.5
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    ratio = rng.uniform(0.1, 1.0, (2, 3, 9, 3))
    weight = (rng.uniform(size=(2, 3, 9)) > 0.2).astype(np.float64)
    zeros = np.zeros((2, 3), np.int32)
    obs = Observations(jnp.asarray(ratio), jnp.asarray(weight), jnp.asarray(dirs), jnp.asarray([0.0, 0, 1]),
                       zeros, zeros, zeros)
    fit = lambertian_fit(obs)
    for h in range(2):
        for w in range(3):
            sel = weight[h, w] > 0
            b = np.linalg.lstsq(dirs[sel], ratio[h, w, sel], rcond=None)[0]  # 3 x C
            n = b.sum(axis=1) / np.linalg.norm(b.sum(axis=1))
            np.testing.assert_allclose(np.asarray(fit.normal)[h, w], n, atol=1e-5)
            np.testing.assert_allclose(np.asarray(fit.albedo)[h, w], np.maximum(n @ b, 0), atol=1e-5)


def test_angular_error_and_normal_maps(tmp_path):
    gt = np.zeros((2, 2, 3))
    gt[..., 2] = 1.0
    gt[1, 1] = 0  # outside the benchmark's mask: zero
    est = gt.copy()
    est[0, 0] = [np.sin(np.radians(10)), 0, np.cos(np.radians(10))]
    mean, err = angular_error_deg(est, gt)
    assert mean == pytest.approx(10 / 3, abs=1e-9) and np.isnan(err[1, 1])
    np.save(tmp_path / "n.npy", gt)
    np.testing.assert_array_equal(read_normal_map(tmp_path / "n.npy", (2, 2)), gt)
    assert list(heldout_split(12, 6)[1]) == [5, 11]


def test_report_on_irregular_lights_with_holdout_and_normals(tmp_path, capsys):
    """An LED-rig layout (random directions, per-light intensities, no white board, a mask) of a
    Lambertian surface with known normals: `fitting fit` + `fitting report --holdout 4 --normals`
    (the table used to crash on elevations that are not regular rings)."""
    from jaxrender.app.cli.programs import fitting_main

    rng = np.random.default_rng(5)
    size, n = (6, 7), 12
    normals = rng.normal(size=size + (3,)) * [0.3, 0.3, 1.0]
    normals[..., 2] = np.abs(normals[..., 2]) + 0.5
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    dirs = rng.normal(size=(n, 3)) * [1.0, 1.0, 0.5]
    dirs[:, 2] = np.abs(dirs[:, 2]) + 0.6
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    albedo, intensity = np.array([0.6, 0.5, 0.4]), rng.uniform(1.0, 2.0, (n, 3))
    root = tmp_path / "cap"
    root.mkdir()
    for i in range(n):
        shade = np.maximum(normals @ dirs[i], 0.0)[..., None] * albedo * intensity[i]
        write_exr(root / f"l{i}.exr", shade)
    mask = np.ones(size)
    mask[0] = 0
    write_png(root / "mask.png", mask, srgb=False)
    _manifest(root, [{"direction": d.tolist(), "intensity": c.tolist(), "images": [f"l{i}.exr"]}
                     for i, (d, c) in enumerate(zip(dirs, intensity))], mask="mask.png")
    (root / "capture.json").write_text((root / "capture.json").read_text().replace('[4, 5]', '[6, 7]'))
    np.save(tmp_path / "normals.npy", normals)
    assert fitting_main(["fit", str(root), "--out", str(tmp_path / "btf"), "--no-pyramid"]) == 0
    capsys.readouterr()
    assert fitting_main(["report", str(root), str(tmp_path / "btf"), "--holdout", "4", "--normals",
                         str(tmp_path / "normals.npy")]) == 0
    out = capsys.readouterr().out
    assert "texels 35 (of 42)" in out  # the masked row is skipped
    normal_err = float(out.split("mean angular error ")[1].split(" deg")[0])
    held = out.split("relative RMS ")[1]
    fit_err, lambert_err = float(held.split(" ")[0]), float(held.split("same lights: ")[1].rstrip(")\n").split(")")[0])
    # exact Lambertian data: the fit predicts the held-out lights to float32 and LM tolerance; the
    # least-squares baseline fits attached shadows' zeros linearly (no max(0, .)), so it is off by ~1 %
    assert normal_err < 0.1 and fit_err < 1e-3 and 1e-3 < lambert_err < 0.05, out


def test_masked_pyramid_averages_inside_children_only():
    """A coarse texel with two inside children of one material and two outside (rho 0) is that
    material, not half of it; its mask is 1; a coarse texel of outside children only has mask 0."""
    import jax.numpy as jnp

    from fitting.pyramid import pyramid_levels
    from jaxrender.brdf import BTFTexel

    h, w = 4, 4
    mask = np.zeros((h, w))
    mask[:2, :1] = 1  # the top-left coarse texel: children (0,0), (1,0) inside, (0,1), (1,1) outside
    rho_d = np.where(mask[..., None] > 0, [0.4, 0.3, 0.2], 0.0)
    rho_s = np.where(mask[..., None] > 0, [0.2, 0.2, 0.2], 0.0)
    normal = np.tile([0.0, 0.0, 1.0], (h, w, 1))
    sigma = np.full((h, w), 0.15)
    level0 = BTFTexel.single(jnp.asarray(rho_d), jnp.asarray(rho_s), jnp.asarray(normal), jnp.asarray(sigma),
                             jnp.asarray(sigma))
    levels, stats = pyramid_levels(level0, levels=2, mask=jnp.asarray(mask))
    coarse = levels[0]
    np.testing.assert_allclose(np.asarray(coarse.rho_d)[0, 0], [0.4, 0.3, 0.2], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(coarse.lobe0.rho_s)[0, 0], [0.2, 0.2, 0.2], rtol=1e-5)
    np.testing.assert_allclose(np.asarray(coarse.lobe0.sigma_x)[0, 0], 0.15, rtol=1e-4)
    np.testing.assert_array_equal(stats[0]["mask"], [[1, 0], [0, 0]])
    np.testing.assert_array_equal(np.asarray(coarse.rho_d)[1, 1], 0.0)

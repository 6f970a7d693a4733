"""Capture directories: loading, validation of every malformed case (one line naming the file,
all problems at once), code values of 8/16-bit PNG and EXR, and `merge_capture` against a
float64 reference. Captures here are written by hand (numpy + jaxrender.io), not by `synth`."""

import json

import numpy as np
import pytest
from capture_helpers import write_foreign_exr

from fitting import Capture, CaptureError, load_capture, merge_capture
from jaxrender.io import InputError, write_exr, write_png

SIZE = (4, 5)
EXPOSURES = [0.01, 0.1, 1.0]
LIGHTS = [(0.0, 0.0), (30.0, 90.0), (60.0, 225.0)]
BOARD = [0.9, 0.8, 0.7]
# float32 merge vs float64: sRGB pow(c, 2.4) costs ~eps * 2.4 * |ln c| per sample, hat weights near the
# thresholds a few ulps
MERGE_TOL = 2e-5


def _codes(rng, shape, bits):
    if bits == 0:
        return rng.uniform(0.0, 1.0, shape).astype(np.float32)
    levels = 2**bits - 1
    return (rng.integers(0, levels + 1, shape) / levels).astype(np.float32)


def make_capture(root, *, fmt="png", bits=8, response="linear", seed=0):
    """A valid capture: images with random codes, and the codes in a dict keyed by relative path."""
    rng = np.random.default_rng(seed)
    (root / "images").mkdir(parents=True)
    ext = "exr" if fmt == "exr" else "png"
    written = {}

    def image(name):
        codes = _codes(rng, SIZE + (3,), 0 if fmt == "exr" else bits)
        if fmt == "exr":
            write_exr(root / name, codes)
        else:
            write_png(root / name, codes, srgb=False, bits=bits)
        written[name] = codes
        return name

    white = [image(f"images/white_e{e}.{ext}") for e in range(len(EXPOSURES))]
    lights = [{"theta_deg": t, "phi_deg": p,
               "images": [image(f"images/l{i}_e{e}.{ext}") for e in range(len(EXPOSURES))]}
              for i, (t, p) in enumerate(LIGHTS)]
    manifest = {"format": "jaxrender-capture", "version": 1, "size": list(SIZE), "response": response,
                "exposures_s": EXPOSURES, "view": {"theta_deg": 0, "phi_deg": 0},
                "white": {"reflectance": BOARD, "images": white}, "lights": lights}
    (root / "capture.json").write_text(json.dumps(manifest))
    return manifest, written


def edit_manifest(root, change):
    manifest = json.loads((root / "capture.json").read_text())
    change(manifest)
    (root / "capture.json").write_text(json.dumps(manifest))


def problems_of(root):
    with pytest.raises(CaptureError) as info:
        load_capture(root)
    assert isinstance(info.value, InputError)
    lines = str(info.value).split("\n")
    assert lines == info.value.problems
    return lines


def test_valid_capture_loads(tmp_path):
    make_capture(tmp_path)
    capture = load_capture(tmp_path)
    assert isinstance(capture, Capture)
    assert capture.size == SIZE and capture.exposures_s == tuple(EXPOSURES) and capture.n_lights == 3
    np.testing.assert_allclose(capture.white_reflectance, BOARD)
    # (theta, phi) -> (sin t cos p, sin t sin p, cos t), design.md's sample frame, spelled out.
    expected = np.array([[0, 0, 1], [0, 0.5, np.sqrt(3) / 2],
                         [-np.sqrt(3) / 2 * np.sqrt(0.5), -np.sqrt(3) / 2 * np.sqrt(0.5), 0.5]])
    np.testing.assert_allclose(capture.light_dirs, expected, atol=1e-15)
    np.testing.assert_allclose(capture.view_dir, [0, 0, 1], atol=1e-15)
    assert capture.light_images[1][2] == tmp_path / "images/l1_e2.png"


def _delete(path):
    path.unlink()


MALFORMED = {
    # name: (how to break a valid capture, [(file, message fragment), ...])
    "no capture.json": (lambda r: _delete(r / "capture.json"), [("capture.json", "missing")]),
    "bad JSON": (lambda r: (r / "capture.json").write_text("{\"format\": "), [("capture.json", "not valid JSON")]),
    "unknown version": (lambda r: edit_manifest(r, lambda m: m.update(version=2)),
                        [("capture.json", "version: unknown version 2")]),
    "unknown format": (lambda r: edit_manifest(r, lambda m: m.update(format="other")),
                       [("capture.json", "format: 'other' is not 'jaxrender-capture'")]),
    "missing field": (lambda r: edit_manifest(r, lambda m: m.pop("exposures_s")),
                      [("capture.json", "exposures_s: missing")]),
    "wrong type": (lambda r: edit_manifest(r, lambda m: m.update(size="4x5")),
                   [("capture.json", "size: '4x5' is not [H, W]")]),
    "bad reflectance": (lambda r: edit_manifest(r, lambda m: m["white"].update(reflectance=[1, 2])),
                        [("capture.json", "white.reflectance: [1, 2] is not a positive number or RGB triple")]),
    "missing image": (lambda r: _delete(r / "images/l2_e1.png"), [("images/l2_e1.png", "missing image")]),
    "unreadable image": (lambda r: (r / "images/l0_e0.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage"),
                         [("images/l0_e0.png", "not a readable image")]),
    "size differs": (lambda r: write_png(r / "images/white_e1.png", np.zeros((4, 6, 3)), srgb=False),
                     [("images/white_e1.png", "size 4x6 differs from capture.json's size 4x5")]),
    "light at the horizon": (lambda r: edit_manifest(r, lambda m: m["lights"][1].update(theta_deg=90)),
                             [("capture.json", "lights[1].theta_deg: 90 is at or below the horizon")]),
    "light below the horizon": (lambda r: edit_manifest(r, lambda m: m["lights"][2].update(theta_deg=120.5)),
                                [("capture.json", "lights[2].theta_deg: 120.5 is at or below the horizon")]),
    "exposures do not match images": (
        lambda r: edit_manifest(r, lambda m: m["lights"][0]["images"].pop()),
        [("capture.json", "lights[0].images: 2 images for 3 exposures")]),
    "white images do not match exposures": (
        lambda r: edit_manifest(r, lambda m: m["white"]["images"].append("images/white_e0.png")),
        [("capture.json", "white.images: 4 images for 3 exposures")]),
    "unsupported image type": (
        lambda r: edit_manifest(r, lambda m: m["lights"][0]["images"].__setitem__(0, "capture.json")),
        [("capture.json", "unsupported image type '.json'")]),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_each_malformed_case_names_the_file(tmp_path, case):
    make_capture(tmp_path)
    breaker, expected = MALFORMED[case]
    breaker(tmp_path)
    lines = problems_of(tmp_path)
    assert len(lines) == len(expected), lines
    for (name, fragment), line in zip(expected, lines, strict=True):
        assert line.startswith(str(tmp_path / name) + ": "), line
        assert fragment in line, line


def test_nan_and_inf_in_exr(tmp_path):
    make_capture(tmp_path, fmt="exr")
    load_capture(tmp_path)  # valid as written
    bad = np.full(SIZE + (3,), 0.5, np.float32)
    bad[1, 2, 0] = np.nan
    write_foreign_exr(tmp_path / "images/l1_e0.exr", bad)
    bad[0, 0, 1] = np.inf
    write_foreign_exr(tmp_path / "images/white_e2.exr", bad)
    lines = problems_of(tmp_path)
    assert sorted(lines) == sorted([f"{tmp_path / 'images/l1_e0.exr'}: 1 non-finite values (NaN)",
                                    f"{tmp_path / 'images/white_e2.exr'}: 2 non-finite values (NaN, Inf)"])


def test_every_problem_is_reported_at_once(tmp_path):
    make_capture(tmp_path)
    edit_manifest(tmp_path, lambda m: (m["lights"][1].update(theta_deg=95), m["lights"][2]["images"].pop(),
                                       m.update(response="gamma")))
    (tmp_path / "images/l0_e1.png").unlink()
    write_png(tmp_path / "images/l2_e0.png", np.zeros((3, 5)), srgb=False)
    lines = problems_of(tmp_path)
    assert len(lines) == 5, lines
    joined = "\n".join(lines)
    for fragment in ("response: 'gamma'", "lights[1].theta_deg: 95 is at or below the horizon",
                     "lights[2].images: 2 images for 3 exposures", "l0_e1.png: missing image",
                     "l2_e0.png: size 3x5 differs"):
        assert fragment in joined


def test_fit_cli_prints_every_problem_and_exits_2(tmp_path, capsys):
    """Through the command line: all problems, one line each, exit code 2, nothing written."""
    from jaxrender.app.cli.programs import fitting_main

    make_capture(tmp_path / "capture")
    edit_manifest(tmp_path / "capture", lambda m: (m["lights"][1].update(theta_deg=90), m["white"]["images"].pop()))
    (tmp_path / "capture" / "images/l2_e0.png").unlink()
    assert fitting_main(["fit", str(tmp_path / "capture"), "--out", str(tmp_path / "btf")]) == 2
    err = capsys.readouterr().err.strip().split("\n")
    assert len(err) == 3, err
    assert err[0].startswith("fitting fit: error: ")
    for fragment in ("lights[1].theta_deg: 90 is at or below the horizon", "white.images: 2 images for 3 exposures",
                     f"{tmp_path / 'capture' / 'images/l2_e0.png'}: missing image"):
        assert sum(fragment in line for line in err) == 1, (fragment, err)
    assert not (tmp_path / "btf").exists()


def test_images_must_agree_when_the_manifest_size_is_bad(tmp_path):
    make_capture(tmp_path)
    edit_manifest(tmp_path, lambda m: m.pop("size"))
    write_png(tmp_path / "images/l2_e2.png", np.zeros((5, 5, 3)), srgb=False)
    lines = problems_of(tmp_path)
    assert lines == [f"{tmp_path / 'capture.json'}: size: missing field",
                     f"{tmp_path / 'images/l2_e2.png'}: size 5x5 differs from {tmp_path / 'images/white_e0.png'}'s 4x5"]


@pytest.mark.parametrize("fmt,bits", [("png", 8), ("png", 16), ("exr", 0)])
def test_raw_code_values(tmp_path, fmt, bits):
    """PNG codes are integer / full scale, not linearised (saturation is judged on them); EXR
    values come through as they are."""
    _, written = make_capture(tmp_path, fmt=fmt, bits=bits, response="srgb" if fmt == "png" else "linear")
    capture = load_capture(tmp_path)
    for name in ("images/l1_e2." + ("exr" if fmt == "exr" else "png"), capture.white_images[0].relative_to(tmp_path)):
        codes = capture.read_codes(tmp_path / name)
        assert codes.dtype == np.float32 and codes.shape == SIZE + (3,)
        np.testing.assert_array_equal(codes, written[str(name)])


@pytest.mark.parametrize("response", ["linear", "srgb"])
def test_merge_capture_matches_reference(tmp_path, response):
    """merge_capture = merged radiance / merged white radiance * board reflectance, per texel and
    channel, computed here in float64 numpy from the written codes."""
    from test_hdr import reference_merge

    _, written = make_capture(tmp_path, bits=16, response=response)
    capture = load_capture(tmp_path)
    obs = merge_capture(capture, batch=2, progress=False)  # 3 lights in batches of 2: padding exercised
    t = np.asarray(EXPOSURES)
    white_codes = np.stack([written[f"images/white_e{e}.png"] for e in range(3)])
    white, white_sat, white_dark, _ = reference_merge(white_codes, t, response)
    white_ok = ~(white_sat | white_dark).any(-1)
    assert obs.ratio.shape == SIZE + (3, 3) and obs.weight.shape == SIZE + (3,)
    n_valid = np.zeros(SIZE, int)
    for i in range(3):
        codes = np.stack([written[f"images/l{i}_e{e}.png"] for e in range(3)])
        radiance, sat, dark, _ = reference_merge(codes, t, response)
        valid = ~(sat | dark).any(-1) & white_ok
        np.testing.assert_array_equal(np.asarray(obs.weight)[:, :, i], valid.astype(np.float32))
        expected = radiance / white * np.asarray(BOARD)
        np.testing.assert_allclose(np.asarray(obs.ratio)[:, :, i][valid], expected[valid], rtol=MERGE_TOL)
        n_valid += valid
    np.testing.assert_array_equal(np.asarray(obs.n_valid), n_valid)
    assert 0 < n_valid.sum() < n_valid.size * 3  # random codes: some valid, some flagged
    np.testing.assert_allclose(np.asarray(obs.light_dirs), capture.light_dirs, rtol=1e-6, atol=1e-7)

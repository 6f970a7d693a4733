"""`fitting ingest`, `fitting fit` and `fitting manifest` on the command line: every malformed
capture exits 2 with one line per problem naming the file, and leaves no BTF_DIR and no store
(problems of the manifest and headers before anything is written, pixel problems found during the
pass); `--keep-store` keeps the store, which `fitting fit STORE_DIR` then fits to the same maps."""

import json

import jax
import numpy as np
import pytest
from capture_helpers import write_capture, write_foreign_exr

from jaxrender.app.cli.programs import fitting_main
from jaxrender.io import read_btf, write_exr, write_png

SIZE = (4, 4)


def _capture(root, fmt="png"):
    rng = np.random.default_rng(2)
    (root / "images").mkdir(parents=True)

    def image(name):
        codes = rng.uniform(0.2, 0.8, SIZE + (3,)).astype(np.float32)
        write_exr(root / name, codes) if fmt == "exr" else write_png(root / name, codes, srgb=False)
        return name

    return write_capture(root, image, size=SIZE, ext=fmt, lights=8, exposures_s=[0.1, 1.0], angle_step=(8.0, 37.0))


def _edit(root, change):
    manifest = json.loads((root / "capture.json").read_text())
    change(manifest)
    (root / "capture.json").write_text(json.dumps(manifest))


def _truncate(path):
    path.write_bytes(path.read_bytes()[:70])


def _nan(path):
    image = np.full(SIZE + (3,), 0.5, np.float32)
    image[0, 0] = np.nan
    write_foreign_exr(path, image)


CASES = {
    # name: (format, breaker, [(file, fragment)] in order)
    "light below the horizon": ("png", lambda r: _edit(r, lambda m: m["lights"][2].update(theta_deg=95)),
                                [("capture.json", "lights[2].theta_deg: 95 is at or below the horizon")]),
    "missing image and bad size": (
        "png", lambda r: ((r / "images/l1_e0.png").unlink(),
                          write_png(r / "images/l5_e1.png", np.zeros((4, 6, 3)), srgb=False)),
        [("images/l1_e0.png", "missing image"), ("images/l5_e1.png", "size 4x6 differs")]),
    "truncated PNG (pixel pass)": ("png", lambda r: _truncate(r / "images/l6_e1.png"),
                                   [("images/l6_e1.png", "not a readable image")]),
    "NaN in EXR (pixel pass)": ("exr", lambda r: (_nan(r / "images/l3_e0.exr"), _nan(r / "images/l7_e1.exr")),
                                # the pass stops at the first light block with a problem
                                [("images/l3_e0.exr", "3 non-finite values (NaN)")]),
}


@pytest.mark.parametrize("command", ["ingest", "fit"])
@pytest.mark.parametrize("case", sorted(CASES))
def test_malformed_capture_exits_2_and_leaves_nothing(tmp_path, capsys, command, case):
    fmt, breaker, expected = CASES[case]
    cap = _capture(tmp_path / "cap", fmt)
    breaker(cap)
    out = tmp_path / "out"
    argv = ["ingest", str(cap), "--store", str(out)] if command == "ingest" else ["fit", str(cap), "--out", str(out)]
    # one light per block: the pixel problems of l6 / l7 are met after earlier blocks were written
    argv += ["--memory-gb", "0.000001"]
    assert fitting_main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    lines = err.strip().split("\n")
    lines = [line.split(": error: ", 1)[1] for line in lines]  # each problem line names the command
    assert len(lines) == len(expected), lines
    for line, (name, fragment) in zip(lines, expected, strict=True):
        assert line.startswith(f"{cap / name}: ") and fragment in line, line
    assert not out.exists()


def test_ingest_then_fit_the_kept_store(tmp_path, capsys):
    cap = _capture(tmp_path / "cap")
    assert fitting_main(["ingest", str(cap), "--store", str(tmp_path / "store"), "--dtype", "float32"]) == 0
    assert "4x4 texels x 8 lights, float32" in capsys.readouterr().out
    with jax.enable_x64(False):  # float32 fits, as the console script runs
        assert fitting_main(["fit", str(cap), "--out", str(tmp_path / "a"), "--keep-store", "--no-pyramid",
                             "--store-dtype", "float32", "--chunk", "16"]) == 0
        assert (tmp_path / "a/.store/store.json").is_file() and not (tmp_path / "a/.partial").exists()
        assert fitting_main(["fit", str(tmp_path / "store"), "--out", str(tmp_path / "b"), "--no-pyramid",
                             "--chunk", "16"]) == 0
    _, a = read_btf(tmp_path / "a")
    _, b = read_btf(tmp_path / "b")
    for name in a[0]:  # the same capture, the same float32 store: the same maps
        np.testing.assert_array_equal(a[0][name], b[0][name], err_msg=name)


def test_fit_refuses_an_unfinished_store(tmp_path, capsys):
    (tmp_path / "store/.ingest").mkdir(parents=True)
    assert fitting_main(["fit", str(tmp_path / "store"), "--out", str(tmp_path / "btf")]) == 2
    assert "store.json: missing: the observation store is unfinished" in capsys.readouterr().err
    assert not (tmp_path / "btf").exists()


def test_manifest_command(tmp_path, capsys):
    (tmp_path / "raw").mkdir()
    for name in ("w0", "w1", "l0", "l1"):
        write_png(tmp_path / f"raw/{name}.png", np.full(SIZE + (3,), 0.5), srgb=False)
    csv_path = tmp_path / "IMAGES.csv"
    csv_path.write_text("image,kind,theta_deg,phi_deg,exposure_s\nraw/w0.png,white,,,0.1\nraw/w1.png,white,,,1\n"
                        "raw/l0.png,light,20,0,0.1\nraw/l1.png,light,20,0,1\n")
    out = tmp_path / "cap/capture.json"
    assert fitting_main(["manifest", str(csv_path), "--out", str(out), "--white-reflectance", "0.9", "0.8", "0.7",
                         "--view", "5", "0"]) == 0
    assert json.loads(out.read_text())["white"]["reflectance"] == [0.9, 0.8, 0.7]
    csv_path.write_text(csv_path.read_text() + "raw/l1.png,light,20,0,2\n")
    assert fitting_main(["manifest", str(csv_path), "--out", str(tmp_path / "cap2/capture.json")]) == 2
    err = capsys.readouterr().err.strip().split("\n")
    assert err == [f"fitting manifest: error: {csv_path}:2: the white board has no image for exposure 2 s"]
    assert not (tmp_path / "cap2").exists()

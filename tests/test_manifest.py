"""`write_manifest`: a capture manifest from IMAGES.csv (EXIF ExposureTime when exposure_s is
empty), checked by `load_capture`; every bad row reported at once, one line naming the CSV line."""

import json

import numpy as np
import pytest
from PIL import Image, TiffImagePlugin

from fitting import CaptureError, load_capture
from fitting.manifest import exif_exposure_s, write_manifest
from jaxrender.io import write_png

SIZE = (4, 5)
HEADER = "image,kind,theta_deg,phi_deg,exposure_s\n"


def _jpeg_with_exposure(path, seconds: TiffImagePlugin.IFDRational | None):
    exif = Image.Exif()
    if seconds is not None:
        exif.get_ifd(0x8769)[0x829A] = seconds
    Image.fromarray(np.full(SIZE + (3,), 100, np.uint8)).save(path, exif=exif, quality=95)


@pytest.fixture
def images(tmp_path):
    d = tmp_path / "raw"
    d.mkdir()
    for name in ("w_a", "w_b", "l0_a", "l0_b", "l1_a"):
        write_png(d / f"{name}.png", np.full(SIZE + (3,), 0.5), srgb=False)
    _jpeg_with_exposure(d / "l1_b.jpg", TiffImagePlugin.IFDRational(1, 10))  # 0.1 s, from EXIF
    return d


GOOD = ("raw/w_a.png,white,,,0.01\nraw/w_b.png,white,,,0.1\nraw/l0_a.png,light,30,90,0.01\n"
        "raw/l0_b.png,light,30,90,0.1\nraw/l1_a.png,light,45.5,180,0.01\nraw/l1_b.jpg,light,45.5,180,\n")


def test_exif_exposure(images):
    assert exif_exposure_s(images / "l1_b.jpg") == pytest.approx(0.1, rel=1e-12)
    assert exif_exposure_s(images / "w_a.png") is None


def test_manifest_from_csv_loads_as_a_capture(tmp_path, images):
    (tmp_path / "IMAGES.csv").write_text(HEADER + GOOD)
    out = write_manifest(tmp_path / "IMAGES.csv", tmp_path / "cap" / "capture.json", response="srgb",
                         white_reflectance=0.9, view=(10.0, 0.0))
    manifest = json.loads(out.read_text())
    assert manifest["exposures_s"] == [0.01, 0.1] and manifest["size"] == list(SIZE)
    assert manifest["white"] == {"reflectance": 0.9, "images": ["../raw/w_a.png", "../raw/w_b.png"]}
    assert [(light["theta_deg"], light["phi_deg"]) for light in manifest["lights"]] == [(30.0, 90.0), (45.5, 180.0)]
    assert manifest["lights"][1]["images"] == ["../raw/l1_a.png", "../raw/l1_b.jpg"]
    capture = load_capture(tmp_path / "cap")
    assert capture.n_lights == 2 and capture.response == "srgb" and capture.view_angles == (10.0, 0.0)


def test_every_bad_row_is_one_line(tmp_path, images):
    _jpeg_with_exposure(images / "noexif.jpg", None)
    rows = ("raw/w_a.png,white,,,0.01\n"            # line 2: fine
            "raw/w_b.png,white,,,0.1\n"             # line 3: fine
            "raw/l0_a.png,lamp,30,90,0.01\n"        # line 4: kind
            "raw/l0_b.png,light,95,90,0.1\n"        # line 5: below the horizon
            "raw/l1_a.png,light,45,abc,0.01\n"      # line 6: phi
            "raw/l1_a.png,light,45,0,-1\n"          # line 7: exposure
            "raw/gone.png,light,45,0,0.1\n"         # line 8: missing image
            "raw/noexif.jpg,light,45,0,\n"          # line 9: no exposure anywhere
            "raw/l0_a.png,light,60,0,0.01\n"        # line 10: light (60, 0) lacks 0.1 s
            "raw/l0_b.png,light,60,0,0.01\n")       # line 11: a second 0.01 s image
    csv_path = tmp_path / "IMAGES.csv"
    csv_path.write_text(HEADER + rows)
    with pytest.raises(CaptureError) as info:
        write_manifest(csv_path, tmp_path / "cap" / "capture.json")
    c = str(csv_path)
    assert info.value.problems == [
        f"{c}:4: kind: 'lamp' is not 'light' or 'white'",
        f"{c}:5: theta_deg: '95' is not a number in [0, 90)",
        f"{c}:6: phi_deg: 'abc' is not a number",
        f"{c}:7: exposure_s: '-1' is not a positive number of seconds",
        f"{c}:8: raw/gone.png: missing image",
        f"{c}:9: exposure_s: empty and raw/noexif.jpg has no EXIF ExposureTime",
        f"{c}:11: light (theta 60, phi 0) has a second image for exposure 0.01 s (first on line 10)",
        f"{c}:10: light (theta 60, phi 0) has no image for exposure 0.1 s",
    ]
    assert not (tmp_path / "cap").exists()


def test_missing_columns_and_bad_options(tmp_path, images):
    (tmp_path / "IMAGES.csv").write_text("image,kind\nraw/w_a.png,white\n")
    with pytest.raises(CaptureError) as info:
        write_manifest(tmp_path / "IMAGES.csv", tmp_path / "capture.json", response="gamma", view=(95.0, 0.0))
    assert info.value.problems == [
        "--response: 'gamma' is not one of ('linear', 'srgb')",
        "--view: (95.0, 0.0) is not THETA PHI with theta in [0, 90)",
        f"{tmp_path / 'IMAGES.csv'}: missing columns exposure_s, theta_deg and phi_deg (or light_x, light_y, light_z) "
        "(has image, kind)"]

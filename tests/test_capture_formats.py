"""Captures of 8/16-bit TIFF and JPEG images: header checks, code values against the integers
written (numpy's own division), the merge of a TIFF capture against the same codes as PNG, JPEG
against Pillow's decode, and the types refused with a one-line message."""

import json

import numpy as np
import pytest
import tifffile
from capture_helpers import write_capture
from PIL import Image

from fitting import CaptureError, ingest_capture, load_capture, merge_capture, open_store
from fitting.capture import image_header
from jaxrender.io import InputError, write_png

SIZE = (4, 5)
EXPOSURES = [0.05, 0.5]


def _capture(root, ext, writer, *, response="linear"):
    """3 lights x 2 exposures and the white board; returns the integer codes written, by path."""
    rng = np.random.default_rng(1)
    written = {}

    def image(name):
        codes = writer(root / name, rng)
        written[name] = codes
        return name

    write_capture(root, image, size=SIZE, ext=ext, lights=3, exposures_s=EXPOSURES, angle_step=(20.0, 40.0),
                  response=response)
    return written


def _tiff_writer(bits):
    def write(path, rng):
        codes = rng.integers(0, 2**bits, SIZE + (3,), dtype=np.uint8 if bits == 8 else np.uint16)
        tifffile.imwrite(path, codes, photometric="rgb")
        return codes
    return write


@pytest.mark.parametrize("bits", [8, 16])
def test_tiff_codes_are_the_integers_over_full_scale(tmp_path, bits):
    written = _capture(tmp_path, "tif", _tiff_writer(bits))
    assert image_header(tmp_path / "images/w0.tif") == (SIZE, 3, f"uint{bits}")
    capture = load_capture(tmp_path)
    load_capture(tmp_path, headers_only=True)
    for name, codes in written.items():
        got = capture.read_codes(tmp_path / name)
        np.testing.assert_array_equal(got, (codes / (2**bits - 1)).astype(np.float32), err_msg=name)


def test_tiff_capture_merges_as_the_same_codes_in_png(tmp_path):
    written = _capture(tmp_path / "tif", "tif", _tiff_writer(16))
    png = tmp_path / "png"
    (png / "images").mkdir(parents=True)
    for name, codes in written.items():
        write_png(png / name.replace(".tif", ".png"), codes / 65535.0, srgb=False, bits=16)
    manifest = json.loads((tmp_path / "tif/capture.json").read_text().replace(".tif", ".png"))
    (png / "capture.json").write_text(json.dumps(manifest))
    a = merge_capture(load_capture(tmp_path / "tif"), progress=False)
    b = merge_capture(load_capture(png), progress=False)
    np.testing.assert_array_equal(np.asarray(a.ratio), np.asarray(b.ratio))  # same codes, same merge
    store = open_store(ingest_capture(tmp_path / "tif", tmp_path / "store", dtype="float32", progress=False))
    np.testing.assert_array_equal(np.asarray(store.observations().ratio), np.asarray(a.ratio))


def _jpeg_writer(path, rng):
    # smooth content: JPEG's error stays small, and Pillow's decode is the reference
    y, x = np.mgrid[0:SIZE[0], 0:SIZE[1]]
    base = rng.uniform(60, 190, 3)
    codes = np.clip(base + 8 * x[..., None] + 5 * y[..., None], 0, 255).astype(np.uint8)
    Image.fromarray(codes).save(path, quality=95)
    return codes


def test_jpeg_capture_decodes_as_pillow_and_ingests(tmp_path):
    written = _capture(tmp_path, "jpg", _jpeg_writer, response="srgb")
    assert image_header(tmp_path / "images/w0.jpg") == (SIZE, 3, "uint8")
    capture = load_capture(tmp_path)
    for name, codes in written.items():
        got = capture.read_codes(tmp_path / name)
        with Image.open(tmp_path / name) as image:
            decoded = np.asarray(image.convert("RGB"))
        np.testing.assert_array_equal(got, (decoded / 255.0).astype(np.float32), err_msg=name)
        # quality 95 on a smooth ramp: within 6 codes of what was written (JPEG is lossy)
        assert np.abs(decoded.astype(int) - codes).max() <= 6
    obs = merge_capture(capture, progress=False)
    store = open_store(ingest_capture(tmp_path, tmp_path / "store", dtype="float32", progress=False))
    np.testing.assert_array_equal(np.asarray(store.observations().ratio), np.asarray(obs.ratio))


def test_gray_jpeg_is_repeated_to_rgb(tmp_path):
    Image.fromarray(np.full(SIZE, 128, np.uint8)).save(tmp_path / "g.jpg", quality=100)
    assert image_header(tmp_path / "g.jpg") == (SIZE, 1, "uint8")


def _palette(index):
    image = Image.fromarray(index, mode="P")
    image.putpalette(list(range(256)) * 3)  # 256 colours: an 8-bit palette PNG
    return image


REFUSED = {
    "float TIFF": (lambda p: tifffile.imwrite(p, np.zeros(SIZE + (3,), np.float32), photometric="rgb"), "t.tif",
                   "TIFF pixel type float32"),
    "CMYK JPEG": (lambda p: Image.new("CMYK", SIZE[::-1]).save(p), "c.jpg", "JPEG mode CMYK"),
    "palette PNG": (lambda p: _palette(np.arange(20, dtype=np.uint8).reshape(SIZE)).save(p), "p.png",
                    "PNG colour type 3"),
    "1-bit PNG": (lambda p: Image.new("1", SIZE[::-1]).save(p), "b.png", "1-bit PNG"),
    "not an image": (lambda p: p.write_bytes(b"II*\x00garbage"), "x.tiff", "not a readable image"),
}


@pytest.mark.parametrize("case", sorted(REFUSED))
def test_refused_types_name_the_file(tmp_path, case):
    write, name, fragment = REFUSED[case]
    write(tmp_path / name)
    with pytest.raises(InputError) as info:
        image_header(tmp_path / name)
    assert str(info.value).startswith(f"{tmp_path / name}: ") and fragment in str(info.value)
    assert "\n" not in str(info.value)


def test_header_only_validation_reports_every_bad_image(tmp_path):
    _capture(tmp_path, "tif", _tiff_writer(8))
    tifffile.imwrite(tmp_path / "images/l1_e0.tif", np.zeros((4, 6, 3), np.uint8), photometric="rgb")
    tifffile.imwrite(tmp_path / "images/l2_e1.tif", np.zeros(SIZE + (3,), np.float32), photometric="rgb")
    with pytest.raises(CaptureError) as info:
        load_capture(tmp_path, headers_only=True)
    assert sorted(info.value.problems) == sorted([
        f"{tmp_path / 'images/l1_e0.tif'}: size 4x6 differs from capture.json's size 4x5 (H x W)",
        f"{tmp_path / 'images/l2_e1.tif'}: TIFF pixel type float32 (use 8/16-bit PNG or TIFF, JPEG, or EXR; "
        "float images as EXR)"])

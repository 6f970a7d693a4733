"""`write_manifest(IMAGES.csv, CAPTURE_DIR/capture.json)`: a capture manifest from a table of images.

The CSV has a header row and the columns `image` (a path relative to the CSV), `kind` (`light`
or `white`), `theta_deg` and `phi_deg` (lights; the direction toward the light, design.md's
sample frame) and `exposure_s` (seconds; when empty, the image's EXIF ExposureTime). Rows of one
light share (theta_deg, phi_deg); every light and the white board need one image per exposure of
the capture (the set of all exposures in the table). The manifest's image paths are made relative
to the manifest's directory; `size` comes from the images' headers.

Every problem is reported at once, one line each naming the CSV and its line number
(`IMAGES.csv:7: exposure_s: ...`), as `CaptureError` (the command line prints them and exits 2);
nothing is written then. The manifest is written atomically.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections import defaultdict
from pathlib import Path

from jaxrender.io import InputError, atomic_path

from .capture import CAPTURE_FORMAT, CAPTURE_VERSION, CaptureError, image_header
from .hdr import RESPONSES

__all__ = ["write_manifest", "exif_exposure_s", "MANIFEST_COLUMNS"]

MANIFEST_COLUMNS = ("image", "kind", "theta_deg", "phi_deg", "exposure_s")
_EXPOSURE_TIME, _EXIF_IFD = 0x829A, 0x8769  # EXIF tags: ExposureTime, the Exif sub-IFD


def exif_exposure_s(path: str | os.PathLike) -> float | None:
    """The EXIF ExposureTime of an image in seconds (Pillow), or None when it has none."""
    from PIL import Image

    try:
        with Image.open(path) as image:
            exif = image.getexif()
            value = exif.get_ifd(_EXIF_IFD).get(_EXPOSURE_TIME, exif.get(_EXPOSURE_TIME))
    except Exception:  # no EXIF reader for this type (EXR) or a damaged block: no exposure
        return None
    try:
        value = float(value)
    except (TypeError, ValueError, ZeroDivisionError):
        return None
    return value if math.isfinite(value) and value > 0 else None


def _number(text: str | None) -> float | None:
    try:
        value = float(text)
    except (TypeError, ValueError):
        return None
    return value if math.isfinite(value) else None


def _same(value: float) -> float:
    """Exposure times as keys: 1/100 typed as 0.01 and read from EXIF as 1/100 are one exposure."""
    return float(f"{value:.9g}")


def write_manifest(csv_path: str | os.PathLike, out: str | os.PathLike, *, response: str = "linear",
                   white_reflectance: float | list[float] = 1.0, view: tuple[float, float] = (0.0, 0.0)) -> Path:
    """Write the capture manifest `out` (usually `CAPTURE_DIR/capture.json`) from `csv_path`.

    `response`: how integer codes are linearised ("linear", or "srgb" for camera JPEGs);
    `white_reflectance`: the board's reflectance (a number or RGB); `view`: (theta_deg, phi_deg)
    of the camera. Returns `out`; raises `CaptureError` with one line per problem (module docstring).
    """
    csv_path, out = Path(csv_path), Path(out)
    problems: list[str] = []
    if response not in RESPONSES:
        problems.append(f"--response: {response!r} is not one of {RESPONSES}")
    refl = white_reflectance if isinstance(white_reflectance, list) else [white_reflectance]
    if len(refl) not in (1, 3) or not all(_number(str(r)) is not None and float(r) > 0 for r in refl):
        problems.append(f"--white-reflectance: {white_reflectance!r} is not a positive number or RGB triple")
    if not (len(view) == 2 and all(_number(str(v)) is not None for v in view) and 0 <= float(view[0]) < 90):
        problems.append(f"--view: {view!r} is not THETA PHI with theta in [0, 90)")
    if not csv_path.is_file():
        raise CaptureError(problems + [f"{csv_path}: no such file"])
    try:
        with open(csv_path, newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            rows = [(reader.line_num, row) for row in reader]
            columns = reader.fieldnames or []
    except (OSError, UnicodeDecodeError, csv.Error) as error:
        raise CaptureError(problems + [f"{csv_path}: not a readable CSV ({error})"]) from None
    missing = [c for c in MANIFEST_COLUMNS if c not in columns]
    if missing:
        raise CaptureError(problems + [f"{csv_path}: missing columns {', '.join(missing)} (has {', '.join(columns)})"])
    if not rows:
        raise CaptureError(problems + [f"{csv_path}: no image rows"])

    base = csv_path.parent
    entries = []  # (line, kind, angles or None, exposure, path)
    size = None
    for line, row in rows:
        where = f"{csv_path}:{line}"
        bad = []
        name = (row.get("image") or "").strip()
        kind = (row.get("kind") or "").strip()
        path = base / name
        if not name:
            bad.append(f"{where}: image: empty")
        elif not path.is_file():
            bad.append(f"{where}: {name}: missing image")
        else:
            try:
                shape, _, _ = image_header(path)
                if size is None:
                    size = (shape, line)
                elif shape != size[0]:
                    bad.append(f"{where}: {name}: size {shape[0]}x{shape[1]} differs from line {size[1]}'s "
                               f"{size[0][0]}x{size[0][1]}")
            except InputError as error:
                bad.append(f"{where}: {error}")
        if kind not in ("light", "white"):
            bad.append(f"{where}: kind: {kind!r} is not 'light' or 'white'")
        angles = None
        if kind == "light":
            theta, phi = _number(row.get("theta_deg")), _number(row.get("phi_deg"))
            if theta is None or not 0 <= theta < 90:
                bad.append(f"{where}: theta_deg: {row.get('theta_deg')!r} is not a number in [0, 90)")
            if phi is None:
                bad.append(f"{where}: phi_deg: {row.get('phi_deg')!r} is not a number")
            angles = (theta, phi)
        text = (row.get("exposure_s") or "").strip()
        exposure = _number(text) if text else (exif_exposure_s(path) if path.is_file() else None)
        if text and (exposure is None or exposure <= 0):
            bad.append(f"{where}: exposure_s: {text!r} is not a positive number of seconds")
        elif not text and exposure is None and name and path.is_file():
            bad.append(f"{where}: exposure_s: empty and {name} has no EXIF ExposureTime")
        problems += bad
        if not bad:
            entries.append((line, kind, angles, _same(exposure), name))

    exposures = sorted({e for _, _, _, e, _ in entries})
    groups: dict = defaultdict(list)  # ("white",) or ("light", theta, phi) -> [(line, exposure, name)]
    for line, kind, angles, exposure, name in entries:
        groups[("white",) if kind == "white" else ("light", *angles)].append((line, exposure, name))
    if ("white",) not in groups and entries:
        problems.append(f"{csv_path}: no white-board images (kind 'white')")
    if not any(key[0] == "light" for key in groups) and entries:
        problems.append(f"{csv_path}: no light images (kind 'light')")
    for key, images in groups.items():
        what = "the white board" if key == ("white",) else f"light (theta {key[1]:g}, phi {key[2]:g})"
        seen: dict = {}
        for line, exposure, _ in images:
            if exposure in seen:
                problems.append(f"{csv_path}:{line}: {what} has a second image for exposure {exposure:g} s "
                                f"(first on line {seen[exposure]})")
            seen.setdefault(exposure, line)
        lacking = [e for e in exposures if e not in seen]
        if lacking:
            problems.append(f"{csv_path}:{images[0][0]}: {what} has no image for exposure "
                            f"{', '.join(f'{e:g}' for e in lacking)} s")
    if problems:
        raise CaptureError(problems)

    def ordered(images):  # one path per exposure, by exposure, relative to the manifest
        by_exposure = {e: name for _, e, name in images}
        return [os.path.relpath((base / by_exposure[e]).resolve(), out.parent.resolve()) for e in exposures]

    manifest = {
        "format": CAPTURE_FORMAT, "version": CAPTURE_VERSION, "size": list(size[0]), "response": response,
        "exposures_s": exposures, "view": {"theta_deg": float(view[0]), "phi_deg": float(view[1])},
        "white": {"reflectance": float(refl[0]) if len(refl) == 1 else [float(r) for r in refl],
                  "images": ordered(groups[("white",)])},
        "lights": [{"theta_deg": key[1], "phi_deg": key[2], "images": ordered(images)}
                   for key, images in groups.items() if key[0] == "light"],
    }
    with atomic_path(out) as tmp:
        tmp.write_text(json.dumps(manifest, indent=1) + "\n")
    return out

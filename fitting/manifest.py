"""Capture manifests written from what a lab has: a table of images (`write_manifest`, IMAGES.csv)
or a photometric-stereo folder in the DiLiGenT layout (`write_folder_manifest`).

The CSV has a header row and the columns `image` (a path relative to the CSV), `kind` (`light` or
`white`), the direction toward the light as `theta_deg`, `phi_deg` or as a unit vector `light_x`,
`light_y`, `light_z` (design.md's sample frame), optionally its calibrated intensity as `intensity`
or `intensity_r`, `intensity_g`, `intensity_b`, and `exposure_s` (seconds; when empty, the image's
EXIF ExposureTime). Rows of one light share its direction; every light and the white board need
one image per exposure (the set of all exposures in the table); without a white board every light
needs an intensity.

A DiLiGenT-format folder holds `filenames.txt`, `light_directions.txt` (unit vectors, one a line),
`light_intensities.txt` (RGB, one a line), the 16-bit PNGs and optionally `mask.png`; its capture
refers to the images in place, one exposure of 1 s, no white board: the observation is the
benchmark's own normalisation, code / 65535 / intensity.

Every problem is reported at once, one line each naming the file and its line (`IMAGES.csv:7:
exposure_s: ...`), as `CaptureError` (the command line prints them and exits 2); nothing is written
then. The manifest is written atomically; its image paths are relative to the manifest's folder.
"""

from __future__ import annotations

import csv
import json
import math
import os
from collections import defaultdict
from pathlib import Path

import numpy as np

from jaxrender.io import InputError, Problems, atomic_path, image_header, output_file, read_image

from .capture import CAPTURE_FORMAT, CAPTURE_VERSION, UNIT_TOLERANCE, CaptureError
from .hdr import RESPONSES

__all__ = ["write_manifest", "write_folder_manifest", "exif_exposure_s", "MANIFEST_COLUMNS", "FOLDER_FILES"]

MANIFEST_COLUMNS = ("image", "kind", "exposure_s")  # and a direction: theta_deg, phi_deg or light_x, light_y, light_z
_ANGLES, _VECTOR = ("theta_deg", "phi_deg"), ("light_x", "light_y", "light_z")
_RGB_INTENSITY = ("intensity_r", "intensity_g", "intensity_b")
_EXPOSURE_TIME, _EXIF_IFD = 0x829A, 0x8769  # EXIF tags: ExposureTime, the Exif sub-IFD
FOLDER_FILES = ("filenames.txt", "light_directions.txt", "light_intensities.txt")


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


def _relative(path: Path, out: Path) -> str:
    """`path` relative to the manifest's folder when it is near it (at most two levels up), else absolute."""
    rel = os.path.relpath(path.resolve(), out.parent.resolve())
    return rel if not rel.startswith(os.path.join("..", "..", "..")) else str(path.resolve())


def _write(out: Path, manifest: dict, inputs: list[Path]) -> Path:
    output_file(out, inputs=inputs, make_folder=True)   # never over one of the files it describes
    with atomic_path(out) as tmp:
        tmp.write_text(json.dumps(manifest, indent=1) + "\n")
    return out


def _check_options(response, white_reflectance, view, problems: Problems) -> None:
    if response not in RESPONSES:
        problems.add(f"--response: {response!r} is not one of {RESPONSES}")
    refl = white_reflectance if isinstance(white_reflectance, list) else [white_reflectance]
    if len(refl) not in (1, 3) or not all(_number(str(r)) is not None and float(r) > 0 for r in refl):
        problems.add(f"--white-reflectance: {white_reflectance!r} is not a positive number or RGB triple")
    if not (len(view) == 2 and all(_number(str(v)) is not None for v in view) and 0 <= float(view[0]) < 90):
        problems.add(f"--view: {view!r} is not THETA PHI with theta in [0, 90)")


def _read_csv(csv_path: Path, problems: Problems) -> list[tuple[int, dict]]:
    """The rows (with their line numbers); the problems so far raised with the CSV's own."""
    if not csv_path.is_file():
        problems.add(f"{csv_path}: no such file")
        problems.check()
    try:
        with open(csv_path, newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            rows = [(reader.line_num, row) for row in reader]
            columns = reader.fieldnames or []
    except (OSError, UnicodeDecodeError, csv.Error) as error:
        problems.add(f"{csv_path}: not a readable CSV ({error})")
        problems.check()
    missing = [c for c in MANIFEST_COLUMNS if c not in columns]
    if not (set(_ANGLES) <= set(columns) or set(_VECTOR) <= set(columns)):
        missing.append(" and ".join(c for c in _ANGLES if c not in columns) + " (or light_x, light_y, light_z)")
    if missing:
        problems.add(f"{csv_path}: missing columns {', '.join(missing)} (has {', '.join(columns)})")
    elif not rows:
        problems.add(f"{csv_path}: no image rows")
    problems.check()
    return rows


def _row_direction(row: dict, where: str, bad: list[str]) -> tuple | None:
    """The light's key: (theta, phi) as given, or a unit vector (x, y, z) rounded to 1e-6."""
    if any((row.get(c) or "").strip() for c in _VECTOR):
        v = [_number(row.get(c)) for c in _VECTOR]
        if None in v:
            bad.append(f"{where}: light_x, light_y, light_z: {[row.get(c) for c in _VECTOR]} are not numbers")
            return None
        norm = math.sqrt(sum(x * x for x in v))
        if abs(norm - 1.0) > UNIT_TOLERANCE or v[2] <= 0:
            bad.append(f"{where}: light_x, light_y, light_z: {v} is not a unit vector above the horizon (z > 0)")
            return None
        return ("vector", *(round(x / norm, 6) for x in v))
    theta, phi = _number(row.get("theta_deg")), _number(row.get("phi_deg"))
    if theta is None or not 0 <= theta < 90:
        bad.append(f"{where}: theta_deg: {row.get('theta_deg')!r} is not a number in [0, 90)")
    if phi is None:
        bad.append(f"{where}: phi_deg: {row.get('phi_deg')!r} is not a number")
    return None if theta is None or phi is None or not 0 <= theta < 90 else ("angles", theta, phi)


def _row_intensity(row: dict, where: str, bad: list[str]) -> tuple | None:
    texts = [(row.get(c) or "").strip() for c in ("intensity", *_RGB_INTENSITY)]
    if not any(texts):
        return None
    values = [_number(t) for t in texts[1:]] if any(texts[1:]) else [_number(texts[0])] * 3
    if None in values or min(values) <= 0:
        bad.append(f"{where}: intensity: {[t for t in texts if t]} is not a positive number or RGB triple")
        return None
    return tuple(values)


def _describe(key: tuple) -> str:
    if key[0] == "white":
        return "the white board"
    if key[0] == "angles":
        return f"light (theta {key[1]:g}, phi {key[2]:g})"
    return f"light ({key[1]:g}, {key[2]:g}, {key[3]:g})"


def _rows(rows, base: Path, csv_path: Path, problems: Problems) -> tuple[list[tuple], tuple | None]:
    """(entries (line, key, exposure, name, intensity) of the good rows, (image size, its line))."""
    entries, size = [], None
    for line, row in rows:
        where, bad = f"{csv_path}:{line}", []
        name, kind = (row.get("image") or "").strip(), (row.get("kind") or "").strip()
        path = base / name
        if not name:
            bad.append(f"{where}: image: empty")
        elif not path.is_file():
            bad.append(f"{where}: {name}: missing image")
        else:
            try:
                shape = image_header(path).size
                if size is None:
                    size = (shape, line)
                elif shape != size[0]:
                    bad.append(f"{where}: {name}: size {shape[0]}x{shape[1]} differs from line {size[1]}'s "
                               f"{size[0][0]}x{size[0][1]}")
            except InputError as error:
                bad.append(f"{where}: {error}")
        if kind not in ("light", "white"):
            bad.append(f"{where}: kind: {kind!r} is not 'light' or 'white'")
        key = ("white",) if kind == "white" else _row_direction(row, where, bad) if kind == "light" else None
        intensity = _row_intensity(row, where, bad) if kind == "light" else None
        text = (row.get("exposure_s") or "").strip()
        exposure = _number(text) if text else (exif_exposure_s(path) if path.is_file() else None)
        if text and (exposure is None or exposure <= 0):
            bad.append(f"{where}: exposure_s: {text!r} is not a positive number of seconds")
        elif not text and exposure is None and name and path.is_file():
            bad.append(f"{where}: exposure_s: empty and {name} has no EXIF ExposureTime")
        problems.extend(bad)
        if not bad:
            entries.append((line, key, _same(exposure), name, intensity))
    return entries, size


def _groups(entries, csv_path: Path, problems: Problems) -> tuple[list[float], dict]:
    """(every exposure, key -> [(line, exposure, name, intensity)]) with each group's problems noted."""
    exposures = sorted({e for _, _, e, _, _ in entries})
    groups: dict = defaultdict(list)
    for line, key, exposure, name, intensity in entries:
        groups[key].append((line, exposure, name, intensity))
    lights = [key for key in groups if key[0] != "white"]
    with_intensity = [key for key in lights if all(i is not None for *_, i in groups[key])]
    if entries and not lights:
        problems.add(f"{csv_path}: no light images (kind 'light')")
    if ("white",) not in groups and entries and len(with_intensity) < len(lights):
        problems.add(f"{csv_path}: no white-board images (kind 'white'), and not every light has an intensity")
    if 0 < len(with_intensity) < len(lights):
        problems.add(f"{csv_path}: {len(with_intensity)} of {len(lights)} lights have an intensity: give every "
                        "light one, or none")
    for key, images in groups.items():
        seen: dict = {}
        for line, exposure, _, _ in images:
            if exposure in seen:
                problems.add(f"{csv_path}:{line}: {_describe(key)} has a second image for exposure {exposure:g} s "
                                f"(first on line {seen[exposure]})")
            seen.setdefault(exposure, line)
        lacking = [e for e in exposures if e not in seen]
        if lacking:
            problems.add(f"{csv_path}:{images[0][0]}: {_describe(key)} has no image for exposure "
                            f"{', '.join(f'{e:g}' for e in lacking)} s")
        if len({i for *_, i in images}) > 1:
            problems.add(f"{csv_path}:{images[0][0]}: {_describe(key)} has rows with different intensities")
    return exposures, groups


def write_manifest(csv_path: str | os.PathLike, out: str | os.PathLike, *, response: str = "linear",
                   white_reflectance: float | list[float] = 1.0, view: tuple[float, float] = (0.0, 0.0)) -> Path:
    """Write the capture manifest `out` (usually `CAPTURE_DIR/capture.json`) from `csv_path`.

    `response`: how integer codes are linearised ("linear", or "srgb" for camera JPEGs);
    `white_reflectance`: the board's reflectance (a number or RGB); `view`: (theta_deg, phi_deg)
    of the camera. Returns `out`; raises `CaptureError` with one line per problem (module docstring).
    """
    csv_path, out = Path(csv_path), output_file(out, make_folder=True)
    problems = Problems(error=CaptureError)
    _check_options(response, white_reflectance, view, problems)
    rows = _read_csv(csv_path, problems)
    base = csv_path.parent
    entries, size = _rows(rows, base, csv_path, problems)
    exposures, groups = _groups(entries, csv_path, problems)
    problems.check()

    def ordered(images):  # one path per exposure, by exposure, relative to the manifest
        by_exposure = {e: name for _, e, name, _ in images}
        return [_relative(base / by_exposure[e], out) for e in exposures]

    def light(key, images):
        entry = ({"theta_deg": key[1], "phi_deg": key[2]} if key[0] == "angles"
                 else {"direction": list(key[1:])})
        intensity = images[0][3]
        if intensity is not None:
            entry["intensity"] = intensity[0] if len(set(intensity)) == 1 else list(intensity)
        return {**entry, "images": ordered(images)}

    refl = white_reflectance if isinstance(white_reflectance, list) else [white_reflectance]
    manifest = {"format": CAPTURE_FORMAT, "version": CAPTURE_VERSION, "size": list(size[0]), "response": response,
                "exposures_s": exposures, "view": {"theta_deg": float(view[0]), "phi_deg": float(view[1])}}
    if ("white",) in groups:
        manifest["white"] = {"reflectance": float(refl[0]) if len(refl) == 1 else [float(r) for r in refl],
                             "images": ordered(groups[("white",)])}
    manifest["lights"] = [light(key, images) for key, images in groups.items() if key[0] != "white"]
    read = [csv_path] + [base / name for images in groups.values() for _, _, name, _ in images]
    return _write(out, manifest, read)


def _table(path: Path, columns: int, problems: Problems) -> list[list[float] | None] | None:
    """Rows of `columns` numbers of a whitespace-separated text file (None for a bad line, noted)."""
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as error:
        problems.add(f"{path}: cannot read ({error})")
        return None
    rows = []
    for number, text in enumerate(lines, start=1):
        if not text.strip():
            continue
        values = [_number(v) for v in text.replace(",", " ").split()]
        if len(values) != columns or None in values:
            problems.add(f"{path}:{number}: expected {columns} numbers, got {text.strip()!r}")
            values = None
        rows.append(values)
    return rows


def _folder_lights(folder: Path, problems: Problems) -> tuple[list[str], list, list] | None:
    """(image names, directions, intensities) of a DiLiGenT-format folder, or None after noting problems."""
    missing = [name for name in FOLDER_FILES if not (folder / name).is_file()]
    for name in missing:
        problems.add(f"{folder / name}: missing (a DiLiGenT-format folder has {', '.join(FOLDER_FILES)})")
    if missing:
        return None
    names = [line.strip() for line in (folder / "filenames.txt").read_text().splitlines() if line.strip()]
    dirs = _table(folder / "light_directions.txt", 3, problems)
    intensities = _table(folder / "light_intensities.txt", 3, problems)
    if dirs is None or intensities is None:
        return None
    counts = {"filenames.txt": len(names), "light_directions.txt": len(dirs),
              "light_intensities.txt": len(intensities)}
    if len(set(counts.values())) > 1:
        problems.add(f"{folder}: row counts differ: " + ", ".join(f"{k} {v}" for k, v in counts.items()))
        return None
    for i, (d, inten) in enumerate(zip(dirs, intensities), start=1):
        if d is None or inten is None:
            continue  # (noted)
        norm = math.sqrt(sum(x * x for x in d))
        if abs(norm - 1.0) > UNIT_TOLERANCE:
            problems.add(f"{folder / 'light_directions.txt'}:{i}: {d} is not a unit vector (length {norm:.4g})")
        elif d[2] <= 0:
            problems.add(f"{folder / 'light_directions.txt'}:{i}: {d} points downward (z must be > 0: toward the "
                         "camera's side)")
        if min(inten) <= 0:
            problems.add(f"{folder / 'light_intensities.txt'}:{i}: {inten} has a non-positive intensity")
    return names, dirs, intensities


def _folder_images(folder: Path, names: list[str], problems: Problems) -> tuple[int, int] | None:
    size, first = None, None
    for name in names:
        path = folder / name
        if not path.is_file():
            problems.add(f"{path}: missing image")
            continue
        try:
            header = image_header(path)
        except InputError as error:
            problems.add(str(error))
            continue
        if size is None:
            size, first = header.size, path
        elif header.size != size:
            problems.add(f"{path}: size {header.size[0]}x{header.size[1]} differs from {first.name}'s "
                         f"{size[0]}x{size[1]}")
    return size


def write_folder_manifest(folder: str | os.PathLike, out: str | os.PathLike) -> Path:
    """Write the capture manifest `out` of a DiLiGenT-format photometric-stereo folder (module
    docstring); the images stay in place. Returns `out`; raises `CaptureError` with one line per
    problem (missing files, row counts that differ, non-unit or downward directions, non-positive
    intensities, missing images or images of another size), nothing written then."""
    folder, out = Path(folder), output_file(out, make_folder=True)
    problems = Problems(error=CaptureError)
    if not folder.is_dir():
        raise CaptureError([f"{folder}: no such folder"])
    lights = _folder_lights(folder, problems)
    size = _folder_images(folder, lights[0], problems) if lights is not None else None
    mask = folder / "mask.png"
    if mask.is_file() and size is not None:
        try:
            if image_header(mask).size != size:
                problems.add(f"{mask}: size differs from the images' {size[0]}x{size[1]}")
            elif not np.any(read_image(mask, srgb=False)):
                problems.add(f"{mask}: no pixel is on the object (the mask is all zero)")
        except InputError as error:
            problems.add(str(error))
    problems.check()
    names, dirs, intensities = lights
    units = np.asarray(dirs, np.float64)
    units /= np.linalg.norm(units, axis=1, keepdims=True)
    manifest = {"format": CAPTURE_FORMAT, "version": CAPTURE_VERSION, "size": list(size), "response": "linear",
                "exposures_s": [1.0], "view": {"direction": [0.0, 0.0, 1.0]},
                "source": f"DiLiGenT-format folder {folder.resolve()}: observation = code / 65535 / intensity",
                "lights": [{"direction": [round(float(x), 9) for x in d], "intensity": [float(x) for x in inten],
                            "images": [_relative(folder / name, out)]}
                           for d, inten, name in zip(units, intensities, names)]}
    if mask.is_file():
        manifest["mask"] = _relative(mask, out)
    read = [folder / name for name in (*FOLDER_FILES, "mask.png", "Normal_gt.mat", *names)]
    return _write(out, manifest, read)

"""Capture directories (design.md, "Capture directory for fitting", extended: docs/formats.md):
loading and validation.

`load_capture` reads the manifest with the shared field reader (`jaxrender.io.Fields`) and then
checks every image (existence, type, size; pixels too unless `headers_only`), reporting every
problem at once as one `CaptureError`, one line each naming the file, and stopping after
`MAX_PROBLEMS` of them (a huge broken manifest fails within seconds). Integer images (8/16-bit
PNG or TIFF, JPEG) are code values, linearised by the capture's `response`; EXR images are linear
radiance.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import itertools
import json
import os
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from jaxrender.io import (
    IMAGE_SUFFIXES,
    MAX_PROBLEMS,
    SUPPORTED_IMAGES,
    Fields,
    InputError,
    InputErrors,
    image_header,
    is_number,
    read_exr,
    read_image,
)

__all__ = ["CAPTURE_FORMAT", "CAPTURE_VERSION", "CaptureError", "Capture", "ImageLists", "load_capture",
           "direction_from_angles", "angles_from_direction", "MAX_IMAGE_PROBLEMS", "UNIT_TOLERANCE"]

CAPTURE_FORMAT = "jaxrender-capture"
CAPTURE_VERSION = 1
MAX_IMAGE_PROBLEMS = MAX_PROBLEMS  # the problems reported before a validation stops
UNIT_TOLERANCE = 1e-3  # a light's `direction` may differ from unit length by this much (it is normalised)
MANIFEST_FIELDS = ("format", "version", "size", "response", "exposures_s", "view", "white", "lights", "mask",
                   "saturation", "source", "synth", "notes")  # source, synth, notes: free-form, for people
RESPONSES = ("linear", "srgb")
_CHECK_BATCH = 256  # images checked per round of the thread pool (a huge capture is never queued at once)


class CaptureError(InputErrors):
    """Every problem of a capture directory, one `PATH: problem` line each (str joins them)."""


def direction_from_angles(theta_deg, phi_deg) -> np.ndarray:
    """Unit vector(s) from the sample toward a light/camera: (sin t cos p, sin t sin p, cos t)."""
    t, p = np.radians(np.asarray(theta_deg, np.float64)), np.radians(np.asarray(phi_deg, np.float64))
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)


def angles_from_direction(direction) -> np.ndarray:
    """(theta_deg, phi_deg) of unit vector(s) `... 3`, phi in (-180, 180], rounded to 1e-9 degrees
    (angles given in a manifest come back as written)."""
    d = np.asarray(direction, np.float64)
    theta = np.degrees(np.arccos(np.clip(d[..., 2], -1.0, 1.0)))
    return np.round(np.stack([theta, np.degrees(np.arctan2(d[..., 1], d[..., 0]))], axis=-1), 9) + 0.0


class ImageLists(Sequence):
    """The image paths of every light, one tuple per light, resolved against the capture directory
    on access (the manifest's own strings are kept: no per-image objects for a million lights)."""

    def __init__(self, root: Path, names: Sequence[Sequence[str]]):
        self.root, self.names = root, names

    def __len__(self) -> int:
        return len(self.names)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        return tuple(self.root / name for name in self.names[index])

    def __iter__(self) -> Iterator[tuple[Path, ...]]:
        return (tuple(self.root / name for name in names) for names in self.names)

    def all_paths(self) -> Iterator[Path]:
        return (self.root / name for names in self.names for name in names)


@dataclasses.dataclass(frozen=True)
class Capture:
    """A validated capture. Directions are unit vectors in the sample frame (x = image columns,
    y = rows toward the top, z = toward the camera).

    Observation of a texel under light l = radiance / `light_intensities[l]` (per channel, when the
    lights carry intensities) / white-board radiance * `white_reflectance` (when there is a white
    board). `encoding`: "codes" (integer images: code values, the HDR merge's hat applies) or
    "radiance" (EXR: linear values, saturated only at or above `saturation` when given).
    """

    root: Path
    size: tuple[int, int]
    response: str  # "linear" or "srgb": how integer codes are linearised
    exposures_s: tuple[float, ...]
    view_dir: np.ndarray  # 3
    light_dirs: np.ndarray  # L 3
    light_images: ImageLists  # L x E
    white_images: tuple[Path, ...] = ()  # one per exposure; () without a white board
    white_reflectance: np.ndarray | None = None  # 3
    light_intensities: np.ndarray | None = None  # L 3
    mask: Path | None = None  # texels where it is 0 are not fitted
    saturation: float | None = None  # EXR radiance at or above this is saturated
    encoding: str = "codes"
    manifest: dict = dataclasses.field(repr=False, default_factory=dict)

    @property
    def n_lights(self) -> int:
        return len(self.light_images)

    @property
    def has_white(self) -> bool:
        return bool(self.white_images)

    @property
    def light_angles(self) -> np.ndarray:
        """`L 2` (theta_deg, phi_deg) of the light directions."""
        return angles_from_direction(self.light_dirs)

    @property
    def view_angles(self) -> tuple[float, float]:
        theta, phi = angles_from_direction(self.view_dir)
        return (float(theta), float(phi))

    @property
    def merge_response(self) -> str:
        """The response the merge linearises with (EXR radiance is already linear)."""
        return "linear" if self.encoding == "radiance" else self.response

    def intensities(self) -> np.ndarray:
        """`L 3` per-light intensities (ones when the lights carry none)."""
        return np.ones((self.n_lights, 3)) if self.light_intensities is None else self.light_intensities

    def read_mask(self) -> np.ndarray:
        """`H W` bool: the texels to fit (all when the capture has no mask)."""
        if self.mask is None:
            return np.ones(self.size, bool)
        return np.any(read_image(self.mask, srgb=False)[..., :3] > 0, axis=-1)

    def read_codes(self, path: str | os.PathLike) -> np.ndarray:
        """One image as float32 `H W 3`: integer codes / full scale (not linearised: saturation is
        judged on the raw code), or EXR values as they are. Gray is repeated to RGB, alpha dropped."""
        return _to_rgb(read_image(path, srgb=False))

    def read_checked(self, path: str | os.PathLike) -> tuple[np.ndarray | None, list[str]]:
        """(`read_codes` of one image, its problems): the pixel checks `load_capture` skips with
        `headers_only` (decodable in full, of the manifest's size, finite values)."""
        path = Path(path)
        try:
            codes = self.read_codes(path)
        except InputError as error:
            return None, [str(error)]
        except Exception as error:  # decoders raise many types for corrupt files
            return None, [f"{path}: not a readable image ({type(error).__name__}: {error})"]
        problems = []
        if tuple(codes.shape[:2]) != tuple(self.size):
            problems.append(f"{path}: size {codes.shape[0]}x{codes.shape[1]} differs from capture.json's size "
                            f"{self.size[0]}x{self.size[1]} (H x W)")
        bad = ~np.isfinite(codes)
        if bad.any():
            kinds = ", ".join(k for k, m in (("NaN", np.isnan(codes)), ("Inf", np.isinf(codes))) if m.any())
            problems.append(f"{path}: {int(bad.sum())} non-finite values ({kinds})")
        return (None if problems else codes), problems


def _to_rgb(image: np.ndarray) -> np.ndarray:
    if image.shape[2] == 1:
        image = np.repeat(image, 3, axis=2)
    return np.ascontiguousarray(image[..., :3], dtype=np.float32)


# -- the manifest, section by section ----------------------------------------------------------------


def _size(doc: Fields) -> tuple[int, int] | None:
    size = doc.raw("size")
    if size is None:
        return None
    if not (isinstance(size, list) and len(size) == 2
            and all(isinstance(s, int) and not isinstance(s, bool) and s > 0 for s in size)):
        doc.problem("size", f"{size!r} is not [H, W] with positive integers")
        return None
    return int(size[0]), int(size[1])


def _exposures(doc: Fields) -> tuple[float, ...] | None:
    exposures = doc.raw("exposures_s")
    if exposures is None:
        return None
    if not (isinstance(exposures, list) and exposures and all(is_number(e) and e > 0 for e in exposures)):
        doc.problem("exposures_s", "must be a non-empty list of positive numbers (seconds)")
        return None
    if len(set(exposures)) != len(exposures):
        doc.problem("exposures_s", "exposure times must be distinct")
        return None
    return tuple(float(e) for e in exposures)


def _direction(f: Fields) -> np.ndarray | None:
    """A unit vector toward the light (camera) from `direction` [x, y, z] or `theta_deg`/`phi_deg`,
    strictly above the horizon."""
    if f.has("direction"):
        d = f.vector("direction")
        if d is None:
            return None
        norm = float(np.linalg.norm(d))
        if abs(norm - 1.0) > UNIT_TOLERANCE:
            f.problem("direction", f"{d.tolist()} is not a unit vector (length {norm:.4g})")
            return None
        if d[2] <= 0:
            f.problem("direction", f"{d.tolist()} is at or below the horizon (z must be > 0)")
            return None
        return d / norm
    theta, phi = f.raw("theta_deg"), f.raw("phi_deg")  # (a missing one is noted)
    ok = True
    if theta is not None and not is_number(theta):
        f.problem("theta_deg", f"{theta!r} is not a finite number")
        ok = False
    elif theta is not None and theta >= 90:
        f.problem("theta_deg", f"{theta} is at or below the horizon (must be < 90)")
        ok = False
    elif theta is not None and theta < 0:
        f.problem("theta_deg", f"{theta} is negative (must be in [0, 90))")
        ok = False
    if phi is not None and not is_number(phi):
        f.problem("phi_deg", f"{phi!r} is not a finite number")
        ok = False
    if theta is None or phi is None or not ok:
        return None
    return direction_from_angles(theta, phi)


def _images(f: Fields, key: str, n_exposures: int | None) -> list[str] | None:
    names = f.strings(key)
    if names is not None and n_exposures is not None and len(names) != n_exposures:
        f.problem(key, f"{len(names)} images for {n_exposures} exposures in exposures_s")  # (still checked)
    return names


def _white(f: Fields, n_exposures: int | None) -> tuple[np.ndarray | None, list[str] | None]:
    if not f.valid:
        return None, None
    f.known(("reflectance", "images"))
    reflectance = f.raw("reflectance")  # (noted when missing)
    if reflectance is not None and not ((is_number(reflectance) and reflectance > 0) or (
            isinstance(reflectance, list) and len(reflectance) == 3
            and all(is_number(x) and x > 0 for x in reflectance))):
        f.problem("reflectance", f"{reflectance!r} is not a positive number or RGB triple")
        reflectance = None
    refl = None if reflectance is None else np.broadcast_to(np.asarray(reflectance, np.float64), (3,)).copy()
    return refl, _images(f, "images", n_exposures)


def _lights(doc: Fields, n_exposures: int | None):
    """(directions `L 3`, image names per light, intensities `L 3` or None) of the valid lights."""
    items = doc.items("lights", nonempty=True)
    dirs, names, intensities, with_intensity = [], [], [], 0
    for f in items:
        f.known(("theta_deg", "phi_deg", "direction", "intensity", "images"))
        dirs.append(_direction(f))
        names.append(_images(f, "images", n_exposures))
        if f.has("intensity"):
            with_intensity += 1
            intensities.append(f.rgb("intensity", positive=True))
    if 0 < with_intensity < len(items):
        doc.problem("lights", f"{with_intensity} of {len(items)} lights carry an intensity: give every light one, "
                              "or none")
    return dirs, names, (intensities if with_intensity == len(items) and items else None)


def _read_manifest(root: Path) -> dict:
    manifest_path = root / "capture.json"
    if not root.is_dir():
        raise CaptureError([f"{root}: no such capture directory"])
    if not manifest_path.is_file():
        raise CaptureError([f"{manifest_path}: missing (a capture directory needs capture.json)"])
    try:
        manifest = json.loads(manifest_path.read_text())
    except (OSError, UnicodeDecodeError) as error:
        raise CaptureError([f"{manifest_path}: unreadable ({error})"]) from None
    except json.JSONDecodeError as error:
        raise CaptureError([f"{manifest_path}: not valid JSON ({error})"]) from None
    return manifest


# -- images ---------------------------------------------------------------------------------------------


def _image_problems(path: Path, size: tuple[int, int] | None, check_pixels: bool,
                    headers_only: bool) -> tuple[list[str], tuple[int, int] | None]:
    """(problems of one image file (empty when fine), its H x W or None when unreadable)."""
    if not path.exists():
        return [f"{path}: missing image"], None
    if not path.is_file():
        return [f"{path}: not a file"], None
    suffix = path.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        return [f"{path}: unsupported image type {suffix or '(none)'!r} ({SUPPORTED_IMAGES})"], None
    problems = []
    try:
        shape = image_header(path).size  # type, bit depth and channel layout, as the header says
        if not headers_only and suffix == ".exr":
            channels = read_exr(path)
            names = ["R", "G", "B"] if all(c in channels for c in "RGB") else ["Y"]
            image = np.stack([channels[n] for n in names], axis=-1)
            shape = image.shape[:2]
            if check_pixels and not np.isfinite(image).all():
                kinds = ", ".join(k for k, m in (("NaN", np.isnan(image)), ("Inf", np.isinf(image))) if m.any())
                problems.append(f"{path}: {int((~np.isfinite(image)).sum())} non-finite values ({kinds})")
        elif not headers_only:
            shape = read_image(path, srgb=False).shape[:2]  # decoded in full: a truncated file fails here
    except InputError as error:
        return [str(error)], None
    except Exception as error:  # decoders raise many types for corrupt files
        return [f"{path}: not a readable image ({type(error).__name__}: {error})"], None
    if size is not None and tuple(shape) != tuple(size):
        problems.append(f"{path}: size {shape[0]}x{shape[1]} differs from capture.json's size "
                        f"{size[0]}x{size[1]} (H x W)")
    return problems, tuple(shape)


def _check_images(paths: Iterator[Path], size, problems, *, check_pixels: bool, headers_only: bool,
                  workers: int) -> None:
    """Every image checked (threads: the decoders release the GIL) in rounds of `_CHECK_BATCH`, each
    problem noted; `problems` stops the check once it holds `MAX_PROBLEMS` lines. Without a usable
    size in the manifest the images must agree with the first readable one."""
    first = None
    seen: set[Path] = set()
    with concurrent.futures.ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        while batch := [p for p in itertools.islice(paths, _CHECK_BATCH) if not (p in seen or seen.add(p))]:
            results = pool.map(lambda p: _image_problems(p, size, check_pixels, headers_only), batch)
            for path, (lines, shape) in zip(batch, results, strict=True):
                problems.extend(lines)
                if size is None and shape is not None:
                    if first is None:
                        first = (path, shape)
                    elif shape != first[1]:
                        problems.add(f"{path}: size {shape[0]}x{shape[1]} differs from {first[0]}'s "
                                     f"{first[1][0]}x{first[1][1]}")
            if len(seen) > 4 * _CHECK_BATCH:
                seen.clear()  # duplicates are only skipped nearby: memory stays bounded


def load_capture(capture_dir: str | os.PathLike, *, check_pixels: bool = True, headers_only: bool = False,
                 workers: int = 4) -> Capture:
    """Load and validate a capture directory; raise `CaptureError` listing every problem.

    Checked: capture.json (present, JSON, format "jaxrender-capture", version 1, no unknown field),
    every field and its type (`size`, `response`, `exposures_s`, `view`, `white` (optional when every
    light carries an `intensity`), `lights` (each: `theta_deg`/`phi_deg` or a unit `direction`
    strictly above the horizon, optional `intensity`, one image per exposure), `mask`,
    `saturation`), and every image: present, readable, of a supported type and of the manifest's
    size; decoded in full and (EXR, when `check_pixels`) free of NaN/Inf unless `headers_only`,
    where only headers are read and the reader of the pixels checks the rest
    (`Capture.read_checked`). Image paths are absolute or relative to the capture directory.
    """
    root = Path(capture_dir)
    manifest_path = root / "capture.json"
    doc = Fields.document(_read_manifest(root), manifest_path, error=CaptureError)
    doc.known(MANIFEST_FIELDS)
    if doc.raw("format", default=None) != CAPTURE_FORMAT:
        doc.problem("format", f"{doc.raw('format', default=None)!r} is not {CAPTURE_FORMAT!r}")
    if doc.raw("version", default=None) != CAPTURE_VERSION:
        doc.problem("version", f"unknown version {doc.raw('version', default=None)!r} "
                               f"(this reader knows {CAPTURE_VERSION})")
    size = _size(doc)
    response = doc.raw("response")
    if response is not None and response not in RESPONSES:
        doc.problem("response", f"{response!r} is not 'linear' or 'srgb'")
    exposures = _exposures(doc)
    view_fields = doc.section("view")
    view_fields.known(("theta_deg", "phi_deg", "direction"))
    view = _direction(view_fields) if view_fields.valid else None
    white_fields = doc.section("white", required=False)
    reflectance, white_names = _white(white_fields, None if exposures is None else len(exposures))
    dirs, names, intensities = _lights(doc, None if exposures is None else len(exposures))
    if not white_fields.valid and intensities is None and doc.has("lights"):
        doc.problem("white", "missing (a capture needs a white board unless every light carries an intensity)")
    mask_name = doc.string("mask", default=None)
    saturation = doc.number("saturation", default=None, lo=0.0, lo_open=True)
    lights_ok = bool(dirs) and all(d is not None for d in dirs) and all(n is not None for n in names)

    # every image, once, after the manifest's own problems (a typo is found before any file is opened)
    images = ImageLists(root, [n for n in names if n is not None])
    white_paths = [root / p for p in (white_names or [])]
    mask_paths = [] if mask_name is None else [root / mask_name]
    exr = {name.lower().endswith(".exr") for name in itertools.chain(white_names or [], *(n for n in names if n))}
    if len(exr) > 1:
        doc.problem("lights", "the capture mixes EXR radiance and integer images: use one kind")
    _check_images(itertools.chain(white_paths, images.all_paths(), mask_paths), size, doc.problems,
                  check_pixels=check_pixels, headers_only=headers_only, workers=workers)
    doc.problems.check()
    if not lights_ok or response is None or exposures is None or view is None or size is None:
        raise CaptureError([f"{manifest_path}: incomplete"])  # (every missing field was noted above)
    encoding = "radiance" if exr == {True} else "codes"
    return Capture(
        root=root.resolve(), size=size, response=response, exposures_s=exposures, view_dir=view,
        light_dirs=np.asarray(dirs, np.float64).reshape(-1, 3), light_images=ImageLists(root.resolve(), names),
        white_images=tuple(p.resolve() if not p.is_absolute() else p for p in white_paths),
        white_reflectance=reflectance,
        light_intensities=None if intensities is None else np.asarray(intensities, np.float64).reshape(-1, 3),
        mask=None if mask_name is None else (root / mask_name).resolve(), saturation=saturation, encoding=encoding,
        manifest=doc.data)

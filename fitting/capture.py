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
import json
import math
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
# other keys are ignored, as version 1 always did (`fitting synth` records its settings under `synth`)
MANIFEST_FIELDS = ("format", "version", "size", "response", "exposures_s", "view", "white", "lights", "mask",
                   "saturation", "encoding")
ENCODINGS = ("codes", "radiance")
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
        mask = np.any(read_image(self.mask, srgb=False)[..., :3] > 0, axis=-1)
        if not mask.any():
            raise CaptureError([f"{self.mask}: no texel is on the object (the mask is all zero): nothing to fit"])
        return mask

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


def _direction(f: Fields) -> tuple[float, float, float] | None:
    """A unit vector toward the light (camera) from `direction` [x, y, z] or `theta_deg`/`phi_deg`,
    strictly above the horizon (plain floats: a million lights are read without an array each)."""
    if f.has("direction"):
        d = f.raw("direction")
        if not (isinstance(d, list) and len(d) == 3 and all(is_number(x) for x in d)):
            f.problem("direction", f"expected a list of 3 numbers, got {d!r}")
            return None
        norm = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        if abs(norm - 1.0) > UNIT_TOLERANCE:
            f.problem("direction", f"{[float(x) for x in d]} is not a unit vector (length {norm:.4g})")
            return None
        if d[2] <= 0:
            f.problem("direction", f"{[float(x) for x in d]} is at or below the horizon (z must be > 0)")
            return None
        return (d[0] / norm, d[1] / norm, d[2] / norm)
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
    t, p = math.radians(theta), math.radians(phi)
    return (math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t))


def _images(f: Fields, key: str, n_exposures: int | None) -> list[str] | None:
    names = f.strings(key)
    if names is not None and n_exposures is not None and len(names) != n_exposures:
        f.problem(key, f"{len(names)} images for {n_exposures} exposures in exposures_s")  # (still checked)
    return names


def _white(f: Fields, n_exposures: int | None) -> tuple[np.ndarray | None, list[str] | None]:
    if not f.valid:
        return None, None
    reflectance = f.raw("reflectance")  # (noted when missing)
    if reflectance is not None and not ((is_number(reflectance) and reflectance > 0) or (
            isinstance(reflectance, list) and len(reflectance) == 3
            and all(is_number(x) and x > 0 for x in reflectance))):
        f.problem("reflectance", f"{reflectance!r} is not a positive number or RGB triple")
        reflectance = None
    refl = None if reflectance is None else np.broadcast_to(np.asarray(reflectance, np.float64), (3,)).copy()
    return refl, _images(f, "images", n_exposures)


def _lights(doc: Fields, n_exposures: int | None, root: Path, images: "_ImageChecker"):
    """(directions `L 3`, image names per light (the manifest's own lists), intensities `L 3` or None,
    the set of "is EXR" of their images), reading the lights and checking their images a batch of
    `_CHECK_BATCH` at a time: the first problems of a huge manifest stop it within seconds."""
    entries = doc.raw("lights")
    if entries is None:
        return np.zeros((0, 3)), [], None, set()
    if not isinstance(entries, list) or not entries:
        doc.problem("lights", "must be a non-empty list of lights")
        return np.zeros((0, 3)), [], None, set()
    n = len(entries)
    dirs, intensities = np.full((n, 3), np.nan), np.full((n, 3), np.nan)
    names: list = [None] * n
    with_intensity, exr = 0, set()
    for start in range(0, n, _CHECK_BATCH):
        paths = []
        for i in range(start, min(start + _CHECK_BATCH, n)):
            f = Fields(entries[i], f"lights[{i}]", doc.source, doc.problems)
            if not f.valid:
                f.problem(None, "expected an object")
                continue
            d = _direction(f)
            if d is not None:
                dirs[i] = d
            names[i] = _images(f, "images", n_exposures)
            if f.has("intensity"):
                with_intensity += 1
                rgb = f.rgb("intensity", positive=True)
                if rgb is not None:
                    intensities[i] = rgb
            paths += [root / name for name in names[i] or ()]
            exr |= {name.lower().endswith(".exr") for name in names[i] or ()}
        images.check(paths)
    if 0 < with_intensity < n:
        doc.problem("lights", f"{with_intensity} of {n} lights carry an intensity: give every light one, or none")
    return dirs, names, (intensities if with_intensity == n else None), exr


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


class _ImageChecker:
    """Checks images batch by batch (threads: the decoders release the GIL), noting each problem;
    the shared `Problems` stops the validation at `MAX_PROBLEMS` lines. Without a usable size in
    the manifest the images must agree with the first readable one."""

    def __init__(self, size, problems, *, check_pixels: bool, headers_only: bool, workers: int):
        self.size, self.problems = size, problems
        self.options = dict(check_pixels=check_pixels, headers_only=headers_only)
        self.first = None
        self.pool = concurrent.futures.ThreadPoolExecutor(max_workers=max(1, workers))

    def check(self, paths: list[Path]) -> None:
        paths = list(dict.fromkeys(paths))
        results = self.pool.map(lambda p: _image_problems(p, self.size, **self.options), paths)
        for path, (lines, shape) in zip(paths, results, strict=True):
            self.problems.extend(lines)
            if self.size is None and shape is not None:
                if self.first is None:
                    self.first = (path, shape)
                elif shape != self.first[1]:
                    self.problems.add(f"{path}: size {shape[0]}x{shape[1]} differs from {self.first[0]}'s "
                                      f"{self.first[1][0]}x{self.first[1][1]}")

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)


def load_capture(capture_dir: str | os.PathLike, *, check_pixels: bool = True, headers_only: bool = False,
                 workers: int = 4) -> Capture:
    """Load and validate a capture directory; raise `CaptureError` listing every problem.

    Checked: capture.json (present, JSON, format "jaxrender-capture", version 1; other keys ignored),
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
    view = _direction(view_fields) if view_fields.valid else None
    white_fields = doc.section("white", required=False)
    reflectance, white_names = _white(white_fields, None if exposures is None else len(exposures))
    mask_name = doc.string("mask", default=None)
    saturation = doc.number("saturation", default=None, lo=0.0, lo_open=True)
    declared = doc.string("encoding", default=None)
    if declared is not None and declared not in ENCODINGS:
        doc.problem("encoding", f"{declared!r} is not 'codes' or 'radiance'")
    white_paths = [root / p for p in (white_names or [])]
    # the images with the entries that name them, batch by batch (the problems stop at MAX_PROBLEMS)
    images = _ImageChecker(size, doc.problems, check_pixels=check_pixels, headers_only=headers_only, workers=workers)
    try:
        images.check(white_paths + ([] if mask_name is None else [root / mask_name]))
        dirs, names, intensities, exr = _lights(doc, None if exposures is None else len(exposures), root, images)
    finally:
        images.close()
    if not white_fields.valid and intensities is None and len(names) > 0:   # (no lights: noted above)
        doc.problem("white", "missing (a capture needs a white board unless every light carries an intensity)")
    exr |= {name.lower().endswith(".exr") for name in white_names or ()}
    if len(exr) > 1:
        doc.problem("lights", "the capture mixes EXR radiance and integer images: use one kind")
    doc.problems.check()
    if response is None or exposures is None or view is None or size is None or np.isnan(dirs).any():
        raise CaptureError([f"{manifest_path}: incomplete"])  # (every missing field was noted above)
    if declared == "radiance" and exr != {True}:
        doc.problem("encoding", "'radiance' needs EXR images (integer images are codes)")
        doc.problems.check()
    # EXR is radiance unless the manifest says its floats are a camera's codes (`fitting synth`)
    encoding = declared or ("radiance" if exr == {True} else "codes")
    return Capture(
        root=root.resolve(), size=size, response=response, exposures_s=exposures, view_dir=np.asarray(view),
        light_dirs=dirs, light_images=ImageLists(root.resolve(), names),
        white_images=tuple(p.resolve() if not p.is_absolute() else p for p in white_paths),
        white_reflectance=reflectance,
        light_intensities=intensities,
        mask=None if mask_name is None else (root / mask_name).resolve(), saturation=saturation, encoding=encoding,
        manifest=doc.data)

"""Capture directories (design.md, "Capture directory for fitting"): loading and validation.

`load_capture` checks everything before any work starts (the manifest, every field, every image:
existence, readability, pixel type, size, NaN/Inf in EXR) and raises one `CaptureError` listing
every problem found, one line each, naming the file. The command lines print it and exit with 2.
With `headers_only=True` (the streaming ingest, `fitting.ingest`) each image is checked by its
header alone (existence, type, bit depth, channels, size) and the pixels are checked as they are
read (`Capture.read_checked`).

Images: 8/16-bit PNG, 8/16-bit TIFF, JPEG (8-bit; a camera's JPEG is sRGB: `response: "srgb"`)
and EXR. Integer codes are normalised to full scale and linearised by the capture's `response`.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import json
import math
import os
from pathlib import Path

import numpy as np

from jaxrender.io import InputError, linear_to_srgb, read_exr, read_image

__all__ = ["CAPTURE_FORMAT", "CAPTURE_VERSION", "CaptureError", "Capture", "load_capture", "MAX_IMAGE_PROBLEMS",
           "IMAGE_SUFFIXES", "image_header"]

CAPTURE_FORMAT = "jaxrender-capture"
CAPTURE_VERSION = 1
MAX_IMAGE_PROBLEMS = 200  # beyond this many image problems the rest are summarised in one line
IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".exr")
_SUPPORTED = "use 8/16-bit PNG or TIFF, JPEG, or EXR"


class CaptureError(InputError):
    """Every problem of a capture directory, one `PATH: problem` line each (str joins them)."""

    def __init__(self, problems: list[str]):
        self.problems = list(problems)
        super().__init__(None, "\n".join(self.problems))


@dataclasses.dataclass(frozen=True)
class Capture:
    """A validated capture. Image paths are the capture directory joined with the manifest's;
    directions are unit vectors in the sample frame (x = image columns, y = rows toward the top,
    z = toward the camera)."""

    root: Path
    size: tuple[int, int]
    response: str  # "linear" or "srgb": how PNG code values are linearised
    exposures_s: tuple[float, ...]
    view_angles: tuple[float, float]  # (theta_deg, phi_deg)
    view_dir: np.ndarray  # 3
    white_reflectance: np.ndarray  # 3 (a scalar in the manifest is repeated)
    white_images: tuple[Path, ...]  # one per exposure
    light_angles: np.ndarray  # L 2 (theta_deg, phi_deg)
    light_dirs: np.ndarray  # L 3
    light_images: tuple[tuple[Path, ...], ...]  # L x E
    manifest: dict = dataclasses.field(repr=False, default_factory=dict)

    @property
    def n_lights(self) -> int:
        return len(self.light_images)

    def read_codes(self, path: str | os.PathLike) -> np.ndarray:
        """Raw code values of one image as float32 `H W 3`, normalised to full scale.

        PNG: integer codes / (2^8 - 1 or 2^16 - 1), NOT linearised (saturation is judged on the
        raw code; `fitting.hdr` linearises by `response`). EXR: its linear values, sRGB-encoded
        when the capture's response is "srgb" so that one response applies to all images.
        Gray images are repeated to RGB, alpha is dropped.
        """
        path = Path(path)
        if path.suffix.lower() == ".exr":
            image = read_image(path)
            if self.response == "srgb":
                image = np.asarray(linear_to_srgb(image), np.float32)
        else:
            image = read_image(path, srgb=False)
        return _to_rgb(image)

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


def image_header(path: str | os.PathLike) -> tuple[tuple[int, int], int, str]:
    """((H, W), channels, pixel type) of an image from its header alone, without decoding pixels.

    Pixel type: "uint8", "uint16" (PNG, TIFF, JPEG) or "float" (EXR). Raises `InputError` naming
    the file for an unsupported type, bit depth or channel layout, or an unreadable header.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise InputError(path, f"unsupported image type {suffix or '(none)'!r} ({_SUPPORTED})")
    try:
        if suffix == ".png":
            return _png_header(path)
        if suffix in (".tif", ".tiff"):
            return _tiff_header(path)
        if suffix in (".jpg", ".jpeg"):
            return _jpeg_header(path)
        return _exr_header(path)
    except InputError:
        raise
    except Exception as error:  # decoders raise many types for corrupt headers
        raise InputError(path, f"not a readable image ({type(error).__name__}: {error})") from None


_PNG_CHANNELS = {0: 1, 2: 3, 6: 4}  # colour type -> channels (gray, RGB, RGBA); palette and gray+alpha refused


def _png_header(path: Path):
    with open(path, "rb") as f:
        head = f.read(33)
    if len(head) < 33 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        raise InputError(path, "not a readable image (no PNG header)")
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    depth, colour = head[24], head[25]
    if depth not in (8, 16):
        raise InputError(path, f"{depth}-bit PNG ({_SUPPORTED})")
    if colour not in _PNG_CHANNELS:
        raise InputError(path, f"PNG colour type {colour} (use gray, RGB or RGBA)")
    return (height, width), _PNG_CHANNELS[colour], f"uint{depth}"


def _tiff_header(path: Path):
    import tifffile

    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        shape, dtype = tuple(page.shape), np.dtype(page.dtype)
        samples = int(page.samplesperpixel)
    if dtype not in (np.uint8, np.uint16):
        raise InputError(path, f"TIFF pixel type {dtype} ({_SUPPORTED}; float images as EXR)")
    if len(shape) not in (2, 3) or samples not in (1, 3, 4):
        raise InputError(path, f"TIFF of shape {shape} (use gray, RGB or RGBA)")
    if len(shape) == 3 and shape[0] == samples and shape[2] != samples:
        raise InputError(path, "planar (separate-plane) TIFF (use interleaved gray, RGB or RGBA)")
    return (int(shape[0]), int(shape[1])), samples, str(dtype)


def _jpeg_header(path: Path):
    from PIL import Image

    with Image.open(path) as image:
        mode, (width, height) = image.mode, image.size
    if mode not in ("L", "RGB"):
        raise InputError(path, f"JPEG mode {mode} (use gray or RGB)")
    return (height, width), 1 if mode == "L" else 3, "uint8"


def _exr_header(path: Path):
    import OpenEXR

    try:
        with OpenEXR.File(str(path), header_only=True) as exr:
            header = exr.header()
    except Exception as error:
        raise InputError(path, f"not a readable EXR file ({error})") from None
    if "channels" not in header or "dataWindow" not in header:
        # OpenEXR's header_only read comes back empty in some processes (seen under pytest's
        # warning filters): read the channels instead
        channels = read_exr(path)
        names = set(channels)
        shape = next(iter(channels.values())).shape if channels else (0, 0)
        header = {"channels": [], "dataWindow": ((0, 0), (shape[1] - 1, shape[0] - 1))}
    else:
        names = {c.name for c in header["channels"]}
    if not ({"R", "G", "B"} <= names or "Y" in names):
        raise InputError(path, f"EXR has no R, G, B or Y channels (has {sorted(names)})")
    (x0, y0), (x1, y1) = header["dataWindow"]
    return (int(y1 - y0 + 1), int(x1 - x0 + 1)), 3 if {"R", "G", "B"} <= names else 1, "float"


def _to_rgb(image: np.ndarray) -> np.ndarray:
    if image.shape[2] == 1:
        image = np.repeat(image, 3, axis=2)
    return np.ascontiguousarray(image[..., :3], dtype=np.float32)


def _is_number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def direction_from_angles(theta_deg, phi_deg) -> np.ndarray:
    """Unit vector(s) from the sample toward a light/camera: (sin t cos p, sin t sin p, cos t)."""
    t, p = np.radians(np.asarray(theta_deg, np.float64)), np.radians(np.asarray(phi_deg, np.float64))
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)


def _check_image(path: Path, size: tuple[int, int] | None, check_pixels: bool,
                 headers_only: bool = False) -> tuple[list[str], tuple | None]:
    """(problems of one image file (empty when fine), its H x W or None when unreadable)."""
    result = _check_image_problems(path, size, check_pixels, headers_only)
    return result if isinstance(result, tuple) else (result, None)


def _check_image_problems(path: Path, size: tuple[int, int] | None, check_pixels: bool, headers_only: bool):
    if not path.exists():
        return [f"{path}: missing image"]
    if not path.is_file():
        return [f"{path}: not a file"]
    suffix = path.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        return [f"{path}: unsupported image type {suffix or '(none)'!r} ({_SUPPORTED})"]
    problems = []
    try:
        if headers_only:
            shape, _, _ = image_header(path)
            image = np.empty(shape + (0,), np.float32)  # its shape only
        elif suffix == ".exr":
            channels = read_exr(path)
            if not (all(c in channels for c in "RGB") or "Y" in channels):
                return [f"{path}: EXR has no R, G, B or Y channels (has {sorted(channels)})"]
            names = ["R", "G", "B"] if all(c in channels for c in "RGB") else ["Y"]
            image = np.stack([channels[n] for n in names], axis=-1)
            if check_pixels:
                bad = ~np.isfinite(image)
                if bad.any():
                    kinds = ", ".join(k for k, m in (("NaN", np.isnan(image)), ("Inf", np.isinf(image))) if m.any())
                    problems.append(f"{path}: {int(bad.sum())} non-finite values ({kinds})")
        else:
            image_header(path)  # type, bit depth and channel layout, as the header says
            image = read_image(path, srgb=False)  # 8/16-bit PNG or TIFF, JPEG (raises InputError for other types)
            if image.shape[2] not in (1, 3, 4):
                return [f"{path}: {image.shape[2]} channels (use gray, RGB or RGBA)"]
    except InputError as error:
        return [str(error)]
    except Exception as error:  # decoders raise many types for corrupt files
        return [f"{path}: not a readable image ({type(error).__name__}: {error})"]
    if size is not None and tuple(image.shape[:2]) != tuple(size):
        problems.append(f"{path}: size {image.shape[0]}x{image.shape[1]} differs from capture.json's size "
                        f"{size[0]}x{size[1]} (H x W)")
    return problems, tuple(image.shape[:2])


def load_capture(capture_dir: str | os.PathLike, *, check_pixels: bool = True, headers_only: bool = False,
                 workers: int = 4) -> Capture:
    """Load and validate a capture directory; raise `CaptureError` listing every problem.

    Checked: capture.json (present, JSON, format "jaxrender-capture", version 1), every field and
    its type (`size`, `response`, `exposures_s`, `view`, `white`, `lights`), light and view
    directions strictly above the horizon (theta in [0, 90)), one image per exposure for the white
    board and for every light, and every image: present, readable (decoded in full when
    `check_pixels` for EXR; PNG, TIFF and JPEG are always decoded), 8/16-bit PNG or TIFF, JPEG or EXR,
    of the manifest's size, and (EXR) free of NaN/Inf. With `headers_only` no pixel is decoded:
    type, bit depth, channels and size come from each header (`image_header`), and the reader of
    the pixels checks the rest (`Capture.read_checked`).
    """
    root = Path(capture_dir)
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
    if not isinstance(manifest, dict):
        raise CaptureError([f"{manifest_path}: must be a JSON object"])

    problems: list[str] = []

    def bad(field: str, problem: str) -> None:
        problems.append(f"{manifest_path}: {field}: {problem}")

    if manifest.get("format") != CAPTURE_FORMAT:
        bad("format", f"{manifest.get('format')!r} is not {CAPTURE_FORMAT!r}")
    if manifest.get("version") != CAPTURE_VERSION:
        bad("version", f"unknown version {manifest.get('version')!r} (this reader knows {CAPTURE_VERSION})")

    size = manifest.get("size")
    if not (isinstance(size, list) and len(size) == 2 and all(isinstance(s, int) and not isinstance(s, bool)
                                                               and s > 0 for s in size)):
        bad("size", "missing or not [H, W] with positive integers" if size is None
            else f"{size!r} is not [H, W] with positive integers")
        size = None
    else:
        size = (int(size[0]), int(size[1]))

    response = manifest.get("response")
    if response not in ("linear", "srgb"):
        bad("response", "missing" if response is None else f"{response!r} is not 'linear' or 'srgb'")

    exposures = manifest.get("exposures_s")
    n_exp = None
    if not (isinstance(exposures, list) and exposures and all(_is_number(e) and e > 0 for e in exposures)):
        bad("exposures_s", "missing" if exposures is None else "must be a non-empty list of positive numbers (seconds)")
        exposures = None
    else:
        n_exp = len(exposures)
        if len(set(exposures)) != n_exp:
            bad("exposures_s", "exposure times must be distinct")

    def check_angles(field: str, entry) -> tuple[float, float] | None:
        if not isinstance(entry, dict):
            bad(field, "missing" if entry is None else "must be an object with theta_deg and phi_deg")
            return None
        theta, phi = entry.get("theta_deg"), entry.get("phi_deg")
        ok = True
        if not _is_number(theta):
            bad(f"{field}.theta_deg", "missing" if theta is None else f"{theta!r} is not a finite number")
            ok = False
        elif theta >= 90:
            bad(f"{field}.theta_deg", f"{theta} is at or below the horizon (must be < 90)")
            ok = False
        elif theta < 0:
            bad(f"{field}.theta_deg", f"{theta} is negative (must be in [0, 90))")
            ok = False
        if not _is_number(phi):
            bad(f"{field}.phi_deg", "missing" if phi is None else f"{phi!r} is not a finite number")
            ok = False
        return (float(theta), float(phi)) if ok else None

    def check_images(field: str, images) -> list[Path] | None:
        if not (isinstance(images, list) and all(isinstance(p, str) and p for p in images)):
            bad(field, "missing" if images is None else "must be a list of image paths (strings)")
            return None
        if n_exp is not None and len(images) != n_exp:
            bad(field, f"{len(images)} images for {n_exp} exposures in exposures_s")
        return [root / p for p in images]

    view = check_angles("view", manifest.get("view"))

    white = manifest.get("white")
    white_refl, white_images = None, None
    if not isinstance(white, dict):
        bad("white", "missing" if white is None else "must be an object with reflectance and images")
    else:
        r = white.get("reflectance")
        if _is_number(r) and r > 0:
            white_refl = np.full(3, float(r))
        elif isinstance(r, list) and len(r) == 3 and all(_is_number(x) and x > 0 for x in r):
            white_refl = np.asarray(r, float)
        else:
            bad("white.reflectance", "missing" if r is None else f"{r!r} is not a positive number or RGB triple")
        white_images = check_images("white.images", white.get("images"))

    lights = manifest.get("lights")
    light_angles, light_images = [], []
    if not (isinstance(lights, list) and lights):
        bad("lights", "missing" if lights is None else "must be a non-empty list of lights")
        lights = []
    for i, light in enumerate(lights):
        field = f"lights[{i}]"
        if not isinstance(light, dict):
            bad(field, "must be an object with theta_deg, phi_deg and images")
            continue
        light_angles.append(check_angles(field, light))
        light_images.append(check_images(f"{field}.images", light.get("images")))

    # Every image, decoded once (threads: the decoders release the GIL).
    paths = list(white_images or []) + [p for images in light_images if images for p in images]
    unique = list(dict.fromkeys(paths))
    with concurrent.futures.ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        results = list(pool.map(lambda p: _check_image(p, size, check_pixels, headers_only), unique))
    image_problems = [line for problems_, _ in results for line in problems_]
    if size is None:  # no usable size in the manifest: the images must at least agree with each other
        shapes = [(path, shape) for path, (_, shape) in zip(unique, results, strict=True) if shape is not None]
        if shapes:
            first_path, first = shapes[0]
            image_problems += [f"{path}: size {shape[0]}x{shape[1]} differs from {first_path}'s {first[0]}x{first[1]}"
                               for path, shape in shapes[1:] if shape != first]
    if len(image_problems) > MAX_IMAGE_PROBLEMS:
        extra = len(image_problems) - MAX_IMAGE_PROBLEMS
        image_problems = image_problems[:MAX_IMAGE_PROBLEMS] + [f"{root}: ... and {extra} more image problems"]
    problems += image_problems
    if problems:
        raise CaptureError(problems)

    angles = np.asarray(light_angles, float)
    return Capture(
        root=root.resolve(), size=size, response=response, exposures_s=tuple(float(e) for e in exposures),
        view_angles=view, view_dir=direction_from_angles(*view), white_reflectance=white_refl,
        white_images=tuple(white_images), light_angles=angles,
        light_dirs=direction_from_angles(*np.asarray(angles, np.float64).reshape(-1, 2).T),
        light_images=tuple(tuple(images) for images in light_images), manifest=manifest)

"""Image headers without decoding pixels: size, channels and pixel type of PNG, TIFF, JPEG and EXR
files (how a capture of thousands of images is checked before any pixel is read)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ..errors import InputError
from ._images import read_exr

__all__ = ["ImageHeader", "image_header", "IMAGE_SUFFIXES", "SUPPORTED_IMAGES"]

IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg", ".exr")
SUPPORTED_IMAGES = "use 8/16-bit PNG or TIFF, JPEG, or EXR"
_PNG_CHANNELS = {0: 1, 2: 3, 6: 4}  # colour type -> channels (gray, RGB, RGBA); palette and gray+alpha refused


class ImageHeader(NamedTuple):
    size: tuple[int, int]  # (H, W)
    channels: int
    pixel_type: str  # "uint8", "uint16" (PNG, TIFF, JPEG) or "float" (EXR)


def image_header(path: str | os.PathLike) -> ImageHeader:
    """The header of an image. Raises `InputError` naming the file for an unsupported type, bit
    depth or channel layout, or an unreadable header."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in IMAGE_SUFFIXES:
        raise InputError(path, f"unsupported image type {suffix or '(none)'!r} ({SUPPORTED_IMAGES})")
    readers = {".png": _png_header, ".tif": _tiff_header, ".tiff": _tiff_header, ".jpg": _jpeg_header,
               ".jpeg": _jpeg_header, ".exr": _exr_header}
    try:
        return readers[suffix](path)
    except InputError:
        raise
    except Exception as error:  # decoders raise many types for corrupt headers
        raise InputError(path, f"not a readable image ({type(error).__name__}: {error})") from None


def _png_header(path: Path) -> ImageHeader:
    with open(path, "rb") as f:
        head = f.read(33)
    if len(head) < 33 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        raise InputError(path, "not a readable image (no PNG header)")
    width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    depth, colour = head[24], head[25]
    if depth not in (8, 16):
        raise InputError(path, f"{depth}-bit PNG ({SUPPORTED_IMAGES})")
    if colour not in _PNG_CHANNELS:
        raise InputError(path, f"PNG colour type {colour} (use gray, RGB or RGBA)")
    return ImageHeader((height, width), _PNG_CHANNELS[colour], f"uint{depth}")


def _tiff_header(path: Path) -> ImageHeader:
    import tifffile

    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        shape, dtype = tuple(page.shape), np.dtype(page.dtype)
        samples = int(page.samplesperpixel)
    if dtype not in (np.uint8, np.uint16):
        raise InputError(path, f"TIFF pixel type {dtype} ({SUPPORTED_IMAGES}; float images as EXR)")
    if len(shape) not in (2, 3) or samples not in (1, 3, 4):
        raise InputError(path, f"TIFF of shape {shape} (use gray, RGB or RGBA)")
    if len(shape) == 3 and shape[0] == samples and shape[2] != samples:
        raise InputError(path, "planar (separate-plane) TIFF (use interleaved gray, RGB or RGBA)")
    return ImageHeader((int(shape[0]), int(shape[1])), samples, str(dtype))


def _jpeg_header(path: Path) -> ImageHeader:
    from PIL import Image

    with Image.open(path) as image:
        mode, (width, height) = image.mode, image.size
    if mode not in ("L", "RGB"):
        raise InputError(path, f"JPEG mode {mode} (use gray or RGB)")
    return ImageHeader((height, width), 1 if mode == "L" else 3, "uint8")


def _exr_header(path: Path) -> ImageHeader:
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
    return ImageHeader((int(y1 - y0 + 1), int(x1 - x0 + 1)), 3 if {"R", "G", "B"} <= names else 1, "float")

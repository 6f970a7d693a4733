"""EXR (OpenEXR) and PNG (scikit-image) files. numpy in, numpy out: this is the I/O edge."""

from __future__ import annotations

import errno
import os
import warnings
from pathlib import Path

import numpy as np

from ..errors import InputError
from ._atomic import atomic_path
from ._color import linear_to_srgb, srgb_to_linear, tonemap
from ._outputs import check_finite

_EXR_RGB = ("R", "G", "B")


def read_exr(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """All channels of an EXR file as float32 `H W` arrays, keyed by channel name."""
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            return {name: np.asarray(ch.pixels, dtype=np.float32) for name, ch in exr.channels().items()}
    except Exception as error:  # OpenEXR raises bare RuntimeErrors for corrupt files
        raise InputError(path, f"not a readable EXR file ({error})") from None


def write_exr(path: str | os.PathLike, image: np.ndarray | dict[str, np.ndarray]) -> Path:
    """Write float32 channels, atomically. `image` is `H W`, `H W 3` (R, G, B),
    `H W C` (channels C0..), or a dict name -> `H W` array."""
    import OpenEXR

    if isinstance(image, dict):
        channels = {name: np.ascontiguousarray(np.asarray(v, dtype=np.float32)) for name, v in image.items()}
    else:
        array = np.asarray(image, dtype=np.float32)
        if array.ndim == 2:
            channels = {"Y": array}
        elif array.ndim == 3 and array.shape[2] == 3:
            channels = {c: array[..., i] for i, c in enumerate(_EXR_RGB)}
        elif array.ndim == 3 and array.shape[2] == 4:
            channels = {c: array[..., i] for i, c in enumerate(("R", "G", "B", "A"))}
        elif array.ndim == 3:
            channels = {f"C{i}": array[..., i] for i in range(array.shape[2])}
        else:
            raise ValueError(f"cannot write an array of shape {array.shape} as EXR")
        channels = {k: np.ascontiguousarray(v) for k, v in channels.items()}
    shapes = {v.shape for v in channels.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"EXR channels must share one 2-D shape, got {shapes}")
    check_finite(np.stack(list(channels.values())), path)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_path(path) as tmp:
        try:
            with OpenEXR.File(header, channels) as exr:
                exr.write(str(tmp))
        except RuntimeError as error:   # OpenEXR reports a failed write (a full disk, say) as a bare RuntimeError
            mapped = _os_error(error, path)
            if mapped is error:
                raise
            raise mapped from error
    return Path(path)


_WRITE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM, errno.EIO, errno.EFBIG)


def _os_error(error: Exception, path) -> Exception:
    """The OSError a library's message describes (by the C library's text of its errno), else `error`."""
    text = str(error)
    for number in _WRITE_ERRNOS:
        if os.strerror(number) in text:
            return OSError(number, os.strerror(number), os.fspath(path))
    return error


def read_image(path: str | os.PathLike, *, srgb: bool = True) -> np.ndarray:
    """A PNG, TIFF, JPEG or EXR image as linear float32 `H W C` (C = 1, 3 or 4).

    PNG, TIFF and JPEG values (8 or 16 bits) are scaled by the maximum of their integer type and, with `srgb`,
    decoded from sRGB (alpha stays linear). EXR files are linear: R, G, B (and A) when present,
    else Y, else every channel in name order.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "no such file")
    suffix = path.suffix.lower()
    if suffix == ".exr":
        channels = read_exr(path)
        if all(c in channels for c in _EXR_RGB):
            names = list(_EXR_RGB) + (["A"] if "A" in channels else [])
        elif "Y" in channels:
            names = ["Y"]
        else:
            names = sorted(channels)
        return np.stack([channels[n] for n in names], axis=-1)
    if suffix not in (".png", ".jpg", ".jpeg", ".tif", ".tiff"):
        raise InputError(path, f"unsupported image type {suffix!r} (use PNG, TIFF, JPEG or EXR)")
    try:
        raw = _decode_png(path) if suffix == ".png" else _decode_other(path)
    except Exception as error:
        raise InputError(path, f"not a readable image ({type(error).__name__}: {error})") from None
    if raw.dtype == np.uint8:
        image = raw.astype(np.float32) / 255.0
    elif raw.dtype == np.uint16:
        image = raw.astype(np.float32) / 65535.0
    elif raw.dtype == bool:
        image = raw.astype(np.float32)
    else:
        raise InputError(path, f"unsupported pixel type {raw.dtype}")
    if image.ndim == 2:
        image = image[..., None]
    if srgb:
        color = min(image.shape[2], 3)
        image = image.copy()
        image[..., :color] = np.asarray(srgb_to_linear(image[..., :color]))
    return image


def _decode_png(path: Path) -> np.ndarray:
    """PNG pixels in their integer type. Pillow (behind scikit-image) truncates 16-bit RGB PNGs
    to 8 bits, so libpng through imagecodecs is used when it is installed."""
    try:
        import imagecodecs
    except ImportError:
        return _decode_other(path)
    return imagecodecs.png_decode(path.read_bytes())


def _decode_other(path: Path) -> np.ndarray:
    import skimage.io

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return skimage.io.imread(str(path))


def write_png(path: str | os.PathLike, image: np.ndarray, *, srgb: bool = True, bits: int = 8) -> Path:
    """Write display values in [0, 1] (`H W`, `H W 1`, `H W 3`, `H W 4`) as an 8- or 16-bit PNG.

    With `srgb`, linear values are sRGB-encoded first (pass `srgb=False` for values that are
    already display-encoded, e.g. the output of `tonemap`, or for data such as masks).
    """
    import skimage.io

    array = np.asarray(image, dtype=np.float32)
    check_finite(array, path)   # a NaN would write as black: refused, not hidden
    if array.ndim == 3 and array.shape[2] == 1:
        array = array[..., 0]
    if srgb:
        color = array if array.ndim == 2 else array[..., :3]
        encoded = np.asarray(linear_to_srgb(color))
        array = encoded if array.ndim == 2 else np.concatenate([encoded, array[..., 3:]], axis=-1)
    array = np.clip(array, 0.0, 1.0)
    if bits == 8:
        out = np.round(array * 255.0).astype(np.uint8)
    elif bits == 16:
        out = np.round(array * 65535.0).astype(np.uint16)
    else:
        raise ValueError("PNG bits must be 8 or 16")
    with atomic_path(Path(path).with_suffix(".png") if Path(path).suffix == "" else path) as tmp:
        try:  # libpng through imagecodecs: Pillow cannot write (or read) 16-bit RGB PNG
            import imagecodecs

            tmp.write_bytes(imagecodecs.png_encode(out))
        except ImportError:
            skimage.io.imsave(str(tmp), out, check_contrast=False)
    return Path(path)


def write_image(path: str | os.PathLike, image: np.ndarray, *, exposure: float = 1.0) -> Path:
    """Write linear radiance: EXR as is, PNG tone-mapped (`tonemap`, ACES) for viewing."""
    path = Path(path)
    if path.suffix.lower() == ".exr":
        return write_exr(path, image)
    if path.suffix.lower() == ".png":
        return write_png(path, np.asarray(tonemap(np.asarray(image), exposure=exposure)), srgb=False)
    raise InputError(path, "output must end in .exr or .png")

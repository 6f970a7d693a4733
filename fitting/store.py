"""The observation store: a capture's merged observations on disk, chunked and compressed (zarr).

`fitting.ingest.ingest_capture` writes it in one streaming pass over the images; `fitting.tiles`
fits it tile by tile. Texels are flattened in row-major order (t = row * W + column), so a tile of
the fit (`--chunk` texels) is one contiguous range of rows of every array:

```
STORE_DIR/zarr.json     zarr v3 group
STORE_DIR/ratio/        T x L x 3   float16 (default) or float32: observed reflectance, 0 where invalid
STORE_DIR/flags/        T x L       uint8: bit 0 valid, bit 1 a channel saturated, bit 2 a channel dark
STORE_DIR/counts/       T x 3       int32: n_valid, n_saturated, n_dark (written after the last light)
STORE_DIR/mask/         T           uint8: 1 for the texels to fit (the capture's mask; all 1 without one)
STORE_DIR/.ingest/      progress of an unfinished ingest (one marker per finished light block)
STORE_DIR/store.json    written last: format, version, size, lights, view, dtype, chunking, fingerprint
```

Chunks are (`tile` texels) x (`light_block` lights): every chunk is written exactly once by the
ingest (one light block of full frames at a time), and a tile of the fit reads L / light_block
chunks of each array. A directory without `store.json` is an unfinished store: readers refuse it
and a rerun of the ingest resumes it.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from jaxrender.io import InputError, atomic_path

from .hdr import ObservationCounts, Observations

__all__ = ["STORE_FORMAT", "STORE_VERSION", "STORE_DTYPES", "DEFAULT_STORE_DTYPE", "ObservationStore",
           "open_store", "is_store", "VALID", "SATURATED", "DARK"]

STORE_FORMAT = "jaxrender-observations"
STORE_VERSION = 1
STORE_DTYPES = ("float16", "float32")
DEFAULT_STORE_DTYPE = "float16"  # benchmarks/capture_scale.py: fit cost of float16 vs float32 (RESULTS.md)
VALID, SATURATED, DARK = 1, 2, 4
MARKER = "store.json"


def is_store(path: str | os.PathLike) -> bool:
    """Whether `path` is an observation store directory (complete or not), not a capture."""
    path = Path(path)
    return path.is_dir() and ((path / MARKER).is_file() or (path / ".ingest").is_dir()) \
        and not (path / "capture.json").is_file()


def write_marker(store_dir: Path, info: dict) -> None:
    with atomic_path(store_dir / MARKER) as tmp:
        tmp.write_text(json.dumps(info, indent=1) + "\n")


class ObservationStore:
    """A complete observation store, opened for reading (see the module docstring).

    `read(start, count)` gives the fit's inputs of texels `start .. start + count - 1` as float32
    (`ratio` `count L 3`, `weight` `count L`, 1 valid / 0 not), exactly what the in-memory
    `Observations` holds for those texels when the store is float32.
    """

    def __init__(self, path: Path, info: dict):
        import zarr

        self.path, self.info = path, info
        group = zarr.open_group(str(path), mode="r")
        self._ratio, self._flags, self._counts = group["ratio"], group["flags"], group["counts"]
        self._mask = group["mask"] if "mask" in group else None  # stores written before masks existed: all in
        self.size = (int(info["size"][0]), int(info["size"][1]))
        self.light_dirs = np.asarray(info["light_dirs"], np.float64)
        self.view_dir = np.asarray(info["view_dir"], np.float64)

    @property
    def n_texels(self) -> int:
        return self.size[0] * self.size[1]

    @property
    def n_lights(self) -> int:
        return int(self.light_dirs.shape[0])

    @property
    def fingerprint(self) -> str:
        return str(self.info["fingerprint"])

    @property
    def dtype(self) -> str:
        return str(self.info["dtype"])

    def read(self, start: int, count: int) -> tuple[np.ndarray, np.ndarray]:
        ratio = np.asarray(self._ratio[start:start + count], np.float32)
        weight = (np.asarray(self._flags[start:start + count]) & VALID).astype(np.float32)
        return ratio, weight

    def flags(self, start: int, count: int) -> np.ndarray:
        return np.asarray(self._flags[start:start + count])

    def mask(self) -> np.ndarray:
        """`H W` bool: the texels to fit."""
        if self._mask is None:
            return np.ones(self.size, bool)
        return np.asarray(self._mask[:]).reshape(self.size) > 0

    def counts(self) -> ObservationCounts:
        """`H W` int32 maps n_valid, n_saturated, n_dark."""
        counts = np.asarray(self._counts[:]).reshape(self.size + (3,))
        return ObservationCounts(counts[..., 0], counts[..., 1], counts[..., 2])

    def observations(self):
        """The whole store as in-memory `fitting.hdr.Observations` (small stores and tests only)."""
        import jax.numpy as jnp

        ratio, weight = self.read(0, self.n_texels)
        h, w = self.size
        counts = self.counts()
        return Observations(ratio=jnp.asarray(ratio.reshape(h, w, self.n_lights, 3)),
                            weight=jnp.asarray(weight.reshape(h, w, self.n_lights)),
                            light_dirs=jnp.asarray(self.light_dirs.astype(np.float32)),
                            view_dir=jnp.asarray(self.view_dir.astype(np.float32)),
                            n_valid=jnp.asarray(counts.n_valid), n_saturated=jnp.asarray(counts.n_saturated),
                            n_dark=jnp.asarray(counts.n_dark), mask=jnp.asarray(self.mask()))


def open_store(store_dir: str | os.PathLike) -> ObservationStore:
    """Open a complete store; `InputError` naming the file when it is missing, unfinished or foreign."""
    store_dir = Path(store_dir)
    marker = store_dir / MARKER
    if not store_dir.is_dir():
        raise InputError(store_dir, "no such observation store")
    if not marker.is_file():
        raise InputError(marker, "missing: the observation store is unfinished (rerun `fitting ingest` to resume)")
    try:
        info = json.loads(marker.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise InputError(marker, f"not valid JSON ({error})") from None
    if not isinstance(info, dict) or info.get("format") != STORE_FORMAT:
        raise InputError(marker, f"not an observation store (format must be {STORE_FORMAT!r})")
    if info.get("version") != STORE_VERSION:
        raise InputError(marker, f"unsupported store version {info.get('version')!r} "
                                 f"(this reader knows {STORE_VERSION})")
    try:
        return ObservationStore(store_dir, info)
    except (KeyError, ValueError, FileNotFoundError) as error:
        raise InputError(store_dir, f"damaged observation store ({type(error).__name__}: {error})") from None

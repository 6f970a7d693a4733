"""Resumable work: finished units saved atomically under a directory that names the inputs and
settings they came from (`fingerprint`); a rerun with the same fingerprint loads them, another
one starts afresh. Used by the fit's chunks (`BTF_DIR/.partial/`, local, tiled and Dask paths).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
from pathlib import Path

import numpy as np

from jaxrender.io import atomic_path

from .lm import TexelFit

__all__ = ["fingerprint", "Checkpoint", "TEXEL_FIT_FIELDS"]

TEXEL_FIT_FIELDS = tuple(f.name for f in dataclasses.fields(TexelFit))
CONFIG = "config.json"


def fingerprint(settings: dict, *parts: str | bytes | np.ndarray) -> str:
    """SHA-256 of `settings` (as sorted JSON) and of each part (text, bytes, or an array's shape and bytes)."""
    h = hashlib.sha256(json.dumps(settings, sort_keys=True).encode())
    for part in parts:
        if isinstance(part, np.ndarray):
            h.update(str(part.shape).encode())
            part = np.ascontiguousarray(part).tobytes()
        h.update(part.encode() if isinstance(part, str) else part)
    return h.hexdigest()


class Checkpoint:
    """Chunks of a fit as `.npz` files (one `TexelFit` of flat leaves each) in `directory`.

    `prepare(fingerprint)` (the driver, once) empties a directory written for another fingerprint;
    `save` and `load` (the driver or a worker process) need nothing else.
    """

    def __init__(self, directory: str | Path):
        self.directory = Path(directory)

    def prepare(self, fingerprint_: str) -> "Checkpoint":
        config = self.directory / CONFIG
        if self.directory.is_dir():
            try:
                same = json.loads(config.read_text()).get("fingerprint") == fingerprint_
            except (OSError, ValueError):
                same = False
            if not same:  # other inputs or other settings: start again
                shutil.rmtree(self.directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        if not config.is_file():
            with atomic_path(config) as tmp:
                tmp.write_text(json.dumps({"fingerprint": fingerprint_}))
        return self

    def path(self, index: int) -> Path:
        return self.directory / f"chunk_{index:06d}.npz"

    def save(self, index: int, fit: TexelFit) -> None:
        """Chunk `index` written atomically."""
        with atomic_path(self.path(index)) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, **{name: np.asarray(getattr(fit, name)) for name in TEXEL_FIT_FIELDS})

    def load(self, index: int, count: int) -> TexelFit | None:
        """Chunk `index` when it is there, readable and of `count` texels; else None (fit it again)."""
        path = self.path(index)
        if not path.is_file():
            return None
        try:
            with np.load(path) as data:
                fields = {name: data[name] for name in TEXEL_FIT_FIELDS}
        except (OSError, ValueError, KeyError, EOFError):
            return None  # unreadable: fit it again
        if any(v.shape[:1] != (count,) for v in fields.values()):
            return None
        return TexelFit(**fields)

    def remove(self) -> None:
        shutil.rmtree(self.directory, ignore_errors=True)

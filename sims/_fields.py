"""Height-field files and long runs for the automata: load/save (.npy, .exr), a shaded preview,
and chunked simulation with a progress bar (the CLI commands are thin layers over these)."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from jaxrender.io import FLOAT32_MAX, InputError, atomic_path, check_finite, read_exr, write_exr

FIELD_SUFFIXES = (".npy", ".exr")


def load_field(path: str | os.PathLike) -> np.ndarray:
    """A height field from .npy (2-D float array) or .exr (channel `height`, `Y`, or the only
    one), as float32 `H W`; bad files raise `InputError` naming the file and the problem."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in FIELD_SUFFIXES:
        raise InputError(path, f"a height field must be .npy or .exr, not {suffix or 'no suffix'}")
    if not path.is_file():
        raise InputError(path, "no such file")
    try:
        if suffix == ".npy":
            field = np.load(path, allow_pickle=False)
        else:
            channels = read_exr(path)
            name = next((n for n in ("height", "Y") if n in channels), None)
            if name is None and len(channels) == 1:
                name = next(iter(channels))
            if name is None:
                raise InputError(path, f"EXR has no 'height' or 'Y' channel (channels: {sorted(channels)})")
            field = channels[name]
    except InputError:
        raise
    except Exception as error:  # numpy/OpenEXR parse errors: report one line
        raise InputError(path, f"cannot read height field ({type(error).__name__}: {error})".splitlines()[0]) from None
    field = np.asarray(field)
    if field.ndim != 2:
        raise InputError(path, f"height field must be 2-D (H, W), got shape {field.shape}")
    if not np.issubdtype(field.dtype, np.number) or np.issubdtype(field.dtype, np.complexfloating):
        raise InputError(path, f"height field must be real numbers, got dtype {field.dtype}")
    if min(field.shape) < 3:
        raise InputError(path, f"height field must be at least 3x3, got {field.shape}")
    if not np.all(np.isfinite(field)):
        raise InputError(path, "height field contains NaN or infinity")
    if np.any(np.abs(field) > FLOAT32_MAX):
        raise InputError(path, f"height field has values beyond float32's range (|x| <= {FLOAT32_MAX:.4g}), in which "
                               "the automata compute")
    return field.astype(np.float32)


def save_field(path: str | os.PathLike, field) -> Path:
    """Write `H W` heights atomically: .npy (float32) or .exr (channel `height`)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in FIELD_SUFFIXES:
        raise InputError(path, f"output must end in .npy or .exr, not {suffix or 'no suffix'}")
    field = np.asarray(field, dtype=np.float32)
    check_finite(field, path)
    if suffix == ".exr":
        return write_exr(path, {"height": field})
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, field)
    return path


def preview_image(field, *, light_deg: float = 135.0) -> np.ndarray:
    """A grey `H W` image in [0, 1] for looking at a field: heights, shaded by the slope toward
    a light at `light_deg` (so ripple crests read even when heights span a wide range)."""
    h = np.asarray(field, dtype=np.float64)
    lo, hi = np.percentile(h, 1), np.percentile(h, 99)
    base = np.clip((h - lo) / max(hi - lo, 1e-12), 0, 1)
    gx = 0.5 * (np.roll(h, -1, 1) - np.roll(h, 1, 1))
    gy = 0.5 * (np.roll(h, -1, 0) - np.roll(h, 1, 0))
    a = np.deg2rad(light_deg)
    shade = np.cos(a) * gx + np.sin(a) * gy
    scale = max(np.percentile(np.abs(shade), 99), 1e-12)
    return np.clip(0.6 * base + 0.4 * (0.5 + 0.5 * np.clip(shade / scale, -1, 1)), 0, 1)


def simulate_in_chunks(simulate: Callable, field, steps: int, *, chunk: int = 100, desc: str = "steps"):
    """Run `simulate(field, steps=n)` in chunks of `chunk` steps with a tqdm bar (quiet when not a
    terminal). At most two compilations (the chunk and the remainder)."""
    from tqdm import tqdm

    with tqdm(total=steps, desc=desc, unit="step", disable=None) as bar:
        done = 0
        while done < steps:
            n = min(chunk, steps - done)
            field = simulate(field, steps=n)
            field.block_until_ready()
            done += n
            bar.update(n)
    return field

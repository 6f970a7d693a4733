"""BTF directories (design.md, "BTF output"): one multi-channel EXR per pyramid level plus
`btf.json`, written last, that marks the directory complete.

```
BTF_DIR/level_00.exr   full resolution: every lobe channel + residual, converged, n_valid, ...
BTF_DIR/level_01.exr   ceil(H/2) x ceil(W/2): every lobe channel
BTF_DIR/btf.json       {"format": "jaxrender-btf", "version": 1, "model": ..., "levels": [...], "units": ...}
```

Readers must treat a directory without `btf.json` as incomplete, and `read_btf` refuses one (naming
the writer when one holds the directory's lock) and one whose listed level files are not all there.
Writers remove `btf.json` before they touch any level and write it again only once every level is
in place; each file is itself written atomically (temporary sibling, then rename).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from ..errors import InputError
from ._atomic import atomic_path
from ._images import read_exr, write_exr, write_png
from ._lock import describe_owner, lock_owner

__all__ = ["BTF_FORMAT", "BTF_VERSION", "BTF_MODELS", "LOBE_CHANNELS", "LEVEL_CHANNELS", "LEVEL0_CHANNELS",
           "MASK_CHANNEL", "BTF_UNITS",
           "btf_level_name", "complete_level", "write_btf", "write_btf_levels", "read_btf", "write_btf_previews"]

BTF_FORMAT = "jaxrender-btf"
BTF_VERSION = 1
BTF_MODELS = ("reciprocal", "paper")

_RGB = ("R", "G", "B")
_XYZ = ("X", "Y", "Z")
LOBE0_CHANNELS: tuple[str, ...] = (
    *(f"rho_d.{c}" for c in _RGB), *(f"rho_s.{c}" for c in _RGB), *(f"normal.{a}" for a in _XYZ),
    "sigma_x", "sigma_y")
LOBE1_CHANNELS: tuple[str, ...] = (
    *(f"lobe1.rho_s.{c}" for c in _RGB), *(f"lobe1.normal.{a}" for a in _XYZ),
    "lobe1.sigma_x", "lobe1.sigma_y", "weight")
#: Channels on every level, in file order.
LOBE_CHANNELS: tuple[str, ...] = LOBE0_CHANNELS + LOBE1_CHANNELS
#: Per-texel fit statistics, on level 0 only.
STAT_CHANNELS: tuple[str, ...] = ("residual", "converged", "n_valid", "n_saturated", "n_dark")
#: 1 where a texel was fitted (a coarse texel: any of its children), 0 outside the capture's mask;
#: every level (an extension of design.md's format; BTFs written before it read as all 1).
MASK_CHANNEL = "mask"
#: Channels of every level.
LEVEL_CHANNELS: tuple[str, ...] = LOBE_CHANNELS + (MASK_CHANNEL,)
#: Channels of level 0.
LEVEL0_CHANNELS: tuple[str, ...] = LEVEL_CHANNELS + STAT_CHANNELS

BTF_UNITS = {
    "rho_d": "reflectance (unitless, linear RGB)",
    "rho_s": "reflectance scale of the slope distribution (unitless, linear RGB)",
    "normal": "unit vector in the sample frame (x = columns, y = rows toward the top, z = toward the camera)",
    "sigma_x": "slope (tan) along the tangent T", "sigma_y": "slope (tan) along the bitangent B = N x T",
    "weight": "weight of lobe 1 (lobe 0 has 1 - weight)",
    "residual": "RMS over valid observations (reflectance units)",
    "converged": "1 converged / 0 not", "n_valid": "count of lights", "n_saturated": "count of lights",
    "n_dark": "count of lights",
}
_RESERVED = ("format", "version", "model", "levels", "units", "channels")


def btf_level_name(index: int) -> str:
    return f"level_{index:02d}.exr"


def complete_level(channels: dict, *, level0: bool) -> dict[str, np.ndarray]:
    """Check a level's channels and fill the second lobe of a one-lobe level.

    Lobe-0 channels are required (and on level 0 the statistics); missing `lobe1.*` channels are
    copied from lobe 0 with `weight` = 0, as design.md asks ("0 where a texel has one lobe").
    Raises ValueError for missing channels, unknown channels or shapes that differ.
    """
    arrays = {name: np.asarray(v, dtype=np.float32) for name, v in channels.items()}
    required = LOBE0_CHANNELS + (STAT_CHANNELS if level0 else ())
    missing = [name for name in required if name not in arrays]
    if missing:
        raise ValueError(f"BTF level is missing channels {missing}")
    allowed = set(LEVEL0_CHANNELS if level0 else LEVEL_CHANNELS)
    unknown = sorted(set(arrays) - allowed)
    if unknown:
        raise ValueError(f"unknown BTF channels {unknown} (design.md names only)")
    shapes = {v.shape for v in arrays.values()}
    if len(shapes) != 1 or len(next(iter(shapes))) != 2:
        raise ValueError(f"BTF channels must share one 2-D shape, got {sorted(shapes)}")
    lobe1 = [name for name in LOBE1_CHANNELS if name != "weight"]
    present = [name for name in lobe1 if name in arrays]
    if present and len(present) != len(lobe1):
        raise ValueError(f"BTF level has only some lobe-1 channels: {present}")
    if not present:
        for name in lobe1:
            arrays[name] = arrays[name.removeprefix("lobe1.")]
        if "weight" in arrays and np.any(arrays["weight"] != 0):
            raise ValueError("a nonzero weight needs lobe-1 channels")
        arrays.setdefault("weight", np.zeros(next(iter(shapes)), np.float32))
    elif "weight" not in arrays:
        raise ValueError("a level with lobe-1 channels needs `weight`")
    arrays.setdefault(MASK_CHANNEL, np.ones(next(iter(shapes)), np.float32))
    order = LEVEL0_CHANNELS if level0 else LEVEL_CHANNELS
    return {name: np.ascontiguousarray(arrays[name]) for name in order}


def _check_sizes(sizes: list[tuple[int, int]], *, start: int = 0) -> None:
    for i in range(1, len(sizes)):
        expected = (math.ceil(sizes[i - 1][0] / 2), math.ceil(sizes[i - 1][1] / 2))
        if sizes[i] != expected:
            raise ValueError(f"BTF level {start + i} has size {sizes[i]}, expected ceil-half {expected}")


def _manifest(model: str, sizes: list[tuple[int, int]], meta: dict | None) -> dict:
    if model not in BTF_MODELS:
        raise ValueError(f"unknown model {model!r}: use one of {BTF_MODELS}")
    manifest = {
        "format": BTF_FORMAT, "version": BTF_VERSION, "model": model,
        "levels": [{"file": btf_level_name(i), "size": [int(h), int(w)]} for i, (h, w) in enumerate(sizes)],
        "channels": {"all_levels": list(LEVEL_CHANNELS), "level_0": list(STAT_CHANNELS)},
        "units": BTF_UNITS,
    }
    for key, value in (meta or {}).items():
        if key in _RESERVED:
            raise ValueError(f"meta may not override {key!r}")
        manifest[key] = value
    return manifest


def _write_json(path: Path, data: dict) -> None:
    text = json.dumps(data, indent=2, default=_json_default)
    with atomic_path(path) as tmp:
        tmp.write_text(text + "\n")


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    raise TypeError(f"cannot store {type(value).__name__} in btf.json")


def _remove_stale_levels(btf_dir: Path, count: int) -> None:
    for path in btf_dir.glob("level_*.exr"):
        stem = path.stem.removeprefix("level_")
        if stem.isdigit() and int(stem) >= count:
            path.unlink()


def write_btf(btf_dir: str | os.PathLike, levels: list[dict], *, model: str,
              meta: dict | None = None) -> Path:
    """Write a complete BTF directory: `level_00.exr`, ... then `btf.json` last.

    `levels[0]` must hold the lobe-0 channels and the statistics (`residual`, `converged`,
    `n_valid`, `n_saturated`, `n_dark`); further levels the lobe channels. One-lobe levels get
    `lobe1.*` copied from lobe 0 and `weight` = 0. `meta` adds keys to btf.json (e.g. solver
    settings). An existing `btf.json` is removed first, so a crash leaves the directory incomplete,
    never inconsistent; level files beyond the new count are removed.
    """
    if not levels:
        raise ValueError("a BTF needs at least level 0")
    completed = [complete_level(level, level0=(i == 0)) for i, level in enumerate(levels)]
    sizes = [next(iter(level.values())).shape for level in completed]
    _check_sizes(sizes)
    manifest = _manifest(model, sizes, meta)
    btf_dir = Path(btf_dir)
    btf_dir.mkdir(parents=True, exist_ok=True)
    (btf_dir / "btf.json").unlink(missing_ok=True)
    for i, level in enumerate(completed):
        write_exr(btf_dir / btf_level_name(i), level)
    _remove_stale_levels(btf_dir, len(completed))
    _write_json(btf_dir / "btf.json", manifest)
    return btf_dir


def write_btf_levels(btf_dir: str | os.PathLike, levels: list[dict], *, start: int = 1,
                     meta: dict | None = None) -> Path:
    """Write or replace levels `start, start + 1, ...` of a complete BTF directory (the pyramid).

    Levels below `start` are kept; levels at or above `start + len(levels)` are removed; the
    sizes must continue the ceil-halving chain. `btf.json` is removed while the levels are written
    and rewritten last with the new level list (existing keys kept, `meta` merged in).
    """
    if start < 1:
        raise ValueError("write_btf_levels keeps level 0: start must be >= 1 (use write_btf for level 0)")
    btf_dir = Path(btf_dir)
    manifest, _ = read_btf(btf_dir, load=False)
    if start > len(manifest["levels"]):
        raise ValueError(f"cannot write level {start}: the BTF has {len(manifest['levels'])} levels")
    completed = [complete_level(level, level0=False) for level in levels]
    kept = [tuple(entry["size"]) for entry in manifest["levels"][:start]]
    sizes = kept + [next(iter(level.values())).shape for level in completed]
    _check_sizes(sizes)
    extra = {k: v for k, v in manifest.items() if k not in _RESERVED}
    extra.update(meta or {})
    new_manifest = _manifest(manifest["model"], sizes, extra)
    (btf_dir / "btf.json").unlink(missing_ok=True)
    for i, level in enumerate(completed):
        write_exr(btf_dir / btf_level_name(start + i), level)
    _remove_stale_levels(btf_dir, len(sizes))
    _write_json(btf_dir / "btf.json", new_manifest)
    return btf_dir


def read_btf(btf_dir: str | os.PathLike, *, load: bool = True) -> tuple[dict, list[dict[str, np.ndarray]]]:
    """(btf.json as a dict, one channel dict of float32 `H W` arrays per level).

    Raises InputError naming the file for an incomplete directory (no btf.json), a bad manifest,
    a missing level file, missing channels or a level whose size differs from btf.json.
    With `load=False` only the manifest is checked and the level list is empty.
    """
    btf_dir = Path(btf_dir)
    path = btf_dir / "btf.json"
    if not btf_dir.is_dir():
        raise InputError(btf_dir, "no such BTF directory")
    if not path.is_file():
        owner = lock_owner(btf_dir)
        writing = f"; {describe_owner(owner)} is writing it" if owner else ""
        raise InputError(path, f"missing: the BTF directory is incomplete (btf.json is written last){writing}")
    try:
        manifest = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise InputError(path, f"not valid JSON ({error})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != BTF_FORMAT:
        raise InputError(path, f"not a BTF manifest (format must be {BTF_FORMAT!r})")
    if manifest.get("version") != BTF_VERSION:
        raise InputError(path, f"unsupported BTF version {manifest.get('version')!r} (this reader knows {BTF_VERSION})")
    if manifest.get("model") not in BTF_MODELS:
        raise InputError(path, f"unknown model {manifest.get('model')!r} (use one of {BTF_MODELS})")
    entries = manifest.get("levels")
    if (not isinstance(entries, list) or not entries
            or not all(isinstance(e, dict) and isinstance(e.get("file"), str) and isinstance(e.get("size"), list)
                       and len(e["size"]) == 2 for e in entries)):
        raise InputError(path, "`levels` must be a non-empty list of {file, size: [H, W]}")
    absent = [entry["file"] for entry in entries if not (btf_dir / entry["file"]).is_file()]
    if absent:
        raise InputError(path, f"lists level files that are not there ({', '.join(absent)}): the BTF is incomplete")
    if not load:
        return manifest, []
    levels = []
    for i, entry in enumerate(entries):
        level_path = btf_dir / entry["file"]
        channels = read_exr(level_path)
        required = LEVEL0_CHANNELS if i == 0 else LEVEL_CHANNELS
        missing = [name for name in required if name not in channels and name != MASK_CHANNEL]
        if missing:
            raise InputError(level_path, f"missing channels {', '.join(missing)}")
        shape = channels[required[0]].shape
        if list(shape) != [int(s) for s in entry["size"]]:
            raise InputError(level_path, f"size {list(shape)} differs from btf.json's {entry['size']}")
        channels.setdefault(MASK_CHANNEL, np.ones(shape, np.float32))  # written before masks existed: all in
        levels.append({name: channels[name] for name in required})
    return manifest, levels


def _scaled(x: np.ndarray) -> np.ndarray:
    """Map a non-negative map to [0, 1] by its 99th percentile (robust to a few outliers)."""
    finite = x[np.isfinite(x)]
    top = float(np.percentile(finite, 99)) if finite.size else 1.0
    return np.clip(np.nan_to_num(x) / (top if top > 0 else 1.0), 0.0, 1.0)


def write_btf_previews(btf_dir: str | os.PathLike, level0: dict | None = None,
                       out_dir: str | os.PathLike | None = None) -> list[Path]:
    """PNG previews of every map of level 0 (read from `btf_dir` when `level0` is None) into
    `out_dir` (default `BTF_DIR/previews`). Colour maps are sRGB-encoded: `rho_d` as is, `rho_s`
    scaled by its 99th percentile; normals as 0.5 + 0.5 N; scalar maps scaled by their 99th
    percentile (`converged` as 0/1). Returns the written paths."""
    btf_dir = Path(btf_dir)
    if level0 is None:
        _, levels = read_btf(btf_dir)
        level0 = levels[0]
    out_dir = Path(out_dir) if out_dir is not None else btf_dir / "previews"
    out_dir.mkdir(parents=True, exist_ok=True)
    c = {name: np.asarray(v, dtype=np.float32) for name, v in level0.items()}
    written = []

    def rgb(prefix):
        return np.stack([c[f"{prefix}.{ch}"] for ch in _RGB], axis=-1)

    def xyz(prefix):
        return np.stack([c[f"{prefix}.{ax}"] for ax in _XYZ], axis=-1)

    for prefix in ("", "lobe1."):
        if f"{prefix}rho_s.R" not in c:
            continue
        if prefix and not np.any(c.get("weight", 0.0)):
            continue  # a one-lobe level: lobe 1 is a copy of lobe 0
        if prefix == "" and "rho_d.R" in c:
            written.append(write_png(out_dir / "rho_d.png", np.clip(rgb("rho_d"), 0, 1)))
        written.append(write_png(out_dir / f"{prefix}rho_s.png", _scaled(rgb(f"{prefix}rho_s"))))
        written.append(write_png(out_dir / f"{prefix}normal.png",
                                 np.clip(0.5 + 0.5 * xyz(f"{prefix}normal"), 0, 1), srgb=False))
        for name in ("sigma_x", "sigma_y"):
            written.append(write_png(out_dir / f"{prefix}{name}.png", _scaled(c[f"{prefix}{name}"]), srgb=False))
    for name in ("weight", *STAT_CHANNELS):
        if name in c:
            image = np.clip(c[name], 0, 1) if name in ("weight", "converged") else _scaled(c[name])
            written.append(write_png(out_dir / f"{name}.png", image, srgb=False))
    return written

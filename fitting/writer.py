"""The BTF directory a fit writes (docs/formats.md, "BTF directory"): previews, level 0, the EM
pyramid and `btf.json` last, so that a directory is complete only once every level is written.
The caller holds the directory's lock (`jaxrender.io.output_lock`)."""

from __future__ import annotations

import shutil
from pathlib import Path

import jax
import numpy as np

from jaxrender.io import complete_level, remove_temporaries, write_btf, write_btf_previews

from .engine import FitResult
from .hdr import ObservationCounts
from .lm import TexelFit, default_tolerances
from .pyramid import pyramid_channels
from .settings import FitSettings

__all__ = ["PARTIAL", "begin_output", "level0_channels", "write_fit"]

PARTIAL = ".partial"   # the checkpoint of a fit in progress, inside BTF_DIR


def begin_output(btf_dir: Path) -> None:
    """A fit starts writing `btf_dir` (its lock held): an older `btf.json` goes, so the directory is
    incomplete until this fit's last step, and so do the temporaries a killed run left."""
    (btf_dir / "btf.json").unlink(missing_ok=True)
    for directory in (btf_dir, btf_dir / "previews", btf_dir / PARTIAL):
        remove_temporaries(directory)


def level0_channels(maps: TexelFit, counts: ObservationCounts, mask: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """BTF level-0 channels (design.md names, and `mask`: 1 for fitted texels) of fitted `H W` maps
    and the observation counts."""
    c: dict[str, np.ndarray] = {}
    for i, ch in enumerate("RGB"):
        c[f"rho_d.{ch}"] = maps.rho_d[..., i]
        c[f"rho_s.{ch}"] = maps.rho_s[..., i]
    for i, ax in enumerate("XYZ"):
        c[f"normal.{ax}"] = maps.normal[..., i]
    c["sigma_x"], c["sigma_y"] = maps.sigma_x, maps.sigma_y
    c["residual"] = maps.residual
    c["converged"] = np.asarray(maps.converged).astype(np.float32)
    c["n_valid"], c["n_saturated"], c["n_dark"] = counts.n_valid, counts.n_saturated, counts.n_dark
    c["mask"] = np.ones(np.shape(maps.sigma_x), np.float32) if mask is None else mask
    return {k: np.asarray(v, np.float32) for k, v in c.items()}


def write_fit(btf_dir: Path, result: FitResult, settings: FitSettings, *, pyramid: bool, seconds: float,
              cpu_seconds: float | None = None, meta: dict | None = None) -> Path:
    """Previews of level 0, then level 0 and the EM pyramid of the fit `result` with `btf.json` last
    (it appears only once every level is written); removes `.partial/` and any temporaries."""
    maps, table, mask = result.maps, result.table, result.mask
    level0 = level0_channels(maps, result.counts, mask)
    inside = np.ones(np.shape(maps.sigma_x), bool) if mask is None else np.asarray(mask, bool)
    rtol, atol = default_tolerances(np.float32)  # the fit always sees float32 observations
    fit = {**settings.describe(), "rtol": rtol, "atol": atol, "devices": jax.local_device_count(),
           "converged_fraction": float(np.mean(maps.converged[inside])) if inside.any() else 0.0,
           "median_residual": float(np.median(maps.residual[inside])) if inside.any() else 0.0,
           "median_steps": float(np.median(maps.num_steps[inside])) if inside.any() else 0.0,
           "seconds": round(seconds, 3), "observations": result.observations}
    if cpu_seconds is not None:  # this process's CPU time (robust to a shared machine's load)
        fit["cpu_seconds"] = round(cpu_seconds, 3)
    fit["level"] = result.level   # the factor the solvers saw the observations multiplied by
    if table is not None:
        fit["materials"] = table.describe(result.level)
    info = {"fit": fit, **(meta or {})}
    write_btf_previews(btf_dir, level0)
    level0 = complete_level(level0, level0=True)
    levels = [level0]
    if pyramid:
        coarse, pyramid_meta = pyramid_channels(level0)
        levels += coarse
        info.update(pyramid_meta)
    write_btf(btf_dir, levels, model=settings.model, meta=info)
    del levels, level0
    shutil.rmtree(btf_dir / PARTIAL, ignore_errors=True)
    for directory in (btf_dir, btf_dir / "previews"):
        remove_temporaries(directory)
    return btf_dir

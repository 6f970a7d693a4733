"""K-fold cross-validation over a capture's lights: an evaluation no single split can be tuned to.

Light `i` belongs to fold `i mod K`; each fold is held out once: the other lights are fitted
(`fitting.fit_maps`), every held-out photograph is predicted (`fitting.relight`) and compared over
its valid pixels inside the mask (relative RMS, `fitting.evaluate.relative_rms`), beside a
least-squares Lambertian fit of the same lights on the same pixels (`fitting.evaluate.lambertian_fit`,
the photometric-stereo benchmarks' baseline). With ground-truth normals, each fold's fitted
normals are compared with them (mean angular error over the mask). `cross_validate` returns the
figures per fold, their mean and worst, and per-texel maps over all folds (every light predicted
once); `figure` draws them.
"""

from __future__ import annotations

import dataclasses
import os
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from matplotlib.figure import Figure
from tqdm.auto import tqdm

from jaxrender.io import atomic_path

from .evaluate import angular_error_deg, lambertian_fit, relative_rms, select_lights
from .fit import fit_maps
from .hdr import Observations
from .report import relight
from .settings import FitSettings

__all__ = ["light_folds", "cross_validate", "CrossValidation", "figure", "DEFAULT_FOLDS"]

DEFAULT_FOLDS = 6


def light_folds(n_lights: int, k: int) -> list[np.ndarray]:
    """The lights of each of `k` folds: light i in fold i mod k (interleaved in the capture's light
    order, so every fold spans the rig)."""
    if not 2 <= k <= n_lights:
        raise ValueError(f"the number of folds must be in 2..{n_lights} (the lights), got {k}")
    lights = np.arange(n_lights)
    return [lights[lights % k == f] for f in range(k)]


@dataclasses.dataclass
class CrossValidation:
    """Figures of a K-fold light cross-validation (`cross_validate`).

    `folds`: one dict per fold (`lights` held out, `heldout` and `lambertian` relative RMS, their
    `ratio`, `normals_deg` and `lambertian_normals_deg` with ground truth, `seconds` and
    `cpu_seconds` of the fold's fit); `heldout_map`, `lambertian_map`: per-texel relative RMS over
    every light (each predicted by the fold that held it out); `normal_map`: per-texel angular error
    averaged over the folds (None without ground truth)."""

    folds: list[dict]
    heldout_map: np.ndarray
    lambertian_map: np.ndarray
    normal_map: np.ndarray | None
    settings: FitSettings

    @property
    def mean_ratio(self) -> float:
        return float(np.mean([f["ratio"] for f in self.folds]))

    @property
    def worst_ratio(self) -> float:
        return float(np.max([f["ratio"] for f in self.folds]))

    def mean(self, key: str) -> float:
        return float(np.mean([f[key] for f in self.folds]))

    def table(self) -> str:
        """The per-fold figures, their mean and worst, as text."""
        gt = "normals_deg" in self.folds[0]
        head = "fold  lights  held-out  Lambertian  ratio" + ("  normals  Lambertian normals (deg)" if gt else "")
        rows = [head]

        def line(label, lights, f):
            text = f"{label:>4}  {lights:>6}  {f['heldout']:8.4f}  {f['lambertian']:10.4f}  {f['ratio']:5.2f}"
            return text + (f"  {f['normals_deg']:7.2f}  {f['lambertian_normals_deg']:7.2f}" if gt else "")

        for i, f in enumerate(self.folds):
            rows.append(line(str(i), str(len(f["lights"])), f))
        keys = ["heldout", "lambertian", "ratio"] + (["normals_deg", "lambertian_normals_deg"] if gt else [])
        rows.append(line("mean", "", {k: self.mean(k) for k in keys}))
        worst = max(self.folds, key=lambda f: f["ratio"])
        rows.append(f"worst fold {self.folds.index(worst)}: ratio {worst['ratio']:.2f}; "
                    f"mean ratio {self.mean_ratio:.2f} (held-out relative RMS of the fit / of a least-squares "
                    "Lambertian fit of the same lights)")
        return "\n".join(rows)


def _predict(maps, light_dirs, view_dir) -> jnp.ndarray:
    texels = jax.tree.map(jnp.asarray, maps).texel()
    return jnp.stack([relight(texels, d, view_dir) for d in np.asarray(light_dirs)], axis=2)


def _texel_sums(predicted, obs: Observations) -> tuple[np.ndarray, np.ndarray]:
    """Per texel: sum of squared error and of squared observation over the valid observations."""
    w = (np.asarray(obs.weight) > 0)[..., None]
    r = np.asarray(obs.ratio, np.float64)
    d = np.asarray(predicted, np.float64) - r
    return np.sum(np.where(w, d * d, 0.0), axis=(2, 3)), np.sum(np.where(w, r * r, 0.0), axis=(2, 3))


def cross_validate(obs: Observations, settings: FitSettings | None = None, *, folds: int = DEFAULT_FOLDS,
                   normals: np.ndarray | None = None, progress: bool | None = None) -> CrossValidation:
    """K-fold light cross-validation of the fit of `obs` (module docstring). `normals`: ground-truth
    `H W 3` normals (optional). `progress`: a bar over the folds (None: on a terminal only)."""
    settings = settings or FitSettings()
    mask = np.ones(obs.size, bool) if obs.mask is None else np.asarray(obs.mask, bool)
    records = []
    err = {"fit": np.zeros(obs.size), "lambertian": np.zeros(obs.size)}
    ref = np.zeros(obs.size)
    normal_sum = np.zeros(obs.size)
    bar = tqdm(light_folds(obs.n_lights, folds), desc="folds", disable=None if progress is None else not progress)
    for held in bar:
        train, test = select_lights(obs, np.setdiff1d(np.arange(obs.n_lights), held)), select_lights(obs, held)
        w0, c0 = time.perf_counter(), time.process_time()
        maps = fit_maps(train, settings, progress=False)
        seconds, cpu = time.perf_counter() - w0, time.process_time() - c0
        predicted = _predict(maps, test.light_dirs, obs.view_dir)
        lambert = lambertian_fit(train)
        lambert_predicted = lambert.predict(test.light_dirs)
        record = {"lights": held.tolist(), "heldout": relative_rms(predicted, test),
                  "lambertian": relative_rms(lambert_predicted, test), "seconds": round(seconds, 2),
                  "cpu_seconds": round(cpu, 2)}
        record["ratio"] = record["heldout"] / record["lambertian"]
        for key, pred in (("fit", predicted), ("lambertian", lambert_predicted)):
            sq_err, sq_ref = _texel_sums(pred, test)
            err[key] += sq_err
        ref += sq_ref   # the same observations for both
        if normals is not None:
            record["normals_deg"], angle = angular_error_deg(maps.normal, normals, mask)
            record["lambertian_normals_deg"] = angular_error_deg(np.asarray(lambert.normal), normals, mask)[0]
            normal_sum += np.nan_to_num(angle)
        records.append(record)

    def relative(sq):
        return np.where(mask & (ref > 0), np.sqrt(sq / np.where(ref > 0, ref, 1.0)), np.nan)

    normal_map = None if normals is None else np.where(mask, normal_sum / folds, np.nan)
    return CrossValidation(records, relative(err["fit"]), relative(err["lambertian"]), normal_map, settings)


def figure(result: CrossValidation, out: str | os.PathLike, title: str) -> Path:
    """A PNG of the per-texel held-out error of the fit and of the Lambertian fit (every light
    predicted by the fold that held it out), their ratio, the angular error map with ground truth,
    and the per-fold ratios."""
    panels = [("held-out relative RMS: fit", result.heldout_map, "magma"),
              ("held-out relative RMS: Lambertian fit", result.lambertian_map, "magma")]
    with np.errstate(divide="ignore", invalid="ignore"):
        panels.append(("log2(fit / Lambertian) per texel", np.log2(result.heldout_map / result.lambertian_map),
                       "coolwarm"))
    if result.normal_map is not None:
        panels.append(("angular error vs ground truth (deg), mean over folds", result.normal_map, "viridis"))
    fig = Figure(figsize=(4.2 * (len(panels) + 1), 4.2))   # no pyplot: no global figure state, any backend
    axes = fig.subplots(1, len(panels) + 1)
    finite = np.concatenate([p[1][np.isfinite(p[1])] for p in panels[:2]])
    top = float(np.percentile(finite, 99)) if finite.size else 1.0
    for ax, (name, image, cmap) in zip(axes, panels):
        if cmap == "coolwarm":
            im = ax.imshow(image, cmap=cmap, vmin=-2, vmax=2, interpolation="nearest")
        elif cmap == "magma":
            im = ax.imshow(image, cmap=cmap, vmin=0, vmax=top, interpolation="nearest")
        else:
            im = ax.imshow(image, cmap=cmap, interpolation="nearest",
                           vmax=float(np.nanpercentile(image, 99)) if np.isfinite(image).any() else None)
        fig.colorbar(im, ax=ax, fraction=0.046)
        ax.set_title(name, fontsize=9)
        ax.axis("off")
    ax = axes[-1]
    ratios = [f["ratio"] for f in result.folds]
    ax.bar(np.arange(len(ratios)), ratios, color=["tab:red" if r > 1 else "tab:blue" for r in ratios])
    ax.axhline(1.0, color="k", lw=0.8)
    ax.set_xlabel("fold")
    ax.set_ylabel("held-out error / Lambertian's")
    ax.set_title(f"per fold (mean {result.mean_ratio:.2f}, worst {result.worst_ratio:.2f})", fontsize=9)
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    out = Path(out)
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    return out

"""Relighting a fitted BTF and reporting how well a fit explains its capture.

`relight(btf, light_dir, view_dir)`: the reflectance R (what a capture observes: radiance over a
white board's at normal incidence) of every texel under one distant light, from a BTF directory
or a `BTFTexel` map, with `jaxrender.brdf.reflectance` (the model form recorded in btf.json).

`fit_report(capture_dir, btf_dir)`: per light direction the relative RMS error of the relit
sample against the merged observations (valid texels inside the mask only), the residual histogram
and the maps, as a PNG figure and a printed table; with `holdout=k` the error on lights held out of
a refit, beside a Lambertian fit's; with `normals=` the angular error against a ground truth.
"""

from __future__ import annotations

import functools
import os
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxrender.brdf import BTFTexel, reflectance
from jaxrender.io import InputError, atomic_path, linear_to_srgb, read_btf

from .capture import load_capture
from .evaluate import angular_error_deg, heldout_split, lambertian_fit, read_normal_map, relative_rms, select_lights
from .fit import fit_maps
from .hdr import merge_capture
from .settings import FitSettings

__all__ = ["relight", "load_btf_texels", "fit_report", "relight_errors", "heldout_report"]


def load_btf_texels(btf_dir: str | os.PathLike, *, level: int = 0) -> tuple[BTFTexel, str]:
    """(the `H W` BTFTexel of one level, the model form) of a BTF directory."""
    manifest, levels = read_btf(btf_dir)
    if not 0 <= level < len(levels):
        raise InputError(Path(btf_dir) / "btf.json", f"no level {level} (the BTF has {len(levels)})")
    return BTFTexel.from_channels(levels[level]), manifest["model"]


@functools.partial(jax.jit, static_argnames="model")
def _relight(texels: BTFTexel, light_dir, view_dir, model: str):
    flat = jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:]), texels)
    out = jax.vmap(lambda t: reflectance(t, light_dir, view_dir, model=model))(flat)
    return out.reshape(texels.rho_d.shape)


def relight(btf: str | os.PathLike | BTFTexel, light_dir, view_dir=(0.0, 0.0, 1.0), *, level: int = 0,
            model: str | None = None) -> Float[Array, "H W 3"]:
    """R of every texel under the distant light `light_dir` seen from `view_dir` (unit vectors,
    sample frame). `btf`: a BTF directory (its recorded model form) or an `H W` BTFTexel."""
    if isinstance(btf, BTFTexel):
        texels, form = btf, model or "reciprocal"
    else:
        texels, form = load_btf_texels(btf, level=level)
        form = model or form
    dt = texels.rho_d.dtype
    return _relight(texels, jnp.asarray(light_dir, dt), jnp.asarray(view_dir, dt), form)


@functools.partial(jax.jit, static_argnames="model")
def _light_errors(texels_flat: BTFTexel, ratio, weight, light_dirs, view_dir, model: str):
    """Per light: (sum of squared error, sum of squared observation) over valid texels."""
    def per_light(wi, r, w):  # r: T 3, w: T
        pred = jax.vmap(lambda t: reflectance(t, wi, view_dir, model=model))(texels_flat)
        d = (pred - r) * w[:, None]
        return jnp.sum(d * d), jnp.sum((r * w[:, None]) ** 2)

    return jax.vmap(per_light, in_axes=(0, 1, 1))(light_dirs, ratio, weight)


def relight_errors(texels: BTFTexel, obs, *, model: str = "reciprocal", batch: int = 64) -> np.ndarray:
    """Relative RMS relighting error per light (`L`) of `H W` texels against `Observations`."""
    h, w = obs.size
    n_lights = obs.n_lights
    flat = jax.tree_util.tree_map(lambda x: jnp.asarray(x, jnp.float32).reshape((h * w,) + x.shape[2:]), texels)
    ratio = np.asarray(obs.ratio, np.float32).reshape(h * w, n_lights, 3)
    valid = (np.asarray(obs.weight) > 0).reshape(h * w, n_lights).astype(np.float32)
    dirs = np.asarray(obs.light_dirs, np.float32)
    view = jnp.asarray(obs.view_dir, jnp.float32)
    num, den = [], []
    for start in range(0, n_lights, batch):  # a handful of light batches: bounded memory
        ids = np.minimum(np.arange(start, start + batch), n_lights - 1)
        a, b = _light_errors(flat, ratio[:, ids], valid[:, ids], dirs[ids], view, model)
        count = min(batch, n_lights - start)
        num.append(np.asarray(a)[:count])
        den.append(np.asarray(b)[:count])
    num, den = np.concatenate(num), np.concatenate(den)
    return np.sqrt(num / np.where(den > 0, den, np.inf))


def _table(angles: np.ndarray, errors: np.ndarray, level0: dict, inside: np.ndarray) -> str:
    """Relighting error per ring of light elevation: the capture's own rings when it has a few
    (a dome of regular rings), else 10-degree bands (any layout, e.g. an LED rig)."""
    rows = ["theta_deg  lights  mean_rel_err  max_rel_err"]
    theta = angles[:, 0]
    rings = np.unique(np.round(theta, 3))
    if len(rings) > 12:  # irregular elevations: bands of 10 degrees
        edges = np.arange(0.0, 100.0, 10.0)
        bands = [(lo, (theta >= lo) & (theta < lo + 10.0)) for lo in edges]
        labels = [(f"{lo:4.0f}-{lo + 10:<4.0f}", sel) for lo, sel in bands if sel.any()]
    else:
        labels = [(f"{t:9.1f}", np.abs(theta - t) < 5e-4) for t in rings]
    for label, sel in labels:
        if sel.any():
            rows.append(f"{label:>9}  {sel.sum():6d}  {np.nanmean(errors[sel]):12.4f}  {np.nanmax(errors[sel]):11.4f}")
    res = level0["residual"][inside]
    rows.append("")
    if res.size:
        rows.append(f"texels {res.size} (of {inside.size})  converged {np.mean(level0['converged'][inside] > 0):.1%}  "
                    f"residual median {np.median(res):.4g}  p90 {np.percentile(res, 90):.4g}  max {np.max(res):.4g}")
    rows.append(f"relighting error over all lights: median {np.nanmedian(errors):.4f}  max {np.nanmax(errors):.4f}")
    return "\n".join(rows)


def heldout_report(obs, k: int, settings: FitSettings | None = None, *, progress: bool | None = None) -> dict:
    """Fit without every `k`-th light and predict those lights: relative RMS of the fit and of a
    least-squares Lambertian fit of the same lights (valid observations inside the mask)."""
    fitted, held = heldout_split(obs.n_lights, k)
    train, test = select_lights(obs, fitted), select_lights(obs, held)
    maps = fit_maps(train, settings, progress=progress)
    texels = jax.tree.map(jnp.asarray, maps).texel()
    predicted = jnp.stack([relight(texels, d, obs.view_dir) for d in np.asarray(test.light_dirs)], axis=2)
    lambert = lambertian_fit(train)
    return {"k": k, "lights_fitted": int(fitted.size), "lights_held_out": int(held.size),
            "fit": relative_rms(predicted, test), "lambertian": relative_rms(lambert.predict(test.light_dirs), test),
            "held_out": held}


def fit_report(capture_dir: str | os.PathLike, btf_dir: str | os.PathLike, *, out: str | os.PathLike | None = None,
               obs=None, holdout: int | None = None, normals: str | os.PathLike | None = None) -> dict:
    """Compare a fitted BTF with its capture (any light layout; texels outside the capture's mask
    skipped). Writes the figure to `out` (default `BTF_DIR/report.png`); returns {"errors": per-light
    relative RMS, "angles": L 2 (theta, phi), "table": str, "figure": Path, "residual": H W}, plus
    "heldout" (`heldout_report`) with `holdout` = k and "normal_error_deg" (mean over the mask) and
    "normal_error_map" with a ground-truth `normals` map (`read_normal_map`). `obs`: already merged
    observations (optional)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    capture = load_capture(capture_dir)
    if holdout is not None and not 2 <= holdout <= capture.n_lights:
        raise InputError(capture_dir, f"--holdout {holdout}: hold out every k-th light with 2 <= k <= "
                                      f"{capture.n_lights} (the capture's lights)")
    gt = None if normals is None else read_normal_map(normals, capture.size)
    if gt is not None and not np.any(capture.read_mask() & (np.linalg.norm(gt, axis=-1) > 0)):
        raise InputError(normals, "no non-zero normal inside the capture's mask: nothing to compare")
    texels, model = load_btf_texels(btf_dir)
    if obs is None:
        obs = merge_capture(capture, progress=False)
    if tuple(texels.rho_d.shape[:2]) != tuple(obs.size):
        raise InputError(Path(btf_dir) / "level_00.exr",
                         f"size {list(texels.rho_d.shape[:2])} differs from the capture's {list(obs.size)}")
    _, levels = read_btf(btf_dir)
    level0 = levels[0]
    inside = capture.read_mask() & (level0["mask"] > 0)
    obs = eqx.tree_at(lambda o: o.weight, obs, obs.weight * jnp.asarray(inside, obs.weight.dtype)[:, :, None])
    errors = relight_errors(texels, obs, model=model)
    angles = np.asarray(capture.light_angles, float)
    table = _table(angles, errors, level0, inside)
    result = {"errors": errors, "angles": angles, "residual": level0["residual"]}
    if gt is not None:
        fitted_normals = np.stack([level0[f"normal.{a}"] for a in "XYZ"], -1)
        result["normal_error_deg"], result["normal_error_map"] = angular_error_deg(fitted_normals, gt, inside)
        table += f"\nnormals: mean angular error {result['normal_error_deg']:.2f} deg over {int(inside.sum())} texels"
    if holdout is not None:
        result["heldout"] = held = heldout_report(obs, holdout)
        table += (f"\nheld-out lights (every {held['k']}-th: {held['lights_held_out']} of {obs.n_lights}, refitted on "
                  f"the other {held['lights_fitted']}): relative RMS {held['fit']:.4f} "
                  f"(least-squares Lambertian fit of the same lights: {held['lambertian']:.4f})")

    fig = plt.figure(figsize=(15, 8.5))
    ax = fig.add_subplot(2, 4, 1, projection="polar")
    sc = ax.scatter(np.radians(angles[:, 1]), angles[:, 0], c=errors, s=12, cmap="magma")
    ax.set_ylim(0, 90)
    ax.set_title("relighting error per light\n(radius: theta, angle: phi)", fontsize=9)
    fig.colorbar(sc, ax=ax, fraction=0.046, pad=0.1)
    ax = fig.add_subplot(2, 4, 2)
    res = level0["residual"][inside].ravel()
    ax.hist(res[np.isfinite(res)], bins=40, color="steelblue")
    ax.set_title("residual (RMS over valid observations)", fontsize=9)
    ax.set_xlabel("reflectance units")

    def rgb(name):
        return np.stack([level0[f"{name}.{c}"] for c in "RGB"], -1)

    last = ("angular error vs ground truth (deg)", np.nan_to_num(result["normal_error_map"])) if gt is not None \
        else ("residual", level0["residual"])
    panels = [("rho_d", np.asarray(linear_to_srgb(np.clip(rgb("rho_d"), 0, 1)))),
              ("rho_s (scaled)", np.clip(rgb("rho_s") / max(np.percentile(rgb("rho_s"), 99), 1e-6), 0, 1)),
              ("normal (0.5 + 0.5 N)", np.clip(0.5 + 0.5 * np.stack([level0[f"normal.{a}"] for a in "XYZ"], -1), 0, 1)),
              ("sigma_x", level0["sigma_x"]), ("sigma_y", level0["sigma_y"]), last]
    for i, (title, img) in enumerate(panels):
        ax = fig.add_subplot(2, 4, 3 + i)
        im = ax.imshow(img, interpolation="nearest", cmap=None if img.ndim == 3 else "viridis")
        if img.ndim == 2:
            fig.colorbar(im, ax=ax, fraction=0.046)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.suptitle(f"fit report: {Path(btf_dir).name} vs {Path(capture_dir).name} ({model} model); "
                 f"median relighting error {np.nanmedian(errors):.3f}", fontsize=11)
    fig.tight_layout()
    out = Path(out) if out is not None else Path(btf_dir) / "report.png"
    with atomic_path(out) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)
    return {**result, "table": table, "figure": out}

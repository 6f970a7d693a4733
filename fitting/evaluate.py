"""How well a fit holds up: normals against a ground-truth map (mean angular error, the
photometric-stereo benchmarks' figure of merit), and lights held out of the fit predicted (the
figure that matters for a BTF rendered under new light), beside a least-squares Lambertian fit of
the same lights (the benchmarks' baseline)."""

from __future__ import annotations

import os
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxrender.io import InputError, read_exr, read_mat

from .hdr import Observations

__all__ = ["LambertianFit", "lambertian_fit", "angular_error_deg", "read_normal_map", "heldout_split",
           "select_lights", "relative_rms"]


class LambertianFit(eqx.Module):
    """Per texel: R_lc = albedo_c max(0, n . l), n and albedo from weighted least squares."""

    albedo: Float[Array, "H W 3"]
    normal: Float[Array, "H W 3"]

    def predict(self, light_dirs: Float[Array, "L 3"]) -> Float[Array, "H W L 3"]:
        shading = jnp.maximum(jnp.einsum("hwk,lk->hwl", self.normal, light_dirs), 0.0)
        return shading[..., None] * self.albedo[:, :, None, :]


@jax.jit
def lambertian_fit(obs: Observations) -> LambertianFit:
    """Classic photometric stereo per channel: b_c = argmin sum_l w_l (R_lc - l . b_c)^2 (valid
    observations only, a ridge at rounding level for texels with fewer than 3), n = b / |b| of the channels' sum,
    albedo_c = n . b_c (>= 0)."""
    dirs = jnp.asarray(obs.light_dirs, obs.ratio.dtype)
    w = obs.weight
    gram = jnp.einsum("hwl,lj,lk->hwjk", w, dirs, dirs)
    eps = 10 * jnp.finfo(gram.dtype).eps  # a ridge at rounding level: texels with < 3 lights stay finite
    ridge = eps * (jnp.trace(gram, axis1=-2, axis2=-1) + eps)
    gram = gram + ridge[..., None, None] * jnp.eye(3, dtype=gram.dtype)[None, None]
    rhs = jnp.einsum("hwl,hwlc,lj->hwjc", w, obs.ratio, dirs)  # 3 x channels
    b = jnp.linalg.solve(gram, rhs)  # H W 3 C
    total = jnp.sum(b, axis=-1)
    norm = jnp.sqrt(jnp.sum(total * total, axis=-1, keepdims=True))
    normal = jnp.where(norm > 0, total / jnp.where(norm > 0, norm, 1.0), jnp.asarray([0.0, 0.0, 1.0], total.dtype))
    albedo = jnp.maximum(jnp.einsum("hwj,hwjc->hwc", normal, b), 0.0)
    return LambertianFit(albedo, normal)


def angular_error_deg(normals, reference, mask=None) -> tuple[float, np.ndarray]:
    """(mean angular error in degrees over the mask, the `H W` error map; NaN outside the mask and where
    the reference is zero)."""
    n = np.asarray(normals, np.float64)
    r = np.asarray(reference, np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    rn = np.linalg.norm(r, axis=-1)
    inside = (rn > 0) if mask is None else (np.asarray(mask, bool) & (rn > 0))
    cos = np.sum(n * r / np.maximum(rn, 1e-12)[..., None], axis=-1)
    err = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    err = np.where(inside, err, np.nan)
    return float(np.nanmean(err)) if inside.any() else float("nan"), err


def read_normal_map(path: str | os.PathLike, size: tuple[int, int] | None = None) -> np.ndarray:
    """A ground-truth normal map `H W 3` (sample frame) from a MAT file (its one `H W 3` variable,
    e.g. DiLiGenT's Normal_gt), a `.npy` array or an EXR (`normal.X/Y/Z` or R, G, B)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".mat":
        arrays = [a for a in read_mat(path).values() if a.ndim == 3 and a.shape[-1] == 3]
        if len(arrays) != 1:
            raise InputError(path, "expected one H x W x 3 array in the MAT file")
        normals = arrays[0]
    elif suffix == ".npy":
        try:
            normals = np.load(path)
        except (OSError, ValueError) as error:
            raise InputError(path, f"not a readable .npy array ({error})") from None
    elif suffix == ".exr":
        channels = read_exr(path)
        names = next((n for n in (("normal.X", "normal.Y", "normal.Z"), ("R", "G", "B"))
                      if all(c in channels for c in n)), None)
        if names is None:
            raise InputError(path, "EXR has neither normal.X/Y/Z nor R, G, B channels")
        normals = np.stack([channels[c] for c in names], axis=-1)
    else:
        raise InputError(path, f"unsupported normal map type {suffix!r} (use .mat, .npy or .exr)")
    normals = np.asarray(normals, np.float64)
    if normals.ndim != 3 or normals.shape[-1] != 3 or not np.isfinite(normals).all():
        raise InputError(path, f"expected a finite H x W x 3 normal map, got shape {normals.shape}")
    if size is not None and tuple(normals.shape[:2]) != tuple(size):
        raise InputError(path, f"size {normals.shape[0]}x{normals.shape[1]} differs from the capture's "
                               f"{size[0]}x{size[1]}")
    return normals


def heldout_split(n_lights: int, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(lights fitted, lights held out): every `k`-th light (indices k-1, 2k-1, ...) is held out."""
    if not 2 <= k <= n_lights:
        raise ValueError(f"hold out every k-th light with 2 <= k <= {n_lights}, got {k}")
    held = np.arange(k - 1, n_lights, k)
    return np.setdiff1d(np.arange(n_lights), held), held


def select_lights(obs: Observations, lights: np.ndarray) -> Observations:
    """The observations of some lights only (counts recomputed from the weights)."""
    lights = np.asarray(lights)
    weight = obs.weight[:, :, lights]
    n_valid = jnp.sum(weight > 0, axis=-1).astype(jnp.int32)
    return Observations(ratio=obs.ratio[:, :, lights], weight=weight, light_dirs=obs.light_dirs[lights],
                        view_dir=obs.view_dir, n_valid=n_valid, n_saturated=jnp.zeros_like(n_valid),
                        n_dark=jnp.zeros_like(n_valid), mask=obs.mask)


def relative_rms(predicted, obs: Observations) -> float:
    """||predicted - R|| / ||R|| over the valid observations inside the mask (`predicted`: `H W L 3`)."""
    w = np.asarray(obs.weight) > 0
    if obs.mask is not None:
        w &= np.asarray(obs.mask, bool)[:, :, None]
    diff = (np.asarray(predicted, np.float64) - np.asarray(obs.ratio, np.float64))[w]
    ref = np.asarray(obs.ratio, np.float64)[w]
    return float(np.linalg.norm(diff) / max(np.linalg.norm(ref), 1e-30))

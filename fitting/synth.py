"""Synthetic multi-light HDR captures with known parameter maps.

A woven fabric in the spirit of the paper's Noh costumes: a plain-weave silk ground (warp threads
along the image rows' direction y, weft along x, in two colours) with a gold brocade motif where
gold weft floats over three warps. Thread profiles tilt the normals (a dome per thread crossing);
the anisotropy axes are swapped between the two thread directions (warp: sigma_x > sigma_y, weft
and gold: sigma_x < sigma_y). Rendered with `jaxrender.brdf.reflectance` at the paper's 2160 light
directions (theta 0..87 step 3, phi 0..355 step 5) or a stratified subset, through a simulated
camera: 6 exposures, a smooth illumination falloff (removed by the white board), shot and read
noise in electrons, clipping at full well, an optional sRGB response and 8/16-bit quantization.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import functools
import json
import os
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray

from jaxrender.brdf import MODELS, BTFTexel, reflectance
from jaxrender.io import InputError, atomic_path, linear_to_srgb, output_folder, write_btf, write_exr, write_png
from jaxrender.maths import default_float

from .capture import direction_from_angles
from .hdr import Observations, observations_from_batches, observe

__all__ = ["EXPOSURES_S", "PAPER_THETAS_DEG", "PAPER_PHIS_DEG", "LIGHT_DIRECTIONS", "paper_light_angles",
           "paper_light_directions", "direction_from_angles", "stratified_light_subset", "Sensor",
           "synth_maps", "synth_codes", "synth_observations", "synth_capture", "truth_level"]

#: The paper's exposure times 1/4000, 1/640, 1/125, 1/20, 1/4, 1 s (design.md's example list).
EXPOSURES_S: tuple[float, ...] = (0.00025, 0.0015625, 0.008, 0.05, 0.25, 1.0)
PAPER_THETAS_DEG = np.arange(0, 90, 3, dtype=np.float64)  # 0..87 step 3: 30 rings
PAPER_PHIS_DEG = np.arange(0, 360, 5, dtype=np.float64)  # 0..355 step 5: 72 per ring


def paper_light_angles() -> np.ndarray:
    """`2160 2` (theta_deg, phi_deg) of the paper's light directions, theta-major."""
    theta, phi = np.meshgrid(PAPER_THETAS_DEG, PAPER_PHIS_DEG, indexing="ij")
    return np.stack([theta.ravel(), phi.ravel()], axis=-1)


def paper_light_directions() -> np.ndarray:
    """`2160 3` unit vectors in the sample frame (float64), in `paper_light_angles` order."""
    angles = paper_light_angles()
    return direction_from_angles(angles[:, 0], angles[:, 1])


LIGHT_DIRECTIONS = paper_light_directions()


def stratified_light_subset(key: PRNGKeyArray, n: int) -> np.ndarray:
    """Sorted indices of `n` of the 2160 paper directions, stratified over the hemisphere.

    Each theta ring gets a share of `n` proportional to its solid angle (jittered systematic
    sampling of the cumulative solid angle, so counts are within two of the share and a small `n`
    spreads over elevations; for dense subsets capped proportional shares, at most 72 a ring), and
    within a ring the chosen directions are one random phi from each of equal consecutive phi
    strata. `n` >= 2160 gives all directions. Deterministic in `key`.
    """
    total = len(PAPER_THETAS_DEG) * len(PAPER_PHIS_DEG)
    if n >= total:
        return np.arange(total)
    if n < 1:
        raise ValueError("the number of lights must be >= 1")
    per_ring = len(PAPER_PHIS_DEG)
    edges = np.radians(np.clip(np.concatenate([PAPER_THETAS_DEG - 1.5, [PAPER_THETAS_DEG[-1] + 1.5]]), 0, 90))
    area = np.cos(edges[:-1]) - np.cos(edges[1:])
    share = area / area.sum()
    # Host-side set-up: a numpy generator seeded by the key's bits (cheaper than tracing jax.random).
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key)).ravel().tolist())
    if n * share.max() + 1 <= per_ring:
        # Jittered systematic sampling of the cumulative solid angle: ring counts within two of
        # n * share, and small n spread over all elevations.
        u = (np.arange(n) + rng.uniform(size=n)) / n
        rings = np.minimum(np.searchsorted(np.cumsum(share), u, side="right"), len(share) - 1)
        counts = np.bincount(rings, minlength=len(share))
    else:  # dense subsets: proportional shares capped at 72 per ring, largest remainders first
        counts = np.zeros(len(area), int)
        remaining = n
        while remaining > 0:  # a handful of passes over 30 rings (host-side set-up)
            open_rings = counts < per_ring
            want = remaining * area * open_rings / np.sum(area * open_rings)
            add = np.minimum(np.floor(want).astype(int), per_ring - counts)
            if add.sum() == 0:
                order = np.argsort(-(want - np.floor(want)) + (~open_rings) * 10.0)  # full rings last
                add[order[:remaining]] = 1
                add = np.minimum(add, per_ring - counts)
            counts += add
            remaining = n - counts.sum()
    chosen = []
    for ring, count in enumerate(counts):
        if count == 0:
            continue
        bounds = np.linspace(0, per_ring, count + 1)
        lo, hi = np.ceil(bounds[:-1]).astype(int), np.ceil(bounds[1:]).astype(int)
        u = rng.uniform(size=count)
        pick = np.minimum(lo + np.floor(u * (hi - lo)).astype(int), hi - 1)
        chosen.append(ring * per_ring + pick)
    return np.sort(np.concatenate(chosen))


class Sensor(eqx.Module):
    """The simulated camera. The numbers are pytree leaves (changing them does not recompile);
    `bits` and `response` are static.

    gain: linear code (fraction of full scale) per unit reflectance per second of exposure (62.5:
    the white board of reflectance 1 at half scale in 1/125 s); full_well, read_noise in electrons;
    noise scales both noise terms (0: noiseless); vignette: illumination falloff toward the corners
    (1 - vignette r^2, r = 1 at the corners; the white board removes it); bits: 8 or 16 (PNG),
    0 (float, EXR: no quantization); response: "linear" or "srgb" (quantized PNG codes only).
    """

    gain: float = 62.5
    full_well: float = 20000.0
    read_noise: float = 10.0
    noise: float = 1.0
    vignette: float = 0.25
    bits: int = 8
    response: str = eqx.field(static=True, default="linear")

    def __check_init__(self):
        if self.bits not in (0, 8, 16):
            raise ValueError("bits must be 8, 16 or 0 (float)")
        if self.response not in ("linear", "srgb"):
            raise ValueError(f"unknown response {self.response!r}")
        if self.response == "srgb" and self.bits == 0:
            raise ValueError("float (EXR) codes are linear: the sRGB response needs 8 or 16 bits")

    def replace(self, **changes) -> "Sensor":
        """A copy with some settings changed."""
        return dataclasses.replace(self, **changes)


# ----------------------------------------------------------------------------------------------
# Parameter maps


def synth_maps(key: PRNGKeyArray, size: tuple[int, int], *, thread: int | None = None) -> BTFTexel:
    """Known one-lobe parameter maps `H W` of a woven sample (module docstring).

    `thread`: thread width in texels (default about min(H, W) / 8, at least 3). Randomness (thread
    colours, per-thread jitter of rho and sigma, the motif's centre) comes from `key` only.
    """
    return _synth_maps(key, (int(size[0]), int(size[1])), None if thread is None else int(thread))


@functools.partial(jax.jit, static_argnums=(1, 2))
def _synth_maps(key: PRNGKeyArray, size: tuple[int, int], thread: int | None) -> BTFTexel:
    h, w = size
    p = int(thread) if thread is not None else max(3, round(min(h, w) / 8))
    dtype = default_float()
    k_col, k_jit, k_motif = jax.random.split(key, 3)
    rows = jnp.arange(h)[:, None] * jnp.ones((1, w), int)
    cols = jnp.ones((h, 1), int) * jnp.arange(w)[None, :]
    ci, cj = rows // p, cols // p  # weft thread index (rows), warp thread index (columns)
    a = ((cols % p).astype(dtype) + 0.5) / p * 2 - 1  # across the warp, -1..1 left to right
    b = ((rows % p).astype(dtype) + 0.5) / p * 2 - 1  # across the weft, -1..1 top to bottom
    y_up = -b

    # Gold motif: a diamond around a random centre, decided per thread crossing (cell centre).
    centre = jax.random.uniform(k_motif, (2,), dtype, 0.35, 0.65)
    cy = (ci.astype(dtype) + 0.5) * p / h
    cx = (cj.astype(dtype) + 0.5) * p / w
    gold = (jnp.abs(cy - centre[0]) + jnp.abs(cx - centre[1])) < 0.3
    plain_warp_up = (ci + cj) % 2 == 0
    brocade_warp_up = (ci + cj) % 4 == 0  # gold weft floats over three warps
    warp_up = jnp.where(gold, brocade_warp_up, plain_warp_up)
    is_gold = gold & ~warp_up

    # Colours: two silk hues, jitter per thread.
    hue = jax.random.uniform(k_col, (2,), dtype)
    hue = hue.at[1].set(hue[0] + 0.35 + 0.3 * hue[1])  # weft hue well apart from the warp's

    def silk_colour(h, value):
        phases = jnp.asarray([0.0, 1 / 3, 2 / 3], dtype)
        return 0.04 + value * (0.5 + 0.5 * jnp.cos(2 * jnp.pi * (h - phases))) ** 2

    warp_rgb, weft_rgb = silk_colour(hue[0], 0.55), silk_colour(hue[1], 0.45)
    n_threads = max(h, w) // p + 2
    jitter = 1 + 0.12 * jax.random.uniform(k_jit, (2, n_threads, 3), dtype, -1.0, 1.0)
    warp_j, weft_j = jitter[0][cj], jitter[1][ci]  # H W 3
    thread_j = jnp.where(warp_up[..., None], warp_j, weft_j)

    gold_d = jnp.asarray([0.06, 0.045, 0.015], dtype)
    gold_s = jnp.asarray([1.6, 1.2, 0.45], dtype)
    silk_s = jnp.asarray([0.45, 0.45, 0.42], dtype)
    # Darkening toward the gaps between threads (across the thread on top).
    across = jnp.where(warp_up, jnp.abs(a), jnp.abs(b))
    gap = (1 - 0.45 * across**4)[..., None]
    silk_d = jnp.where(warp_up[..., None], warp_rgb[None, None, :], weft_rgb[None, None, :])
    rho_d = jnp.where(is_gold[..., None], gold_d[None, None, :], silk_d) * thread_j * gap
    rho_s = jnp.where(is_gold[..., None], gold_s[None, None, :], silk_s[None, None, :]) * thread_j * gap

    # Normals: a dome per crossing, steeper across the thread than along it.
    across_slope, along_slope = 0.55, 0.25
    sx = jnp.where(warp_up, across_slope * a, along_slope * a * jnp.where(is_gold, 0.4, 1.0))
    sy = jnp.where(warp_up, along_slope * y_up, across_slope * y_up * jnp.where(is_gold, 0.6, 1.0))
    normal = jnp.stack([sx, sy, jnp.ones_like(sx)], axis=-1)
    normal = normal / jnp.linalg.norm(normal, axis=-1, keepdims=True)

    # Anisotropy: broad across the fibres, narrow along them; swapped between warp and weft.
    s_jit = thread_j[..., 0]
    sigma_x = jnp.where(warp_up, 0.32, jnp.where(is_gold, 0.09, 0.12)) * s_jit
    sigma_y = jnp.where(warp_up, 0.11, jnp.where(is_gold, 0.22, 0.30)) * s_jit
    return BTFTexel.single(rho_d.astype(dtype), rho_s.astype(dtype), normal.astype(dtype),
                           sigma_x.astype(dtype), sigma_y.astype(dtype))


def vignette(size: tuple[int, int], amount: float, dtype=None) -> Float[Array, "H W"]:
    """Smooth illumination falloff 1 - amount * r^2 (r = 1 at the corners)."""
    h, w = size
    dtype = dtype or jnp.zeros(()).dtype
    y = (jnp.arange(h, dtype=dtype) + 0.5) / h * 2 - 1
    x = (jnp.arange(w, dtype=dtype) + 0.5) / w * 2 - 1
    r2 = (y[:, None] ** 2 + x[None, :] ** 2) / 2
    return 1 - amount * r2


# ----------------------------------------------------------------------------------------------
# Simulated camera


def _texel_reflectance(texel: BTFTexel, wi, wo, model: str):
    return reflectance(texel, wi, wo, model=model)


def render_reflectance(texels: BTFTexel, light_dirs: Float[Array, "B 3"], view_dir: Float[Array, "3"], *,
                       model: str = "reciprocal") -> Float[Array, "B H W 3"]:
    """Noise-free R of every texel under every light (vmapped over lights and texels)."""
    per_texel = functools.partial(_texel_reflectance, model=model)
    over_w = jax.vmap(per_texel, in_axes=(0, None, None))
    over_hw = jax.vmap(over_w, in_axes=(0, None, None))
    over_lights = jax.vmap(over_hw, in_axes=(None, 0, None))
    return over_lights(texels, light_dirs, view_dir)


def _expose(key, radiance_rel, exposures, sensor: Sensor):
    """Codes `E ...` of relative radiance `...` (unit reflectance at full illumination)."""
    dtype = radiance_rel.dtype
    t = jnp.reshape(jnp.asarray(exposures, dtype), (-1,) + (1,) * radiance_rel.ndim)
    linear = radiance_rel[None] * (sensor.gain * t)
    # Shot noise (Gaussian approximation of Poisson: variance = electrons) plus read noise
    # (variance read_noise^2) are independent Gaussians: one draw of their sum. Random numbers
    # dominate the cost of a synthetic capture, so one draw per sample, not two.
    electrons = jnp.maximum(linear, 0.0) * sensor.full_well
    sigma = jnp.sqrt(electrons + jnp.square(sensor.read_noise)) / sensor.full_well
    z = jax.random.normal(key, linear.shape, dtype)
    noisy = jnp.clip(linear + sensor.noise * sigma * z, 0.0, 1.0)
    if sensor.response == "srgb":
        noisy = linear_to_srgb(noisy).astype(dtype)
    # The ADC: round to 2^bits - 1 steps (bits = 0: float codes). A traced `bits`, so 8-bit,
    # 16-bit and float captures share one compilation (textures.quantize needs a static one).
    levels = jnp.exp2(jnp.asarray(sensor.bits).astype(dtype)) - 1
    return jnp.where(levels > 0, jnp.round(noisy * levels) / jnp.maximum(levels, 1.0), noisy)


@functools.partial(jax.jit, static_argnames=("model",))
def synth_codes(key: PRNGKeyArray, texels: BTFTexel, light_dirs: Float[Array, "B 3"],
                light_ids: Int[Array, " B"], view_dir: Float[Array, "3"], exposures: Float[Array, " E"],
                *, sensor: Sensor, model: str = "reciprocal") -> Float[Array, "B E H W 3"]:
    """Raw code values of a batch of lights. The noise of light `light_ids[b]` depends only on
    (`key`, that id), so batching does not change the result."""
    refl = render_reflectance(texels, light_dirs, view_dir, model=model)
    v = vignette(refl.shape[1:3], sensor.vignette, refl.dtype)[None, :, :, None]
    keys = jax.vmap(jax.random.fold_in, in_axes=(None, 0))(key, light_ids)
    return jax.vmap(_expose, in_axes=(0, 0, None, None))(keys, refl * v, exposures, sensor)


@functools.partial(jax.jit, static_argnames=("size",))
def synth_white_codes(key: PRNGKeyArray, reflectance_rgb: Float[Array, "3"], exposures: Float[Array, " E"], *,
                      size: tuple[int, int], sensor: Sensor) -> Float[Array, "E H W 3"]:
    """Codes of the white board lit at normal incidence (reflectance * falloff)."""
    dtype = reflectance_rgb.dtype
    v = vignette(size, sensor.vignette, dtype)
    radiance = v[:, :, None] * jnp.reshape(reflectance_rgb, (1, 1, 3))
    return _expose(key, radiance, exposures, sensor)


def _reflectance_rgb(white_reflectance, dtype) -> Array:
    r = jnp.asarray(white_reflectance, dtype)
    return jnp.broadcast_to(jnp.reshape(r, (-1,)), (3,)) if r.size in (1, 3) else _bad_reflectance()


def _bad_reflectance():
    raise ValueError("white reflectance must be a number or an RGB triple")


def synth_observations(key: PRNGKeyArray, texel_maps: BTFTexel, light_dirs: Float[Array, "L 3"], *,
                       view_dir=(0.0, 0.0, 1.0), model: str = "reciprocal",
                       exposures_s=EXPOSURES_S, sensor: Sensor | None = None,
                       white_reflectance=0.95, batch: int = 64, progress: bool | None = False) -> Observations:
    """Simulate a capture of `texel_maps` and merge it in memory: the same codes `synth_capture`
    writes for the same `key` (and the same lights), without the disk."""
    sensor = sensor or Sensor()
    if model not in MODELS:
        raise ValueError(f"unknown model {model!r}: use one of {MODELS}")
    dtype = texel_maps.rho_d.dtype
    light_dirs = jnp.asarray(light_dirs, dtype)
    view = jnp.asarray(view_dir, dtype)
    exposures = jnp.asarray(exposures_s, dtype)
    size = tuple(int(s) for s in texel_maps.rho_d.shape[:2])
    k_lights, k_white = jax.random.split(key)
    refl_rgb = _reflectance_rgb(white_reflectance, dtype)
    white = synth_white_codes(k_white, refl_rgb, exposures, size=size, sensor=sensor)
    response = "srgb" if (sensor.response == "srgb" and sensor.bits) else "linear"
    n = light_dirs.shape[0]
    batch = max(1, min(batch, n))

    def batches():
        for start in range(0, n, batch):
            ids = jnp.arange(start, start + batch)
            dirs = light_dirs[jnp.minimum(ids, n - 1)]
            codes = synth_codes(k_lights, texel_maps, dirs, ids, view, exposures, sensor=sensor, model=model)
            yield (slice(start, min(start + batch, n)), *observe(codes, exposures, white, refl_rgb, response=response))

    return observations_from_batches(batches(), size=size, n_lights=n, light_dirs=light_dirs,
                                     view_dir=view, dtype=np.dtype(dtype), progress=progress)


# ----------------------------------------------------------------------------------------------
# On disk


def truth_level(texels: BTFTexel, observations: Observations | dict | None = None) -> dict[str, np.ndarray]:
    """Level-0 channels of the true maps: residual 0, converged 1, and the observation counts
    (from `Observations` or a dict with n_valid, n_saturated, n_dark; zeros without)."""
    channels = {k: np.asarray(v, np.float32) for k, v in texels.to_channels().items()}
    shape = channels["sigma_x"].shape
    channels["residual"] = np.zeros(shape, np.float32)
    channels["converged"] = np.ones(shape, np.float32)
    for name in ("n_valid", "n_saturated", "n_dark"):
        if observations is None:
            value = np.zeros(shape)
        else:
            value = observations[name] if isinstance(observations, dict) else getattr(observations, name)
        channels[name] = np.asarray(value, np.float32)
    return channels


def synth_capture(out_dir: str | os.PathLike, *, key: PRNGKeyArray, size: tuple[int, int] = (32, 32),
                  lights: int | str = 300, bits: int = 8, image_format: str = "png",
                  response: str = "linear", noise: float = 1.0, model: str = "reciprocal",
                  white_reflectance=0.95, sensor: Sensor | None = None, batch: int = 64,
                  workers: int = 8, progress: bool | None = None) -> Path:
    """Write a synthetic capture directory (design.md format) and its true maps in `OUT_DIR/truth/`.

    Everything is written into a staging folder and moved into `out_dir` at the end
    (`jaxrender.io.output_folder`), so an interrupted run leaves nothing that looks complete; an
    existing `out_dir` keeps its other files.
    `lights`: "all" (the paper's 2160) or a number (a stratified subset chosen by `key`).

    The same observations without the disk: with `k_maps, k_lights, k_sel = jax.random.split(key, 3)`,
    `synth_observations(k_lights, synth_maps(k_maps, size), LIGHT_DIRECTIONS[ids], sensor=...)`
    where `ids = stratified_light_subset(k_sel, lights)` (or all 2160); the truth's btf.json
    records `light_indices`.
    """
    from tqdm.auto import tqdm

    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(out_dir, "exists and is not a folder")
    if image_format not in ("png", "exr"):
        raise InputError(None, f"unknown image format {image_format!r} (png or exr)")
    if model not in MODELS:
        raise InputError(None, f"unknown model {model!r} (use one of {MODELS})")
    if image_format == "exr":
        bits, response = 0, "linear"
    elif bits not in (8, 16):
        raise InputError(None, "PNG captures are 8- or 16-bit")
    # The file format decides bits and response; `sensor` supplies the rest (gain, noise, ...).
    sensor = (sensor or Sensor(noise=noise)).replace(bits=bits, response=response)
    k_maps, k_lights, k_sel = jax.random.split(key, 3)
    if lights == "all":
        ids = np.arange(len(LIGHT_DIRECTIONS))
    else:
        ids = stratified_light_subset(k_sel, int(lights))
    angles = paper_light_angles()[ids]
    dirs_np = LIGHT_DIRECTIONS[ids]
    texels = synth_maps(k_maps, size)
    dtype = texels.rho_d.dtype
    exposures = jnp.asarray(EXPOSURES_S, dtype)
    view = jnp.asarray([0.0, 0.0, 1.0], dtype)
    dirs = jnp.asarray(dirs_np, dtype)
    k_obs, k_white = jax.random.split(k_lights)
    refl_rgb = _reflectance_rgb(white_reflectance, dtype)
    ext = "exr" if image_format == "exr" else "png"

    def save(path: Path, codes: np.ndarray):
        if image_format == "exr":
            write_exr(path, codes)
        else:
            write_png(path, codes, srgb=False, bits=bits)

    n = len(ids)
    batch = max(1, min(batch, n))
    with output_folder(out_dir) as tmp:
        images = tmp / "images"
        images.mkdir()
        white = synth_white_codes(k_white, refl_rgb, exposures, size=tuple(size), sensor=sensor)
        white_names = []
        for e in range(len(EXPOSURES_S)):
            white_names.append(f"images/white_e{e}.{ext}")
            save(tmp / white_names[-1], np.asarray(white[e]))
        light_entries = []
        counts = {name: np.zeros(tuple(size), np.int32) for name in ("n_valid", "n_saturated", "n_dark")}
        bar = tqdm(total=n, unit="light", desc="synth", disable=None if progress is None else not progress)
        # Image files are written by threads (encoding and renames overlap); each batch is finished
        # before the next is submitted, which bounds memory and surfaces errors early.
        with concurrent.futures.ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
            for start in range(0, n, batch):
                idx = jnp.arange(start, start + batch)
                codes = synth_codes(k_obs, texels, dirs[jnp.minimum(idx, n - 1)], idx, view, exposures,
                                    sensor=sensor, model=model)
                _, valid, saturated, dark = observe(codes, exposures, white, refl_rgb,
                                                    response=response if bits else "linear")
                count = min(batch, n - start)
                for name, flags in zip(counts, (valid, saturated, dark), strict=True):
                    counts[name] += np.asarray(flags)[:, :, :count].sum(axis=-1, dtype=np.int32)
                codes = np.asarray(codes)
                futures = []
                for b in range(count):
                    names = [f"images/l{start + b:04d}_e{e}.{ext}" for e in range(len(EXPOSURES_S))]
                    futures += [pool.submit(save, tmp / name, codes[b, e]) for e, name in enumerate(names)]
                    light_entries.append({"theta_deg": float(angles[start + b, 0]),
                                          "phi_deg": float(angles[start + b, 1]), "images": names})
                for future in futures:
                    future.result()
                bar.update(count)
        bar.close()
        obs = counts
        write_btf(tmp / "truth", [truth_level(texels, obs)], model=model,
                  meta={"source": "fitting synth", "light_indices": [int(i) for i in ids]})
        refl_list = [float(x) for x in np.asarray(refl_rgb)]
        manifest = {
            "format": "jaxrender-capture", "version": 1, "size": [int(size[0]), int(size[1])],
            "response": response if image_format == "png" else "linear",
            # float codes of the emulated camera (clipped at 1, dark below 2/255), not radiance
            "encoding": "codes",
            "exposures_s": list(EXPOSURES_S), "view": {"theta_deg": 0.0, "phi_deg": 0.0},
            "white": {"reflectance": refl_list[0] if len(set(refl_list)) == 1 else refl_list, "images": white_names},
            "lights": light_entries,
            "synth": {"model": model, "bits": bits, "noise": sensor.noise,
                      "sensor": {f.name: getattr(sensor, f.name) for f in dataclasses.fields(sensor)},
                      "light_indices": [int(i) for i in ids]},
        }
        with atomic_path(tmp / "capture.json") as path:
            path.write_text(json.dumps(manifest, indent=1) + "\n")
    return out_dir


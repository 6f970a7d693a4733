"""HDR merge of exposure brackets and the white-board normalisation (design.md, "Capture directory").

A code value c (raw, normalised to [0, 1] of full scale) of exposure t is linearised by the
capture's response, divided by t and averaged over the bracket with the weight

    w(c, t) = hat(c) * t,   hat(c) = clip(min(c - DARK_CODE, SATURATION_CODE - c) / HAT_RAMP, 0, 1),

zero for saturated (c >= 0.98) and near-black (c <= 2/255) samples. The factor t makes the
average approximately inverse-variance under shot noise (the variance of c/t falls as 1/t).
A sample saturated even in the shortest exposure, or dark even in the longest, has no valid
estimate: it is flagged, and its radiance is only a bound (c/t of that exposure), never used.
Observation of a texel under one light = merged radiance / merged white-board radiance at normal
incidence (per texel and channel) * board reflectance.
"""

from __future__ import annotations

import concurrent.futures
import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int
from tqdm.auto import tqdm

from jaxrender.io import srgb_to_linear

__all__ = ["SATURATION_CODE", "DARK_CODE", "HAT_RAMP", "RESPONSES", "Observations", "ObservationCounts", "linearize",
           "exposure_weights", "merge_exposures", "observe", "merge_capture", "thresholds"]

SATURATION_CODE = 0.98  # design.md: code values >= 0.98 of full scale get zero weight
DARK_CODE = 2.0 / 255.0  # design.md: code values <= 2/255 get zero weight
HAT_RAMP = 0.05  # the hat weight reaches 1 this far (in code units) inside the valid range
RESPONSES = ("linear", "srgb")


class ObservationCounts(eqx.Module):
    """Lights per texel whose observation was valid, saturated or dark (`H W` maps; a light with
    both a saturated and a dark channel counts in both)."""

    n_valid: Int[Array, "H W"]
    n_saturated: Int[Array, "H W"]
    n_dark: Int[Array, "H W"]


class Observations(eqx.Module):
    """Per-texel multi-light observations of a capture, ready for the fit.

    `ratio[h, w, l]` is the observed reflectance R (radiance / white-board radiance at normal
    incidence * board reflectance) under light `light_dirs[l]`, seen from `view_dir`;
    `weight[h, w, l]` is 1 where every channel of it is a valid merge, 0 where a channel was
    saturated even in the shortest exposure, dark even in the longest, or the white board was
    invalid at that texel. `n_valid`, `n_saturated`, `n_dark` count lights per texel (a light
    with both a saturated and a dark channel counts in both).
    """

    ratio: Float[Array, "H W L 3"]
    weight: Float[Array, "H W L"]
    light_dirs: Float[Array, "L 3"]
    view_dir: Float[Array, "3"]
    n_valid: Int[Array, "H W"]
    n_saturated: Int[Array, "H W"]
    n_dark: Int[Array, "H W"]
    mask: Bool[Array, "H W"] | None = None  # texels to fit (None: all)

    @property
    def size(self) -> tuple[int, int]:
        return tuple(self.weight.shape[:2])

    @property
    def n_lights(self) -> int:
        return int(self.light_dirs.shape[0])

    @property
    def counts(self) -> ObservationCounts:
        return ObservationCounts(self.n_valid, self.n_saturated, self.n_dark)


def linearize(codes: Float[ArrayLike, "..."], response: str) -> Float[Array, "..."]:
    """Raw normalised code values -> linear values (relative to full scale)."""
    if response not in RESPONSES:
        raise ValueError(f"unknown response {response!r}: use one of {RESPONSES}")
    codes = jnp.asarray(codes)
    return codes if response == "linear" else srgb_to_linear(codes).astype(codes.dtype)


def _expand(exposures: Array, ndim: int) -> Array:
    """`E` -> `E 1 ... 1` with `ndim` axes (explicit: rank promotion is an error in the tests)."""
    return jnp.reshape(exposures, exposures.shape + (1,) * (ndim - 1))


def exposure_weights(codes: Float[ArrayLike, "E ..."], exposures_s: Float[ArrayLike, " E"]) -> Float[Array, "E ..."]:
    """w(c, t) = hat(c) * t (module docstring); 0 at and beyond the saturation and dark codes."""
    codes = jnp.asarray(codes)
    t = _expand(jnp.asarray(exposures_s, dtype=codes.dtype), codes.ndim)
    return _hat(codes, DARK_CODE, SATURATION_CODE) * t


def thresholds(encoding: str, saturation: float | None = None) -> tuple[float, float]:
    """(dark, saturation) levels of an image encoding: integer "codes" keep design.md's 2/255 and
    0.98; "radiance" (EXR) is never dark and saturated only at a level the capture names."""
    if encoding == "codes":
        return DARK_CODE, SATURATION_CODE
    if encoding == "radiance":
        return -math.inf, math.inf if saturation is None else float(saturation)
    raise ValueError(f"unknown encoding {encoding!r}: use 'codes' or 'radiance'")


def _hat(codes: Array, dark, saturation) -> Array:
    """clip(min(c - dark, saturation - c) / RAMP, 0, 1): exactly 0 at and beyond both thresholds
    (1 everywhere for unbounded radiance)."""
    return jnp.clip(jnp.minimum(codes - dark, saturation - codes) * (1.0 / HAT_RAMP), 0.0, 1.0)


@functools.partial(jax.jit, static_argnames=("response",))
def merge_exposures(codes: Float[ArrayLike, "E H W 3"], exposures_s: Float[ArrayLike, " E"], response: str,
                    dark_code=DARK_CODE, saturation_code=SATURATION_CODE,
                    ) -> tuple[Float[Array, "H W 3"], Bool[Array, "H W 3"], Bool[Array, "H W 3"]]:
    """Merge an exposure bracket into linear radiance (code units of full scale per second).

    `codes`: raw normalised code values `E ...` (any trailing shape; PNG codes / full scale, EXR
    values as they are); `exposures_s` in seconds, in any order; `dark_code`, `saturation_code`:
    the thresholds of the images' encoding (`thresholds`). Returns (radiance, saturated, dark):
    `saturated` where even the shortest exposure is saturated (or no exposure is usable), `dark`
    where even the longest is dark; there the radiance is the bound c / t of that exposure and
    must not be used as a measurement.
    """
    codes = jnp.asarray(codes)
    exposures = jnp.asarray(exposures_s, dtype=codes.dtype)
    dark_code, saturation_code = jnp.asarray(dark_code, codes.dtype), jnp.asarray(saturation_code, codes.dtype)
    # sum_e(w * linear / t) / sum_e(w) with w = hat * t: the t cancels in the numerator. The loop
    # over the handful of exposures is unrolled: XLA fuses it into one pass over the codes, where
    # a reduction over the exposure axis is several times slower on CPU.
    numerator = jnp.zeros(codes.shape[1:], codes.dtype)
    total = jnp.zeros(codes.shape[1:], codes.dtype)
    for e in range(codes.shape[0]):
        hat = _hat(codes[e], dark_code, saturation_code)
        numerator = numerator + hat * linearize(codes[e], response)
        total = total + hat * exposures[e]
    merged = numerator / jnp.where(total > 0, total, 1.0)
    shortest, longest = jnp.argmin(exposures), jnp.argmax(exposures)
    c_short = jax.lax.dynamic_index_in_dim(codes, shortest, 0, keepdims=False)
    c_long = jax.lax.dynamic_index_in_dim(codes, longest, 0, keepdims=False)
    dark = c_long <= dark_code
    saturated = (c_short >= saturation_code) | ((total <= 0) & ~dark)
    bound = jnp.where(saturated, linearize(c_short, response) / exposures[shortest],
                      linearize(c_long, response) / exposures[longest])
    radiance = jnp.where(saturated | dark | (total <= 0), bound, merged)
    return radiance, saturated, dark


def observe(codes: Float[ArrayLike, "B E H W 3"], exposures_s: Float[ArrayLike, " E"],
            white_codes: Float[ArrayLike, "E H W 3"] | None, reflectance: Float[ArrayLike, "3"] | None, *,
            response: str, intensities: Float[ArrayLike, "B 3"] | None = None,
            levels: tuple[float, float] = (DARK_CODE, SATURATION_CODE),
            mask: Bool[ArrayLike, "H W"] | None = None) -> tuple[Float[Array, "H W B 3"], Bool[Array, "H W B"],
                                                                 Bool[Array, "H W B"], Bool[Array, "H W B"]]:
    """Observations of a batch of B lights: (ratio, valid, any channel saturated, any dark), `H W B`
    first (the layout of `Observations`).

    ratio = radiance / intensity (per light and channel) / white-board radiance * reflectance; without
    a white board (`white_codes` None) radiance / intensity. `levels`: (dark, saturation) of the
    images' encoding (`thresholds`); `mask`: texels outside it are never valid."""
    codes = jnp.asarray(codes)
    b = codes.shape[0]
    has_white = white_codes is not None
    white = jnp.asarray(white_codes) if has_white else jnp.zeros((1,) + codes.shape[1:], codes.dtype)
    refl = jnp.ones(3) if reflectance is None else jnp.asarray(reflectance)
    inten = jnp.ones((b, 3)) if intensities is None else jnp.asarray(intensities)
    inside = jnp.ones(codes.shape[2:4], bool) if mask is None else jnp.asarray(mask, bool)
    return _observe_jit(codes, jnp.asarray(exposures_s), white, refl, inten, jnp.asarray(levels[0]),
                        jnp.asarray(levels[1]), inside, response=response, has_white=has_white)


@functools.partial(jax.jit, static_argnames=("response", "has_white"))
def _observe_jit(codes, exposures_s, white_codes, reflectance, intensities, dark_code, saturation_code, inside, *,
                 response, has_white):
    dtype = codes.dtype
    exposures = exposures_s.astype(dtype)
    levels = (dark_code.astype(dtype), saturation_code.astype(dtype))
    if has_white:
        white, white_sat, white_dark = merge_exposures(white_codes.astype(dtype), exposures, response, *levels)
        white_ok = jnp.all(~white_sat & ~white_dark & (white > 0), axis=-1) & inside  # H W
        scale = jnp.reshape(reflectance.astype(dtype), (1, 1, 3)) / jnp.where(white > 0, white, 1.0)
    else:
        white_ok, scale = inside, jnp.ones((1, 1, 3), dtype)
    # Exposure axis first: the unrolled loop of merge_exposures reads strided slices, no vmap.
    radiance, saturated, dark = merge_exposures(jnp.moveaxis(codes, 1, 0), exposures, response, *levels)
    ratio = radiance * scale[None] / jnp.reshape(intensities.astype(dtype), (-1, 1, 1, 3))
    sat_any, dark_any = jnp.any(saturated, axis=-1), jnp.any(dark, axis=-1)  # B H W
    valid = ~sat_any & ~dark_any & white_ok[None]
    ratio = jnp.where(valid[..., None], ratio, 0.0)
    to_hwb = lambda x: jnp.moveaxis(x, 0, 2)  # noqa: E731
    return to_hwb(ratio), to_hwb(valid), to_hwb(sat_any), to_hwb(dark_any)


def _counts(valid: np.ndarray, saturated: np.ndarray, dark: np.ndarray) -> tuple[np.ndarray, ...]:
    return tuple(np.sum(x, axis=-1, dtype=np.int32) for x in (valid, saturated, dark))


def observations_from_batches(batches, *, size, n_lights, light_dirs, view_dir,
                              dtype=np.float32, progress=None, mask=None) -> Observations:
    """Assemble `Observations` from an iterable of (light slice, ratio H W B 3, valid, saturated,
    dark) batches (what `observe` returns), writing into preallocated numpy arrays."""
    h, w = size
    ratio = np.zeros((h, w, n_lights, 3), dtype)
    valid = np.zeros((h, w, n_lights), bool)
    saturated = np.zeros((h, w, n_lights), bool)
    dark = np.zeros((h, w, n_lights), bool)
    bar = tqdm(total=n_lights, unit="light", desc="merge", disable=None if progress is None else not progress)
    for lights, r, v, s, d in batches:
        count = lights.stop - lights.start
        ratio[:, :, lights] = np.asarray(r)[:, :, :count]
        valid[:, :, lights] = np.asarray(v)[:, :, :count]
        saturated[:, :, lights] = np.asarray(s)[:, :, :count]
        dark[:, :, lights] = np.asarray(d)[:, :, :count]
        bar.update(count)
    bar.close()
    n_valid, n_saturated, n_dark = _counts(valid, saturated, dark)
    return Observations(
        ratio=jnp.asarray(ratio), weight=jnp.asarray(valid.astype(dtype)),
        light_dirs=jnp.asarray(np.asarray(light_dirs, dtype)), view_dir=jnp.asarray(np.asarray(view_dir, dtype)),
        n_valid=jnp.asarray(n_valid), n_saturated=jnp.asarray(n_saturated), n_dark=jnp.asarray(n_dark),
        mask=None if mask is None else jnp.asarray(mask, bool))


def merge_capture(capture, *, batch: int = 64, progress: bool | None = None, workers: int = 4) -> Observations:
    """Load and merge every bracket of a validated `Capture` (see `fitting.load_capture`).

    Lights are streamed in batches of `batch` (images read by `workers` threads), each merged by
    one jitted call; the last batch is padded so there is a single compilation. `progress`:
    None = a tqdm bar on a terminal only, False = never, True = always.
    """
    h, w = capture.size
    n_lights = len(capture.light_images)
    batch = max(1, min(batch, n_lights))
    exposures = np.asarray(capture.exposures_s, np.float32)
    pool = concurrent.futures.ThreadPoolExecutor(max_workers=max(1, workers))
    prefetch = concurrent.futures.ThreadPoolExecutor(max_workers=1)  # apart from `pool`: no deadlock
    try:
        white = np.stack(list(pool.map(capture.read_codes, capture.white_images))) if capture.has_white else None
        reflectance = None if not capture.has_white else np.asarray(capture.white_reflectance, np.float32)
        intensities = np.asarray(capture.intensities(), np.float32)
        mask = capture.read_mask()

        def read_batch(start):
            paths = [p for images in capture.light_images[start:start + batch] for p in images]
            codes = np.stack(list(pool.map(capture.read_codes, paths)))
            codes = codes.reshape(-1, len(exposures), h, w, 3)
            if codes.shape[0] < batch:  # pad: one shape, one compilation
                pad = np.zeros((batch - codes.shape[0],) + codes.shape[1:], codes.dtype)
                codes = np.concatenate([codes, pad])
            return codes

        def batches():
            starts = list(range(0, n_lights, batch))
            future = prefetch.submit(read_batch, starts[0])
            for i, start in enumerate(starts):
                codes = future.result()
                if i + 1 < len(starts):  # read the next batch while this one merges
                    future = prefetch.submit(read_batch, starts[i + 1])
                inten = intensities[start:start + batch]
                inten = np.concatenate([inten, np.ones((batch - len(inten), 3), np.float32)])  # padded lights
                out = observe(codes, exposures, white, reflectance, response=capture.merge_response,
                              intensities=inten, levels=thresholds(capture.encoding, capture.saturation), mask=mask)
                yield (slice(start, min(start + batch, n_lights)), *out)

        return observations_from_batches(batches(), size=(h, w), n_lights=n_lights,
                                         light_dirs=capture.light_dirs, view_dir=capture.view_dir,
                                         progress=progress, mask=mask)
    finally:
        prefetch.shutdown(wait=True, cancel_futures=True)
        pool.shutdown(wait=True, cancel_futures=True)

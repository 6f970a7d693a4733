"""HDR merge of exposure brackets (design.md "Capture directory"): against a float64 numpy
transcription of the rule, against the known radiance, flags, and the white-board normalisation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fitting import merge_exposures
from fitting.hdr import observe

EXPOSURES = np.array([0.00025, 0.0015625, 0.008, 0.05, 0.25, 1.0])
SHUFFLE = np.array([3, 0, 5, 1, 4, 2])  # the merge must not assume sorted exposures
SAT, DARK, RAMP = 0.98, 2 / 255, 0.05  # design.md thresholds; RAMP = the hat's documented ramp

REF_TOL_F64 = 1e-12  # same formula in float64: only summation order differs
REF_TOL_F32 = 2e-6  # float32 codes/radiance: a few ulps of the weighted average


def srgb_decode(c):
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def srgb_encode(x):
    x = np.clip(np.asarray(x, np.float64), 0, 1)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def reference_merge(codes, t, response):
    """float64 transcription of design.md: weight 0 at c >= 0.98 or c <= 2/255, hat * t between."""
    codes = np.asarray(codes, np.float64)
    tt = t.reshape((-1,) + (1,) * (codes.ndim - 1))
    lin = codes if response == "linear" else srgb_decode(codes)
    usable = (codes > DARK) & (codes < SAT)
    w = np.where(usable, np.clip(np.minimum(codes - DARK, SAT - codes) / RAMP, 0, 1), 0.0) * tt
    radiance = (w * lin / tt).sum(0) / np.where(w.sum(0) > 0, w.sum(0), 1)
    saturated = codes[np.argmin(t)] >= SAT
    dark = codes[np.argmax(t)] <= DARK
    return radiance, saturated, dark, w


def bracket(radiance, t, bits, response="linear"):
    """Codes of a noiseless camera: clip(L t) (response-encoded), rounded to `bits`."""
    linear = np.clip(radiance[None] * t.reshape((-1,) + (1,) * radiance.ndim), 0, 1)
    encoded = linear if response == "linear" else srgb_encode(linear)
    levels = 2.0**bits - 1
    return np.round(encoded * levels) / levels


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(0)
    radiance = np.exp(rng.uniform(np.log(1e-3), np.log(2e4), (5, 7, 3)))
    radiance[0, 0] = 5e4  # saturated even at 1/4000 s
    radiance[0, 1] = 1e-4  # dark even at 1 s (also through the sRGB curve)
    return radiance


@pytest.mark.parametrize("response", ["linear", "srgb"])
def test_merge_matches_float64_reference(scene, response):
    t = EXPOSURES[SHUFFLE]
    codes = bracket(scene, t, 8, response)
    ref, ref_sat, ref_dark, _ = reference_merge(codes, t, response)
    assert ref_sat.sum() >= 3 and ref_dark.sum() >= 3  # the bracket exercises both flags
    valid = ~ref_sat & ~ref_dark
    for jit in (True, False):
        with jax.disable_jit(not jit):
            radiance, sat, dark = merge_exposures(jnp.asarray(codes), jnp.asarray(t), response)
        np.testing.assert_array_equal(np.asarray(sat), ref_sat)
        np.testing.assert_array_equal(np.asarray(dark), ref_dark)
        np.testing.assert_allclose(np.asarray(radiance)[valid], ref[valid], rtol=REF_TOL_F64)
    # Default float32 inputs (what images load as) give the same numbers to float32 precision.
    radiance32, _, _ = merge_exposures(jnp.asarray(codes, jnp.float32), jnp.asarray(t, jnp.float32), response)
    assert radiance32.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(radiance32)[valid], ref[valid], rtol=REF_TOL_F32)


def test_merge_recovers_the_radiance_within_quantization(scene):
    """16-bit codes: each used exposure's estimate is off by at most half a code step / t, so the
    weighted average is off by at most the weighted average of those bounds."""
    t = EXPOSURES
    codes = bracket(scene, t, 16)
    _, ref_sat, ref_dark, w = reference_merge(codes, t, "linear")
    half_step = 0.5 / 65535 / t.reshape(-1, 1, 1, 1)
    bound = (w * half_step).sum(0) / np.maximum(w.sum(0), 1e-300)
    radiance, sat, dark = merge_exposures(jnp.asarray(codes), jnp.asarray(t), "linear")
    valid = ~np.asarray(sat) & ~np.asarray(dark)
    assert valid.sum() >= 60  # ~3/4 of the log-uniform radiances lie inside the bracket
    err = np.abs(np.asarray(radiance) - scene)
    assert np.all(err[valid] <= bound[valid] * (1 + 1e-9))
    # Flagged texels: the saturated one reports the bound 0.98..1 / t_min below its true radiance,
    # the dark one a value at most 2/255 / t_max; neither is silently clipped into the valid set.
    assert sat[0, 0].all() and not dark[0, 0].any() and np.all(np.asarray(radiance)[0, 0] <= 1 / t.min())
    assert dark[0, 1].all() and not sat[0, 1].any() and np.all(np.asarray(radiance)[0, 1] <= DARK / t.max())


def test_flags_saturated_in_shortest_and_dark_in_longest():
    t = jnp.asarray([0.01, 0.1, 1.0])
    # columns: saturated in all; saturated only in the longest; dark in all; dark only in the shortest
    codes = jnp.asarray([[1.0, 0.5, 0.0, 0.0],
                         [1.0, 0.99, 0.0, 0.05],
                         [1.0, 1.0, 1 / 255, 0.5]])[:, None, :]
    radiance, sat, dark = merge_exposures(codes, t, "linear")
    np.testing.assert_array_equal(np.asarray(sat)[0], [True, False, False, False])
    np.testing.assert_array_equal(np.asarray(dark)[0], [False, False, True, False])
    # Saturated in the longest only: the valid shortest exposure alone gives 0.5 / 0.01.
    np.testing.assert_allclose(np.asarray(radiance)[0, 1], 50.0, rtol=1e-12)
    # Dark in the shortest only: hat-weighted mean of 0.05/0.1 and 0.5/1.0 (both 0.5).
    np.testing.assert_allclose(np.asarray(radiance)[0, 3], 0.5, rtol=1e-12)


def test_white_board_normalisation():
    """ratio = sample radiance / white radiance * board reflectance removes the illumination
    falloff and the camera gain per texel and channel (noise-free float codes)."""
    rng = np.random.default_rng(1)
    h, w, n_lights = 4, 6, 5
    t = EXPOSURES
    falloff = rng.uniform(0.5, 1.0, (h, w, 1))
    board = np.array([0.9, 0.8, 0.7])
    gain = 62.5
    truth = np.exp(rng.uniform(np.log(0.02), np.log(5.0), (n_lights, h, w, 3)))
    truth[2, 1, 2, 0] = 1e5  # one channel saturated even at 1/4000 s: the whole observation is invalid
    tt = t.reshape(1, -1, 1, 1, 1)
    codes = np.clip(truth[:, None] * falloff[None, None] * gain * tt, 0, 1)
    white = np.clip(board[None, None, None] * falloff[None] * gain * t.reshape(-1, 1, 1, 1), 0, 1)
    white[:, 3, 5] = 1.0  # the board itself saturated at one texel: no valid observation there
    ratio, valid, sat, dark = observe(jnp.asarray(codes), jnp.asarray(t), jnp.asarray(white), jnp.asarray(board),
                                      response="linear")
    ratio, valid = np.asarray(ratio), np.asarray(valid)
    assert ratio.shape == (h, w, n_lights, 3) and valid.shape == (h, w, n_lights)
    expected_valid = np.ones((h, w, n_lights), bool)
    expected_valid[1, 2, 2] = False
    expected_valid[3, 5, :] = False
    np.testing.assert_array_equal(valid, expected_valid)
    assert np.asarray(sat)[1, 2, 2] and not np.asarray(dark).any()
    np.testing.assert_allclose(ratio[valid], np.moveaxis(truth, 0, 2)[valid], rtol=1e-12)
    assert np.all(ratio[~valid] == 0)


def test_no_retrace_for_same_shapes():
    t = jnp.asarray(EXPOSURES)
    codes = jnp.full((6, 3, 2, 3), 0.3)
    merge_exposures(codes, t, "linear")
    before = merge_exposures._cache_size()
    for scale in (0.1, 0.2, 0.4):
        merge_exposures(codes * scale, t, "linear")
    assert merge_exposures._cache_size() == before

"""The robust fit (`fitting.fit_maps`'s default method) on synthetic captures with what real ones have.

256 texels under 96 lights within 45 deg of the view (a DiLiGenT-like rig), rendered with the
toolkit's BRDF, 1 % noise; every fit here has the same shape (chunk 256, 96 lights: one
compilation per method). Held-out lights are 48 other directions of the same cone.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fitting import FitSettings, Observations, fit_maps, paper_light_angles, paper_light_directions
from fitting.materials import estimate_materials
from jaxrender.brdf import SIGMA_FLOOR, BTFTexel, reflectance

N = 256
CHUNK = 256
ROBUST, PLAIN = FitSettings(chunk=CHUNK), FitSettings(method="plain", chunk=CHUNK)
CONE = np.flatnonzero(paper_light_angles()[:, 0] <= 45)
LIGHTS = paper_light_directions()[CONE[::12]]   # 96 lights
HELD = paper_light_directions()[CONE[6::24]]    # 48 others, between them
VIEW = np.array([0.0, 0.0, 1.0])
NOISE = 0.01

# Shadows and spurious highlights on a glossy surface: measured median normal errors 0.2-0.3 deg
# (robust) against 3-6 deg (least squares); the bound leaves 3x.
ROBUST_NORMAL_TOL_DEG = 1.0
# A matte surface with one spurious bright observation (4x) per texel: the least-squares fit tilts
# the normal to make it a mirror highlight of a sharp lobe (measured relighting error 77 % at
# lights between the measured ones); the robust fit keeps the normal (measured 0.41 deg median;
# 9.7 deg when its first round was weighted by a start fitted to the spike) and relights to 4.5 %
# (the appearance round, on every observation, still gives the spike a small broad lobe: measured
# median rho_s 0.08 against rho_d 0.3-0.6). Bounds with margin.
MATTE_NORMAL_TOL_DEG = 1.0
MATTE_RELIGHT_TOL = 0.08
CONVERGED_SLACK = 0.02   # 5 of 256 texels
MATTE_RHO_S_TOL = 0.15   # the lobe's amplitude where there is none


def _render(texels, dirs):
    one = jax.jit(jax.vmap(lambda t: jax.vmap(lambda wi: reflectance(t, wi, jnp.asarray(VIEW)))(jnp.asarray(dirs))))
    return np.asarray(one(texels))


def _texels(seed, *, rho_s, sigma):
    rng = np.random.default_rng(seed)
    tilt = np.radians(rng.uniform(0, 30, N))
    az = rng.uniform(0, 2 * np.pi, N)
    normal = np.stack([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)], -1)
    rho_d = rng.uniform(0.3, 0.6, (N, 3))
    return BTFTexel.single(jnp.asarray(rho_d), jnp.full((N, 3), rho_s), jnp.asarray(normal), jnp.full(N, sigma),
                           jnp.full(N, sigma))


def _observations(ratio):
    ratio = np.asarray(ratio, np.float32)
    valid = np.ones(ratio.shape[:2], np.float32)
    count = jnp.asarray(np.full((1, N), ratio.shape[1], np.int32))
    zero = jnp.zeros((1, N), jnp.int32)
    return Observations(ratio=jnp.asarray(ratio[None]), weight=jnp.asarray(valid[None]),
                        light_dirs=jnp.asarray(LIGHTS, jnp.float32), view_dir=jnp.asarray(VIEW, jnp.float32),
                        n_valid=count, n_saturated=zero, n_dark=zero)


def _angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1, 1)))


def _noisy(clean, seed):
    rng = np.random.default_rng(seed)
    return clean * (1 + NOISE * rng.normal(size=clean.shape))


@pytest.fixture(scope="module")
def outliers():
    """Glossy texels with a cast shadow over a 70 deg sector of light azimuths (5 % of the light
    left) and two spurious highlights (3x) each."""
    truth = _texels(1, rho_s=0.3, sigma=0.1)
    ratio = _noisy(_render(truth, LIGHTS), 2)
    rng = np.random.default_rng(3)
    light_az = np.degrees(np.arctan2(LIGHTS[:, 1], LIGHTS[:, 0]))
    for t in range(N):
        start = rng.uniform(-180, 180)
        sector = ((light_az - start) % 360) < 70
        ratio[t, sector] *= 0.05
        ratio[t, rng.choice(len(LIGHTS), 2, replace=False)] *= 3.0
    obs = _observations(ratio)
    return truth, fit_maps(obs, ROBUST, progress=False), fit_maps(obs, PLAIN, progress=False)


def test_shadows_and_highlights_are_outliers(outliers):
    truth, robust, plain = outliers
    n_true = np.asarray(truth.lobe0.normal)
    err_robust = np.median(_angle_deg(robust.normal[0], n_true))
    err_plain = np.median(_angle_deg(plain.normal[0], n_true))
    assert err_robust < ROBUST_NORMAL_TOL_DEG, (err_robust, err_plain)
    assert err_plain > 3 * err_robust, (err_robust, err_plain)   # the setting is hard for least squares
    # float32 tolerances under these outliers: measured 85 % converged within max_steps (robust) and
    # 80 % (plain); the unconverged texels' normals are as good (0.35 vs 0.34 deg median). Not worse:
    assert np.mean(robust.converged) >= np.mean(plain.converged) - CONVERGED_SLACK


@pytest.fixture(scope="module")
def matte():
    """Matte texels (no lobe) with one spurious bright observation (4x) each."""
    truth = _texels(4, rho_s=0.0, sigma=0.2)
    ratio = _noisy(_render(truth, LIGHTS), 5)
    rng = np.random.default_rng(6)
    ratio[np.arange(N), rng.integers(0, len(LIGHTS), N)] *= 4.0
    obs = _observations(ratio)
    return truth, fit_maps(obs, ROBUST, progress=False), fit_maps(obs, PLAIN, progress=False)


def _relight_error(maps, truth):
    fields = ("rho_d", "rho_s", "normal", "sigma_x", "sigma_y")
    fitted = BTFTexel.single(*(jnp.asarray(getattr(maps, k)[0], jnp.float64) for k in fields))
    pred, ref = _render(fitted, HELD), _render(truth, HELD)
    return float(np.sqrt(np.sum((pred - ref) ** 2) / np.sum(ref ** 2)))


def test_no_lobe_is_invented(matte):
    truth, robust, plain = matte
    err_robust, err_plain = _relight_error(robust, truth), _relight_error(plain, truth)
    assert np.median(_angle_deg(robust.normal[0], np.asarray(truth.lobe0.normal))) < MATTE_NORMAL_TOL_DEG
    assert err_robust < MATTE_RELIGHT_TOL, (err_robust, err_plain)
    assert err_plain > 5 * err_robust, (err_robust, err_plain)
    assert np.median(np.mean(robust.rho_s[0], -1)) < MATTE_RHO_S_TOL


def test_materials_of_two_lobes():
    """Two materials (distinct colours, a sharp and a broad lobe) in one sample: the table has a
    row for each with its slope (within 25 %: 96 lights, 1 % noise) and rho_s (within 25 %)."""
    rng = np.random.default_rng(7)
    sharp, broad = _texels(8, rho_s=0.5, sigma=0.06), _texels(9, rho_s=0.2, sigma=0.25)
    red = np.array([0.6, 0.2, 0.1]) * rng.uniform(0.9, 1.1, (N, 1))
    blue = np.array([0.1, 0.2, 0.5]) * rng.uniform(0.9, 1.1, (N, 1))
    sharp = BTFTexel.single(jnp.asarray(red), sharp.lobe0.rho_s, sharp.lobe0.normal, sharp.lobe0.sigma_x,
                            sharp.lobe0.sigma_y)
    broad = BTFTexel.single(jnp.asarray(blue), broad.lobe0.rho_s, broad.lobe0.normal, broad.lobe0.sigma_x,
                            broad.lobe0.sigma_y)
    ratio = np.concatenate([_noisy(_render(sharp, LIGHTS), 10), _noisy(_render(broad, LIGHTS), 11)])
    fits = {"normal": np.concatenate([np.asarray(sharp.lobe0.normal), np.asarray(broad.lobe0.normal)]),
            "rho_d": np.concatenate([red, blue]), "rho_s": np.full((2 * N, 3), 0.3),
            "sigma_x": np.full(2 * N, 0.1), "sigma_y": np.full(2 * N, 0.1), "n_valid": np.full(2 * N, 96)}
    table = estimate_materials(ratio, np.ones(ratio.shape[:2]), LIGHTS, VIEW, fits)
    info = table.describe()
    rows = np.isfinite(np.asarray(table.log_share))
    sigma = SIGMA_FLOOR + np.exp(np.asarray(table.s)[rows])
    rho_s = np.asarray(table.rho_s)[rows].mean(-1)
    for want_sigma, want_rho in ((0.06, 0.5), (0.25, 0.2)):
        k = np.argmin(np.abs(np.log(sigma.mean(-1) / want_sigma)))
        np.testing.assert_allclose(sigma[k], want_sigma, rtol=0.25, err_msg=str(info))
        np.testing.assert_allclose(rho_s[k], want_rho, rtol=0.25, err_msg=str(info))


@pytest.mark.parametrize("flag, method", [((), "robust"), (("--method", "plain"), "plain")])
def test_fit_command_passes_the_method(tmp_path, monkeypatch, flag, method):
    """`fitting fit --method` reaches the fit (robust by default); the fit itself is replaced here."""
    import json

    import jaxrender.app.cli.fit as fit_command
    from jaxrender.app.cli.programs import fitting_main

    seen = {}

    def fake_fit_capture(source, out, settings, **kwargs):
        seen["method"] = settings.method
        out = tmp_path / "btf"
        out.mkdir()
        (out / "btf.json").write_text(json.dumps({"fit": {}}))
        return out

    monkeypatch.setattr(fit_command, "fit_capture", fake_fit_capture)
    assert fitting_main(["fit", str(tmp_path / "capture"), "--out", str(tmp_path / "btf"), *flag]) == 0
    assert seen["method"] == method

"""The per-texel Levenberg-Marquardt fit (fitting.lm) against the truth, scipy and jaxopt.

One batch of 9 texels at 180 of the paper's light directions (a stratified subset), float64, is
fitted once per solver (module-scoped fixtures: compile time dominates). Held-out lights are 120
other directions of the paper's set.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize

from fitting.lm import (
    S_MAX,
    S_MIN,
    basis,
    fit_texels,
    geometry_to_theta,
    initial_theta,
    project_rho,
    texel_cost,
    theta_to_geometry,
)
from fitting.settings import FitSettings
from fitting.synth import paper_light_directions, stratified_light_subset
from jaxrender.brdf import SIGMA_FLOOR, BTFTexel, reflectance

# Noise of the synthetic observations: 1% multiplicative (shot noise of well-exposed HDR merges)
# plus 0.002 additive (read noise / quantization of the darkest exposure, in reflectance units).
REL_NOISE, ABS_NOISE = 0.01, 0.002
# Recovery tolerances on texels whose observations constrain the parameter. With 180 lights at 1%
# noise the estimator's spread is ~0.1 deg / ~1% (measured 0.07 deg, 0.2%); 5x that margin.
NORMAL_TOL_DEG = 0.5
SIGMA_REL_TOL = 0.05
RHO_D_ABS_TOL = 0.01
RHO_S_REL_TOL = 0.05
# Relighting error (relative RMS over held-out lights, all channels) of the fitted texel against
# the noiseless truth: the noise averages down, the fit error is ~0.3%; bound with margin.
RELIGHT_TOL = 0.02
# scipy and optimistix minimise the same objective from the same start: equal cost to 1e-4.
COST_REL_TOL = 1e-4
N_REGULAR = 5  # texels 0..4 are regular, 5..7 degenerate (plus two more built from them)

LIGHTS_ALL = paper_light_directions()
_FIT_IDS = stratified_light_subset(jax.random.key(0), 180)
_HELD_IDS = np.setdiff1d(stratified_light_subset(jax.random.key(1), 150), _FIT_IDS)[:120]
LIGHTS = jnp.asarray(LIGHTS_ALL[_FIT_IDS], jnp.float64)
HELD_OUT = jnp.asarray(LIGHTS_ALL[_HELD_IDS], jnp.float64)
VIEW = jnp.array([0.0, 0.0, 1.0])
PLAIN = FitSettings(method="plain")   # the per-texel least squares these tests hold to scipy


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


def _truth():
    # regular: tilted anisotropic, gold-like (strong coloured specular), silk-like (sheen, broad),
    # near-isotropic matte-ish, tilted along y
    normal = [_unit([0.2, -0.1, 1]), _unit([0.0, 0.15, 1]), _unit([-0.1, 0.0, 1]), _unit([0.05, 0.05, 1]),
              _unit([0.0, -0.3, 1]),
              # degenerate: purely diffuse, a single specular observation (mirror-sharp lobe seen only
              # by the light at normal incidence), and a placeholder for the all-black texel
              _unit([0.1, 0.1, 1]), [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]
    rho_d = [[0.3, 0.2, 0.1], [0.05, 0.04, 0.02], [0.4, 0.35, 0.3], [0.5, 0.5, 0.5], [0.1, 0.3, 0.2],
             [0.4, 0.3, 0.2], [0.2, 0.2, 0.2], [0.0, 0.0, 0.0]]
    rho_s = [[0.5, 0.5, 0.5], [2.0, 1.5, 0.6], [0.3, 0.3, 0.35], [0.15, 0.15, 0.15], [0.8, 0.6, 0.6],
             [0.0, 0.0, 0.0], [0.5, 0.5, 0.5], [0.0, 0.0, 0.0]]
    sx = [0.08, 0.15, 0.4, 0.2, 0.25, 0.2, 0.01, 0.2]
    sy = [0.25, 0.1, 0.15, 0.22, 0.1, 0.2, 0.01, 0.2]
    return BTFTexel.single(jnp.asarray(rho_d), jnp.asarray(rho_s), jnp.asarray(np.array(normal)),
                           jnp.asarray(sx), jnp.asarray(sy))


def _render(texels, lights):
    return jax.vmap(lambda t: jax.vmap(lambda wi: reflectance(t, wi, VIEW))(lights))(texels)


@pytest.fixture(scope="module")
def data():
    truth = _truth()
    clean = _render(truth, LIGHTS)
    rng = np.random.default_rng(4)
    noise = REL_NOISE * clean * rng.normal(size=clean.shape) + ABS_NOISE * rng.normal(size=clean.shape)
    ratio = np.array(clean + noise)
    weight = np.ones(ratio.shape[:2])
    ratio[7] = 0.0  # texel 7: all black (valid zero observations)
    ratio = np.concatenate([ratio, ratio[3:4] * 50.0])  # texel 8: a bright texel ...
    weight = np.concatenate([weight, np.zeros((1, weight.shape[1]))])  # ... saturated under every light
    truth = jax.tree_util.tree_map(lambda x: jnp.concatenate([x, x[3:4]]), truth)
    return truth, jnp.asarray(ratio), jnp.asarray(weight)


@pytest.fixture(scope="module")
def fit_optx(data):
    _, ratio, weight = data
    return fit_texels(ratio, weight, LIGHTS, VIEW, PLAIN)


@pytest.fixture(scope="module")
def fit_jaxopt(data):
    _, ratio, weight = data
    return fit_texels(ratio, weight, LIGHTS, VIEW, FitSettings(method="plain", solver="jaxopt"))


@pytest.fixture(scope="module")
def fit_native(data):
    _, ratio, weight = data
    return fit_texels(ratio, weight, LIGHTS, VIEW, FitSettings(method="plain", solver="native"))


def _angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(np.asarray(a) * np.asarray(b), -1), -1, 1)))


def test_basis_is_the_brdf():
    """rho_d a + rho_s b (the fit's linear decomposition) equals jaxrender.brdf.reflectance."""
    truth = _truth()
    for i in range(N_REGULAR):
        t = jax.tree_util.tree_map(lambda x: x[i], truth)
        ab = basis(t.lobe0.normal, t.lobe0.sigma_x, t.lobe0.sigma_y, LIGHTS, VIEW)
        pred = ab[:, :1] * t.rho_d[None, :] + ab[:, 1:] * t.lobe0.rho_s[None, :]
        ref = jax.vmap(lambda wi: reflectance(t, wi, VIEW))(LIGHTS)
        np.testing.assert_allclose(pred, ref, rtol=1e-12, atol=1e-14)  # float64, same operations


def test_theta_roundtrip_and_hemisphere():
    n = _unit([0.3, -0.2, 1.0])
    theta = geometry_to_theta(jnp.asarray(n), 0.12, 0.03)
    n2, sx, sy = theta_to_geometry(theta)
    np.testing.assert_allclose(n2, n, atol=1e-12)
    np.testing.assert_allclose([sx, sy], [0.12, 0.03], rtol=1e-12)
    # any unconstrained value maps into the upper hemisphere with floored, bounded slopes
    for th in ([1e6, -1e6, -1e3, 1e3], [0.0, 0.0, 0.0, 0.0], [-3.0, 2.0, 50.0, -50.0]):
        n, sx, sy = theta_to_geometry(jnp.asarray(th))
        assert n[2] > 0 and np.isclose(np.linalg.norm(n), 1.0)
        for s in (sx, sy):
            assert SIGMA_FLOOR < s <= SIGMA_FLOOR + np.exp(S_MAX) + 1e-12
    assert S_MIN < S_MAX


def test_projection_matches_scipy_nnls():
    """The closed-form 2-variable NNLS against scipy.optimize.nnls (per channel, weighted)."""
    rng = np.random.default_rng(0)
    for trial in range(6):
        ab = rng.uniform(0, 1, (40, 2))
        w = rng.uniform(0.2, 2.0, 40)
        # mixtures that make the unconstrained solution negative in rho_d, rho_s or neither
        coef = [[0.5, 0.3], [-0.2, 0.6], [0.4, -0.3], [-0.1, -0.1], [0.0, 0.7], [0.3, 0.0]][trial]
        ratio = ab @ np.array(coef)[:, None] * np.ones((1, 3)) + 0.01 * rng.normal(size=(40, 3))
        rho_d, rho_s = project_rho(jnp.asarray(ab), jnp.asarray(ratio.T), jnp.asarray(w), ridge=0.0)
        sw = np.sqrt(w)[:, None]
        for c in range(3):
            ref, _ = scipy.optimize.nnls(sw * ab, np.sqrt(w) * ratio[:, c])
            np.testing.assert_allclose([rho_d[c], rho_s[c]], ref, atol=1e-10)  # exact up to rounding


def test_recovers_truth(data, fit_optx):
    truth, ratio, weight = data
    f = fit_optx
    assert bool(jnp.all(f.converged[:N_REGULAR]))
    ang = _angle_deg(f.normal[:N_REGULAR], truth.lobe0.normal[:N_REGULAR])
    assert ang.max() < NORMAL_TOL_DEG, ang
    for got, ref in ((f.sigma_x, truth.lobe0.sigma_x), (f.sigma_y, truth.lobe0.sigma_y)):
        rel = np.abs(np.asarray(got[:N_REGULAR]) / np.asarray(ref[:N_REGULAR]) - 1)
        assert rel.max() < SIGMA_REL_TOL, rel
    assert np.abs(np.asarray(f.rho_d - truth.rho_d)[:N_REGULAR]).max() < RHO_D_ABS_TOL
    rel = np.abs(np.asarray(f.rho_s / truth.lobe0.rho_s)[:N_REGULAR] - 1)
    assert rel.max() < RHO_S_REL_TOL, rel
    # purely diffuse texel: rho_d and the normal are constrained, rho_s ~ 0
    assert _angle_deg(f.normal[5], truth.lobe0.normal[5]) < NORMAL_TOL_DEG
    assert np.abs(np.asarray(f.rho_d[5] - truth.rho_d[5])).max() < RHO_D_ABS_TOL
    assert np.asarray(f.rho_s[5]).max() < 0.02  # ~ noise level x 10
    # residual = RMS over valid observations ~ the noise level
    noise_rms = np.sqrt(np.mean((REL_NOISE * np.asarray(ratio[:N_REGULAR])) ** 2) + ABS_NOISE**2)
    assert np.all(np.asarray(f.residual[:N_REGULAR]) < 2 * noise_rms)


def test_relighting_held_out(data, fit_optx):
    truth, _, _ = data
    fitted = _render(fit_optx.texel(), HELD_OUT)[:N_REGULAR + 1]
    ref = _render(truth, HELD_OUT)[:N_REGULAR + 1]
    err = np.sqrt(np.sum((np.asarray(fitted - ref)) ** 2, axis=(1, 2)) / np.sum(np.asarray(ref) ** 2, axis=(1, 2)))
    assert err.max() < RELIGHT_TOL, err


def test_same_cost_as_scipy(data, fit_optx):
    """scipy.optimize.least_squares over all 10 parameters from the same start reaches the same cost."""
    _, ratio, weight = data

    def unpack(x):
        normal, sx, sy = theta_to_geometry(x[6:])
        return x[:3], x[3:6], normal, sx, sy

    @jax.jit
    def residuals(x, r, w):
        rho_d, rho_s, normal, sx, sy = unpack(x)
        from fitting.lm import texel_residuals
        return texel_residuals(rho_d, rho_s, normal, sx, sy, r, w, LIGHTS, VIEW).reshape(-1)

    for i in range(N_REGULAR):
        r, w = ratio[i], weight[i]
        th0 = initial_theta(r, w, LIGHTS, VIEW)
        n0, sx0, sy0 = theta_to_geometry(th0)
        rd0, rs0 = project_rho(basis(n0, sx0, sy0, LIGHTS, VIEW), r.T, w / jnp.mean(w))
        x0 = np.concatenate([rd0, rs0, th0])
        sol = scipy.optimize.least_squares(lambda x: np.asarray(residuals(jnp.asarray(x), r, w)), x0,
                                           ftol=1e-14, xtol=1e-14, gtol=1e-14, max_nfev=5000)
        c_scipy = float(sol.cost)
        f = jax.tree_util.tree_map(lambda x: x[i], fit_optx)
        c_ours = float(texel_cost(f.rho_d, f.rho_s, f.normal, f.sigma_x, f.sigma_y, r, w, LIGHTS, VIEW))
        np.testing.assert_allclose(c_ours, float(f.cost), rtol=1e-10)  # the reported cost is this cost
        assert abs(c_ours - c_scipy) <= COST_REL_TOL * c_scipy, (i, c_ours, c_scipy)


@pytest.mark.parametrize("other", ["fit_jaxopt", "fit_native"])
def test_other_solvers_give_the_same_fits(data, fit_optx, other, request):
    a, b = fit_optx, request.getfixturevalue(other)
    assert bool(jnp.all(b.converged[:N_REGULAR]))
    np.testing.assert_allclose(b.cost[:N_REGULAR], a.cost[:N_REGULAR], rtol=COST_REL_TOL)
    assert _angle_deg(a.normal[:N_REGULAR], b.normal[:N_REGULAR]).max() < 0.05
    np.testing.assert_allclose(b.sigma_x[:N_REGULAR], a.sigma_x[:N_REGULAR], rtol=5e-3)
    np.testing.assert_allclose(b.rho_s[:N_REGULAR], a.rho_s[:N_REGULAR], rtol=5e-3)


def test_degenerate_texels(data, fit_optx, fit_jaxopt, fit_native):
    _, ratio, weight = data
    for f in (fit_optx, fit_jaxopt, fit_native):
        for leaf in jax.tree_util.tree_leaves(f):
            assert bool(jnp.all(jnp.isfinite(leaf))), "NaN/Inf in the fit"
        # all saturated: no valid observation, nothing was fitted -> not converged, n_valid 0
        assert int(f.n_valid[8]) == 0 and not bool(f.converged[8])
        # all black (valid zeros): the fit reaches cost 0 with zero albedo, and says so
        assert float(f.cost[7]) < 1e-20 and bool(f.converged[7])
        np.testing.assert_allclose(np.concatenate([f.rho_d[7], f.rho_s[7]]), 0.0, atol=1e-12)
        # the normals stay in the upper hemisphere and slopes above the floor everywhere
        assert np.all(np.asarray(f.normal[:, 2]) > 0)
        assert np.all(np.asarray(f.sigma_x) >= SIGMA_FLOOR)
    # the converged flag is the optimistix result code (native: its own termination test): where it
    # says converged the solver stopped before max_steps at a stationary point: the cost's gradient
    # w.r.t. the solver's parameters at the fitted rho ~ 0 (central differences of texel_cost, the
    # explicit model; the small ridge on rho does not depend on theta, so this is the stationarity
    # of the solvers' objective too).
    @jax.jit
    def cost(th, rd, rs, r, w):
        n, sx, sy = theta_to_geometry(th)
        return texel_cost(rd, rs, n, sx, sy, r, w, LIGHTS, VIEW)

    for f, i in ((f, i) for f in (fit_optx, fit_native) for i in range(ratio.shape[0])):
        if not bool(f.converged[i]):
            continue
        assert int(f.num_steps[i]) <= 40   # (native may meet its test on its last allowed step)
        theta = geometry_to_theta(f.normal[i], f.sigma_x[i], f.sigma_y[i])
        h = 1e-6
        args = (f.rho_d[i], f.rho_s[i], ratio[i], weight[i])
        grad = np.array([(cost(theta + h * e, *args) - cost(theta - h * e, *args)) / (2 * h) for e in np.eye(4)])
        scale = max(float(f.cost[i]), 1e-12)
        # gradient small relative to the cost (a relative change of the cost per unit parameter)
        assert np.abs(grad).max() < 1e-3 * scale + 1e-9, (i, grad, scale)


def test_not_converged_when_out_of_steps(data):
    """With max_steps=2 the texels that need more steps report converged = 0."""
    _, ratio, weight = data
    f = fit_texels(ratio[:N_REGULAR], weight[:N_REGULAR], LIGHTS, VIEW, FitSettings(method="plain", max_steps=2))
    assert not bool(jnp.any(f.converged))
    assert np.all(np.asarray(f.num_steps) == 2)


def test_texels_independent_of_batch(data, fit_optx):
    """vmap over texels: a texel's fit does not depend on the other texels of its chunk (the
    property that makes checkpointed and resumed fits bit-identical)."""
    _, ratio, weight = data
    perm = np.array([3, 1, 8, 0, 2, 7, 6, 5, 4])
    f = fit_texels(ratio[perm], weight[perm], LIGHTS, VIEW, PLAIN)
    for name in ("rho_d", "rho_s", "normal", "sigma_x", "sigma_y", "residual", "converged"):
        np.testing.assert_array_equal(np.asarray(getattr(f, name)), np.asarray(getattr(fit_optx, name))[perm])

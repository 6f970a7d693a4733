"""The fit's one-pass Gauss-Newton kernel (fitting._varpro) against autodiff and a dense Schur complement.

float64, a stratified subset of the paper's light directions, both model forms; the references
are built from `columns` (the model) by jax.jacfwd / jax.grad and numpy linear algebra, not from
the written-out derivatives under test.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fitting._varpro import columns, columns_and_derivatives, gauss_newton, lights_of, projected_objective, ridge_of
from fitting.synth import paper_light_directions

LIGHTS = jnp.asarray(paper_light_directions()[::7])
VIEW = jnp.asarray(np.array([0.1, 0.05, 1.0]) / np.linalg.norm([0.1, 0.05, 1.0]))
THETAS = [[0.1, -0.2, np.log(0.1), np.log(0.3)], [0.3, 0.1, np.log(0.05), np.log(0.02)], [0.0, 0.0, -1.0, -1.5]]
# float64 with the same operations reordered: derivatives and matrices agree to rounding
DERIV_RTOL = 1e-10
# the gradient of the penalized objective by autodiff through the NNLS vs the kernel's envelope-theorem
# gradient: equal up to rounding of the 2 x 2 solves
GRAD_RTOL = 1e-8


def _data(theta, model, seed):
    rng = np.random.default_rng(seed)
    a, b = columns(theta, lights_of(LIGHTS, VIEW), model)
    rd, rs = jnp.array([0.3, 0.2, 0.1]), jnp.array([0.5, -0.05, 0.2])   # channel G pushes rho_s to its bound
    ratio = rd[:, None] * a[None] + rs[:, None] * b[None] + 0.01 * rng.normal(size=(3, a.shape[0]))
    return jnp.asarray(ratio), jnp.asarray(rng.uniform(0.5, 1.5, a.shape[0]))


@pytest.mark.parametrize("model", ["reciprocal", "paper"])
@pytest.mark.parametrize("k", range(len(THETAS)))
def test_derivatives_match_autodiff(model, k):
    theta = jnp.asarray(THETAS[k])
    lights = lights_of(LIGHTS, VIEW)
    a, b, da, db = columns_and_derivatives(theta, lights, model)
    ja = jax.jacfwd(lambda t: columns(t, lights, model)[0])(theta)
    jb = jax.jacfwd(lambda t: columns(t, lights, model)[1])(theta)
    a_ref, b_ref = columns(theta, lights, model)
    np.testing.assert_allclose(a, a_ref, rtol=DERIV_RTOL, atol=0)
    np.testing.assert_allclose(b, b_ref, rtol=DERIV_RTOL, atol=0)
    np.testing.assert_allclose(da, ja[:, :2].T, rtol=DERIV_RTOL, atol=1e-12)
    np.testing.assert_array_equal(ja[:, 2:], 0.0)   # a does not depend on the slopes
    np.testing.assert_allclose(db, jb.T, rtol=DERIV_RTOL, atol=1e-12 * float(jnp.max(jnp.abs(jb))))


@pytest.mark.parametrize("model", ["reciprocal", "paper"])
@pytest.mark.parametrize("k", range(len(THETAS)))
def test_gauss_newton_value_gradient_and_schur_matrix(model, k):
    theta0 = jnp.asarray(THETAS[k])
    ratio, w = _data(theta0, model, seed=k)
    theta = theta0 + 0.05
    lights = lights_of(LIGHTS, VIEW)
    gn = gauss_newton(theta, ratio, w, lights, model)
    objective, cost, rd, rs = projected_objective(theta, ratio, w, lights, model)
    np.testing.assert_allclose([gn.objective, gn.cost], [objective, cost], rtol=1e-13)
    np.testing.assert_allclose(np.concatenate([gn.rho_d, gn.rho_s]), np.concatenate([rd, rs]), rtol=1e-13)
    assert np.any(np.asarray(gn.rho_s) == 0.0)   # the bound case is exercised
    grad = jax.grad(lambda t: projected_objective(t, ratio, w, lights, model)[0])(theta)
    np.testing.assert_allclose(gn.grad, grad, rtol=GRAD_RTOL, atol=GRAD_RTOL * float(jnp.max(jnp.abs(grad))))
    # M = the Schur complement, over the free rho, of the full (rho, theta) Gauss-Newton matrix
    def full_residual(x):
        a, b = columns(x[6:], lights, model)
        return (jnp.sqrt(w)[None] * (ratio - x[:3, None] * a[None] - x[3:6, None] * b[None])).reshape(-1)

    jac = np.asarray(jax.jacfwd(full_residual)(jnp.concatenate([gn.rho_d, gn.rho_s, theta])))
    gram = jac.T @ jac
    free = np.concatenate([np.asarray(gn.rho_d) > 0, np.asarray(gn.rho_s) > 0])
    lam = float(ridge_of(w))
    a_rr = gram[:6, :6][np.ix_(free, free)] + lam * np.eye(int(free.sum()))
    a_rt = gram[:6, 6:][free]
    schur = gram[6:, 6:] - a_rt.T @ np.linalg.solve(a_rr, a_rt)
    np.testing.assert_allclose(gn.matrix, schur, rtol=DERIV_RTOL, atol=DERIV_RTOL * np.abs(schur).max())


@pytest.mark.parametrize("ambient", [0.0, 1.0])
@pytest.mark.parametrize("k", range(len(THETAS)))
def test_prior_and_ambient_against_bounded_least_squares(k, ambient):
    """With a `Prior` (rho_s pulled toward mu, log-slopes toward s_mu) and an ambient constant per
    channel projected out: the objective, the projected rho and the gradient equal a brute-force
    reference, scipy's bounded linear least squares over (rho_d >= 0, rho_s >= 0, c free) with
    the ridge and prior as extra rows, and central differences of its optimum."""
    import scipy.optimize

    from fitting._varpro import Prior

    model = "reciprocal"
    theta0 = jnp.asarray(THETAS[k])
    ratio, w = _data(theta0, model, seed=10 + k)
    ratio = ratio + 0.02   # an ambient term the centring absorbs
    theta = theta0 + 0.05
    lights = lights_of(LIGHTS, VIEW)
    prior = Prior(jnp.asarray([0.3, 0.1, 0.2]), jnp.asarray(0.5), jnp.asarray([-2.0, -1.5]), jnp.asarray(0.3))
    lam = float(ridge_of(w))

    def brute(th):
        a, b = (np.asarray(x) for x in columns(jnp.asarray(th), lights, model))
        sw = np.sqrt(np.asarray(w))
        total, rho = 0.0, []
        for c in range(3):
            rows = np.stack([sw * a, sw * b, sw * ambient], axis=1)
            rows = np.concatenate([rows, [[np.sqrt(lam), 0, 0], [0, np.sqrt(lam), 0],
                                          [0, np.sqrt(float(prior.rho_weight)), 0]]])
            rhs = np.concatenate([sw * np.asarray(ratio[c]),
                                  [0.0, 0.0, np.sqrt(float(prior.rho_weight)) * prior.rho_s[c]]])
            sol = scipy.optimize.lsq_linear(rows, rhs, bounds=([0, 0, -np.inf], [np.inf, np.inf, np.inf]),
                                            method="bvls", tol=1e-14)
            total += 0.5 * float(np.sum((rows @ sol.x - rhs) ** 2))
            rho.append(sol.x[:2])
        ds = np.asarray(th)[2:] - np.asarray(prior.s)
        return total + 0.5 * float(prior.s_weight) * float(ds @ ds), np.array(rho)

    gn = gauss_newton(theta, ratio, w, lights, model, prior, ambient=jnp.asarray(ambient))
    ref, rho = brute(theta)
    np.testing.assert_allclose(float(gn.objective), ref, rtol=1e-9)
    np.testing.assert_allclose(np.stack([gn.rho_d, gn.rho_s], 1), rho, rtol=1e-7, atol=1e-10)
    h = 1e-6
    fd = np.array([(brute(theta + h * e)[0] - brute(theta - h * e)[0]) / (2 * h) for e in np.eye(4)])
    np.testing.assert_allclose(gn.grad, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())

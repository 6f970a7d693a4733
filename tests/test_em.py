"""The EM kernel of the multi-resolution BTF (fitting.em): recovery of known mixtures, agreement
with scikit-learn's GaussianMixture, the 1-or-2-lobe rule, energy conservation, NaN safety,
vmap vs loop and jit vs no jit."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from sklearn.mixture import GaussianMixture as SkGaussianMixture

from fitting.em import (
    GaussianMixture,
    em_fit,
    em_texel,
    em_texels,
    lobe_slope_nodes,
    moment_match,
    moment_matched_texels,
    weighted_log_likelihood,
)
from jaxrender.brdf import BTFTexel, Lobe, slope_distribution

N_SAMPLES = 2000
# Sampling error of a fitted mean is sigma / sqrt(n * weight) ~ 0.12 / sqrt(800) = 0.004; 4 standard errors.
MEAN_TOLERANCE = 0.017
# Relative standard error of a variance is sqrt(2 / (n * weight)) ~ 0.05; 4 standard errors.
VARIANCE_RTOL = 0.2
# Standard error of a weight is sqrt(w (1 - w) / n) ~ 0.011; 4 standard errors.
WEIGHT_TOLERANCE = 0.045
# Both EMs run the same iteration from the same start to |change| < 1e-12; they differ only by
# sklearn's 10*eps added to each component mass and its reg_covar (1e-12) vs our floor.
SKLEARN_LOGLIK_TOLERANCE = 1e-7
SKLEARN_PARAM_TOLERANCE = 1e-5
# float64 geometry: normals and sigmas of agreeing children come back up to rounding of the
# fixed-point recentring (4 steps) and the 3x3 Gauss-Hermite second moment (exact for a Gaussian).
EXACT_TOLERANCE = 1e-6
# Two separated children lobes: the other component's responsibility leaks a little mass into
# each lobe's second moment (the lobes are 7 sigma apart): 1 %.
SEPARATED_RTOL = 1e-2
# float32 vs float64 of the same kernel on an O(1) problem.
FLOAT32_TOLERANCE = 1e-4

# One compiled EM per sample count and static settings, shared by the tests below.
em_fit_jit = jax.jit(em_fit, static_argnames=("iterations", "tol", "var_floor", "virtual"))
CONVERGED = dict(iterations=2000, tol=1e-12, var_floor=1e-12)
FIXED = dict(iterations=10, tol=0.0)


def _mixture_samples(key, n=N_SAMPLES):
    weights = np.array([0.6, 0.4])
    means = np.array([[0.3, -0.1], [-0.25, 0.2]])
    std = np.array([[0.10, 0.05], [0.06, 0.12]])
    k1, k2 = jax.random.split(key)
    comp = np.asarray(jax.random.uniform(k1, (n,)) > weights[0]).astype(int)
    z = np.asarray(jax.random.normal(k2, (n, 2), dtype=jnp.float64))
    return means[comp] + std[comp] * z, weights, means, std**2


def _init():
    return GaussianMixture(jnp.array([0.5, 0.5]), jnp.array([[0.1, 0.0], [-0.1, 0.1]]),
                           jnp.array([[0.05, 0.05], [0.05, 0.05]]))


def test_em_recovers_a_known_two_component_mixture():
    x, weights, means, variances = _mixture_samples(jax.random.PRNGKey(0))
    gmm, _, _, converged = em_fit_jit(x, np.ones(len(x)), _init(), **CONVERGED)
    assert bool(converged)
    np.testing.assert_allclose(gmm.weights, weights, atol=WEIGHT_TOLERANCE)
    np.testing.assert_allclose(gmm.means, means, atol=MEAN_TOLERANCE)
    np.testing.assert_allclose(gmm.variances, variances, rtol=VARIANCE_RTOL)


def test_em_matches_sklearn_log_likelihood():
    x, *_ = _mixture_samples(jax.random.PRNGKey(1))
    init = _init()
    gmm, loglik, _, converged = em_fit_jit(x, np.ones(len(x)), init, **CONVERGED)
    sk = SkGaussianMixture(2, covariance_type="diag", tol=1e-12, max_iter=2000, reg_covar=1e-12,
                           weights_init=np.asarray(init.weights), means_init=np.asarray(init.means),
                           precisions_init=1 / np.asarray(init.variances), random_state=0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a ConvergenceWarning would make the comparison meaningless
        sk.fit(x)
    assert bool(converged) and sk.converged_
    assert abs(float(loglik) - sk.score(x)) < SKLEARN_LOGLIK_TOLERANCE * abs(sk.score(x))
    np.testing.assert_allclose(gmm.means, sk.means_, atol=SKLEARN_PARAM_TOLERANCE)
    np.testing.assert_allclose(gmm.variances, sk.covariances_, atol=SKLEARN_PARAM_TOLERANCE)
    np.testing.assert_allclose(gmm.weights, sk.weights_, atol=SKLEARN_PARAM_TOLERANCE)


def _replicated():
    x, *_ = _mixture_samples(jax.random.PRNGKey(2), n=200)
    reps = 1 + (np.arange(len(x)) % 3)
    repeated = np.repeat(x, reps, axis=0)
    # The weighted problem is padded with zero-weight samples to the same shape (one compile).
    padded = np.concatenate([x, np.zeros((len(repeated) - len(x), 2))])
    weights = np.concatenate([reps, np.zeros(len(repeated) - len(x))]).astype(float)
    return padded, weights, repeated


def test_em_integer_weights_equal_replicated_samples_and_zero_weights_are_ignored():
    padded, weights, repeated = _replicated()
    a, la, _, _ = em_fit_jit(padded, weights, _init(), **FIXED)
    b, lb, _, _ = em_fit_jit(repeated, np.ones(len(repeated)), _init(), **FIXED)
    for u, v in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_allclose(u, v, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(la, lb, rtol=1e-12)


def test_em_jit_equals_no_jit():
    _, _, x = _replicated()
    w = np.ones(len(x))
    jitted = em_fit_jit(x, w, _init(), iterations=1, tol=0.0)
    with jax.disable_jit():
        plain = em_fit(x, w, _init(), iterations=1, tol=0.0)
    for a, b in zip(jax.tree.leaves(jitted), jax.tree.leaves(plain)):
        np.testing.assert_allclose(a, b, rtol=1e-10)


def test_grouped_em_equals_closed_form_hierarchical_em():
    """Grouped samples (Gauss-Hermite nodes of 6 Gaussians) vs hierarchical EM written with the
    closed-form expectation E_j[log N_k] = log N_k(mu_j) - sum_d v_jd / (2 v_kd) in numpy."""
    rng = np.random.default_rng(5)
    mu = rng.uniform(-0.4, 0.4, (6, 2))
    var = rng.uniform(0.002, 0.02, (6, 2))
    mass = rng.uniform(0.5, 1.5, 6)
    nodes, weights = np.polynomial.hermite.hermgauss(3)
    a, b = np.meshgrid(nodes, nodes, indexing="ij")
    q = np.outer(weights, weights).ravel() / np.pi
    x = mu[:, None, :] + np.sqrt(2 * var)[:, None, :] * np.stack([a.ravel(), b.ravel()], -1)[None]
    w = mass[:, None] * q[None, :]
    init = GaussianMixture(jnp.array([0.5, 0.5]), jnp.asarray(mu[[0, 3]]), jnp.asarray(var[[0, 3]]))
    virtual = 4.0
    gmm, _, _, _ = em_fit_jit(x, w, init, iterations=8, tol=0.0, virtual=virtual)
    pi, m, v = np.array([0.5, 0.5]), mu[[0, 3]].copy(), var[[0, 3]].copy()
    for _ in range(8):
        logn = -0.5 * np.sum(np.log(2 * np.pi * v)[None] + ((mu[:, None] - m[None]) ** 2 + var[:, None]) / v[None], -1)
        logp = virtual * logn + np.log(pi)[None]
        r = np.exp(logp - logp.max(1, keepdims=True))
        r = r / r.sum(1, keepdims=True) * mass[:, None]
        n = r.sum(0)
        pi = n / n.sum()
        m = (r.T @ mu) / n[:, None]
        v = np.einsum("jk,jkd->kd", r, (mu[:, None] - m[None]) ** 2 + var[:, None]) / n[:, None]
    np.testing.assert_allclose(gmm.weights, pi, rtol=1e-10)
    np.testing.assert_allclose(gmm.means, m, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(gmm.variances, v, rtol=1e-10)


def test_component_tangent_frame_matches_the_brdf():
    """The kernel's structure-of-arrays frame is jaxrender.brdf.tangent_frame, degenerate N = x included."""
    from fitting.em import _tangent_frame3
    from jaxrender.brdf import tangent_frame

    rng = np.random.default_rng(3)
    n = np.concatenate([rng.normal(size=(20, 3)), [[1.0, 0.0, 0.0], [0.0, 0.0, 2.0]]])
    expected = jax.jit(tangent_frame)(jnp.asarray(n))
    got = jax.jit(lambda v: _tangent_frame3(v[:, 0], v[:, 1], v[:, 2]))(jnp.asarray(n))
    for e, g in zip(expected, got):
        np.testing.assert_allclose(np.stack(g, -1), e, atol=1e-12)


def test_moment_match_is_the_one_component_maximum():
    x, *_ = _mixture_samples(jax.random.PRNGKey(4), n=200)
    w = np.linspace(0.5, 1.5, len(x))
    one = moment_match(x, w)
    loglik = jax.jit(weighted_log_likelihood)
    best = loglik(x, w, one)
    for shift in (1e-3, -1e-3):  # perturbing mean or variance can only lower the likelihood
        moved = GaussianMixture(one.weights, one.means + shift, one.variances)
        scaled = GaussianMixture(one.weights, one.means, one.variances * (1 + shift))
        assert loglik(x, w, moved) < best
        assert loglik(x, w, scaled) < best


def test_gauss_hermite_nodes_reproduce_the_slope_distribution():
    """The nodes of an untilted lobe sit at slopes with mean 0 and variance sigma^2 / 2 (D of
    eq. 1 as a Gaussian), checked against a brute-force integral of D over slope space."""
    lobe = Lobe(jnp.ones(3), jnp.array([0.0, 0.0, 1.0]), jnp.asarray(0.2), jnp.asarray(0.07))
    _, x, q = lobe_slope_nodes(lobe)
    s = np.linspace(-1.5, 1.5, 401)
    p, qq = np.meshgrid(s, s, indexing="ij")
    h = np.stack([p, qq, np.ones_like(p)], -1) / np.sqrt(p**2 + qq**2 + 1)[..., None]
    d = np.asarray(jax.jit(jax.vmap(lambda hh: slope_distribution(hh, lobe)))(
        jnp.asarray(h.reshape(-1, 3)))).reshape(p.shape)
    mass = d.sum()
    np.testing.assert_allclose(mass * (s[1] - s[0]) ** 2, np.pi * 0.2 * 0.07, rtol=1e-6)
    for axis, grid in ((0, p), (1, qq)):
        brute = (d * grid**2).sum() / mass
        np.testing.assert_allclose(np.sum(q * x[:, axis] ** 2), brute, rtol=1e-6)
        assert abs(float(np.sum(q * x[:, axis]))) < 1e-12


def _child(tilt_deg, azimuth_deg=0.0, *, sx=0.15, sy=0.1, rho_s=(0.6, 0.5, 0.4), rho_d=(0.1, 0.2, 0.3),
           dtype=jnp.float64):
    t, a = np.radians(tilt_deg), np.radians(azimuth_deg)
    n = np.array([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)])
    return BTFTexel.single(jnp.asarray(rho_d, dtype), jnp.asarray(rho_s, dtype), jnp.asarray(n, dtype),
                           jnp.asarray(sx, dtype), jnp.asarray(sy, dtype))


def _stack(children):
    return jax.tree.map(lambda *a: jnp.stack(a), *children)


def _specular_energy(texel):
    e = lambda lobe: np.pi * lobe.sigma_x * lobe.sigma_y  # noqa: E731
    return (((1 - texel.weight) * e(texel.lobe0))[..., None] * texel.lobe0.rho_s
            + (texel.weight * e(texel.lobe1))[..., None] * texel.lobe1.rho_s)


em_jit = jax.jit(em_texel)


def _em_one(children):
    """em_texel through the batched kernel (8 copies: one compile shared by these tests and test_pyramid)."""
    texel, info = em_texels(_stack([children] * 8))
    return jax.tree.map(lambda a: a[0], (texel, info))


def test_agreeing_children_give_one_lobe_not_two_copies():
    child = _child(15, 30, sx=0.2, sy=0.08)
    texel, info = _em_one(_stack([child] * 4))
    assert float(texel.weight) == 0.0 and not bool(info.two_lobes)
    for field in ("rho_s", "normal", "sigma_x", "sigma_y"):
        np.testing.assert_allclose(getattr(texel.lobe0, field), getattr(child.lobe0, field), atol=EXACT_TOLERANCE)
        np.testing.assert_allclose(getattr(texel.lobe1, field), getattr(texel.lobe0, field), atol=0)
    # Children that differ by much less than their widths (1 degree at sigma ~ 0.15) merge too.
    jittered = [_child(15 + d, 30 - d, sx=0.2, sy=0.08) for d in (-1, 0, 1, 0.5)]
    texel, info = _em_one(_stack(jittered))
    assert float(texel.weight) == 0.0 and float(info.error_one) < 0.01


@pytest.mark.parametrize("tilts, weight", [((20, -20, 20, -20), 0.5), ((25, 25, -15, 25), 0.25)])
def test_two_directions_give_two_lobes_ordered_by_weight(tilts, weight):
    # Equal energies (sigma_x sigma_y = 0.012) so that the weight is the children's count ratio.
    shape = lambda t: dict(sx=0.12, sy=0.1) if t > 0 else dict(sx=0.08, sy=0.15)  # noqa: E731
    children = [_child(t, **shape(t)) for t in tilts]
    texel, info = _em_one(_stack(children))
    assert bool(info.two_lobes)
    np.testing.assert_allclose(texel.weight, weight, rtol=SEPARATED_RTOL)
    positive, negative = children[0], next(c for c in children if float(c.lobe0.normal[0]) < 0)
    major, minor = (positive, negative) if weight < 0.5 or float(texel.lobe0.normal[0]) > 0 else (negative, positive)
    for lobe, child in ((texel.lobe0, major), (texel.lobe1, minor)):
        np.testing.assert_allclose(lobe.normal, child.lobe0.normal, atol=SEPARATED_RTOL * 0.1)
        np.testing.assert_allclose(lobe.sigma_x, child.lobe0.sigma_x, rtol=SEPARATED_RTOL)
        np.testing.assert_allclose(lobe.sigma_y, child.lobe0.sigma_y, rtol=SEPARATED_RTOL)
        np.testing.assert_allclose(lobe.rho_s, child.lobe0.rho_s, rtol=2 * SEPARATED_RTOL)
    np.testing.assert_allclose(texel.rho_d, np.mean([c.rho_d for c in children], axis=0), rtol=1e-12)


def test_specular_energy_is_conserved():
    children = _stack([_child(20, 10), _child(-15, 80, sx=0.3), _child(5, 0, rho_s=(0.1, 0.9, 0.2)),
                       _child(0, 0, sx=0.05)])
    expected = np.mean(_specular_energy(children), axis=0)
    for texel in (_em_one(children)[0], jax.tree.map(lambda a: a[0], moment_matched_texels(_stack([children] * 8)))):
        np.testing.assert_allclose(_specular_energy(texel), expected, rtol=1e-9)


def test_no_nan_for_zero_weight_zero_sigma_zero_energy():
    mirror = _child(10, sx=0.0, sy=0.0)                                  # sigma below the floor
    dark = _child(-10, rho_s=(0.0, 0.0, 0.0))                           # no specular energy
    two = BTFTexel(mirror.rho_d, mirror.lobe0, dark.lobe0, jnp.zeros((), jnp.float64))  # a lobe with weight 0
    all_dark = _stack([dark] * 4)
    for children in (_stack([mirror, dark, two, mirror]), all_dark, _stack([two] * 4)):
        texel, info = _em_one(children)
        for leaf in jax.tree.leaves((texel, info)):
            assert np.all(np.isfinite(np.asarray(leaf, dtype=float)))
    texel, _ = _em_one(all_dark)
    np.testing.assert_allclose(texel.lobe0.rho_s, 0.0, atol=1e-12)


def test_vmap_equals_loop_and_float32():
    distinct = [_stack([_child(20, 0), _child(-20, 0), _child(20, 0), _child(-20, 0)]),
                _stack([_child(10, 45)] * 4),
                _stack([_child(30, 90, sx=0.3), _child(0, 0), _child(-30, 90), _child(5, 5)]),
                _stack([_child(25, 10), _child(25, 10), _child(-15, 100, sx=0.05), _child(25, 10)])]
    batch = distinct * 2  # 8 texels: the shape test_pyramid also compiles
    vmapped, vinfo = em_texels(_stack(batch))
    for i, children in enumerate(distinct):
        single, info = em_jit(children)
        for a, b in zip(jax.tree.leaves((single, info)), jax.tree.leaves((vmapped, vinfo))):
            np.testing.assert_allclose(np.asarray(a, dtype=float), np.asarray(b[i], dtype=float), rtol=1e-10,
                                       atol=1e-12)
    # float32, in the batch of 16 texels that build_pyramid compiles for small levels.
    as32 = jax.tree.map(lambda a: a.astype(jnp.float32), _stack(batch * 2))
    t32, _ = em_texels(as32)
    assert t32.weight.dtype == jnp.float32
    for a, b in zip(jax.tree.leaves(t32), jax.tree.leaves(vmapped)):
        np.testing.assert_allclose(a[:8], b, atol=FLOAT32_TOLERANCE, rtol=FLOAT32_TOLERANCE)

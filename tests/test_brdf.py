"""The one BRDF (paper 004 eq. 1, design.md forms) against a float64 numpy transcription."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrender import brdf

_TOL = 1e-10  # float64, a few dozen operations
_FD_TOL = 1e-6  # central differences with h = 1e-6 on smooth inputs


def _reference_R(rho_d, rho_s, n, sx, sy, wi, wo, model):
    """Straight from design.md, written independently with numpy."""
    n = n / np.linalg.norm(n)
    x = np.array([1.0, 0.0, 0.0])
    t = x - (x @ n) * n
    t /= np.linalg.norm(t)
    b = np.cross(n, t)
    h = (wi + wo) / np.linalg.norm(wi + wo)
    ci, cr = wi @ n, wo @ n
    d = np.exp(-(((h @ t) / sx) ** 2 + ((h @ b) / sy) ** 2) / (h @ n) ** 2) if h @ n > 0 else 0.0
    spec = d / cr if model == "reciprocal" else d / (ci * cr)
    if ci <= 0 or cr <= 0:
        spec = 0.0
    return rho_d * max(ci, 0.0) + rho_s * spec


def _unit(theta, phi):
    return np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])


@pytest.mark.parametrize("model", brdf.MODELS)
@pytest.mark.parametrize("jit", [False, True])
def test_reflectance_matches_reference(model, jit):
    rng = np.random.default_rng(0)
    rho_d, rho_s = rng.random(3), rng.random(3)
    n = _unit(0.3, 1.1)
    texel = brdf.BTFTexel.single(jnp.asarray(rho_d), jnp.asarray(rho_s), jnp.asarray(n), jnp.array(0.15),
                                 jnp.array(0.4))
    fn = jax.jit(brdf.reflectance, static_argnames="model") if jit else brdf.reflectance
    for _ in range(20):
        wi = _unit(rng.uniform(0, 1.4), rng.uniform(0, 2 * np.pi))
        wo = _unit(rng.uniform(0, 1.4), rng.uniform(0, 2 * np.pi))
        got = np.asarray(fn(texel, jnp.asarray(wi), jnp.asarray(wo), model=model))
        np.testing.assert_allclose(got, _reference_R(rho_d, rho_s, n, 0.15, 0.4, wi, wo, model), atol=_TOL)


def test_brdf_is_reciprocal_and_vmaps():
    rng = np.random.default_rng(1)
    texel = brdf.BTFTexel.single(jnp.full(3, 0.2), jnp.full(3, 0.7), jnp.asarray(_unit(0.2, 0.5)), jnp.array(0.1),
                                 jnp.array(0.3))
    wis = jnp.asarray(np.stack([_unit(rng.uniform(0, 1.3), rng.uniform(0, 6.28)) for _ in range(16)]))
    wos = jnp.asarray(np.stack([_unit(rng.uniform(0, 1.3), rng.uniform(0, 6.28)) for _ in range(16)]))
    f = jax.vmap(lambda a, b: brdf.brdf(texel, a, b))
    np.testing.assert_allclose(f(wis, wos), f(wos, wis), rtol=1e-9)
    np.testing.assert_allclose(f(wis, wos), jnp.stack([brdf.brdf(texel, a, b) for a, b in zip(wis, wos)]), atol=_TOL)


def test_two_lobes_mix_linearly_and_weight_zero_is_one_lobe():
    lobe_a = brdf.Lobe(jnp.full(3, 0.5), jnp.asarray(_unit(0.2, 0.0)), jnp.array(0.1), jnp.array(0.2))
    lobe_b = brdf.Lobe(jnp.full(3, 0.9), jnp.asarray(_unit(0.3, 2.0)), jnp.array(0.3), jnp.array(0.1))
    wi, wo = jnp.asarray(_unit(0.4, 0.3)), jnp.asarray(_unit(0.2, 3.0))
    mixed = brdf.reflectance(brdf.BTFTexel(jnp.zeros(3), lobe_a, lobe_b, jnp.array(0.3)), wi, wo)
    only_a = brdf.reflectance(brdf.BTFTexel(jnp.zeros(3), lobe_a, lobe_a, jnp.array(0.0)), wi, wo)
    only_b = brdf.reflectance(brdf.BTFTexel(jnp.zeros(3), lobe_b, lobe_b, jnp.array(0.0)), wi, wo)
    np.testing.assert_allclose(mixed, 0.7 * only_a + 0.3 * only_b, atol=_TOL)


def test_gradients_match_central_differences_and_stay_finite():
    wi, wo = jnp.asarray(_unit(0.5, 0.2)), jnp.asarray(_unit(0.3, 2.5))

    def loss(p):
        texel = brdf.BTFTexel.single(p[0:3], p[3:6], jnp.array([p[6], p[7], 1.0]), p[8], p[9])
        return jnp.sum(brdf.reflectance(texel, wi, wo) ** 2)

    loss = jax.jit(loss)
    p = jnp.array([0.3, 0.2, 0.1, 0.6, 0.5, 0.4, 0.1, -0.05, 0.3, 0.2])
    grad = np.asarray(jax.jit(jax.grad(loss))(p))
    steps = 1e-6 * jnp.eye(p.size)
    fd = np.asarray((jax.vmap(loss)(p[None, :] + steps) - jax.vmap(loss)(p[None, :] - steps)) / 2e-6)
    np.testing.assert_allclose(grad, fd, atol=_FD_TOL, rtol=1e-5)
    # degenerate places: sigma at zero, grazing directions, normal on the x axis, weight 0
    edge = jnp.array([0.3, 0.2, 0.1, 0.6, 0.5, 0.4, 0.0, 0.0, 0.0, 0.0])
    assert np.all(np.isfinite(jax.grad(loss)(edge)))
    grazing = brdf.BTFTexel.single(jnp.ones(3), jnp.ones(3), jnp.array([1.0, 0.0, 0.0]), jnp.array(0.0), jnp.array(0.0))
    g = jax.grad(lambda w: jnp.sum(brdf.brdf(grazing, w, jnp.array([0.0, 0.0, 1.0]))))(jnp.array([1.0, 0.0, 0.0]))
    assert np.all(np.isfinite(g))

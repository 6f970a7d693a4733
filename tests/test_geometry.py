"""Ray-sphere / ray-quad intersection and closest-hit casting against numpy float64 references."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrender.geometry import (
    Quads,
    Spheres,
    cast_rays,
    closest_hit,
    intersect_quad,
    intersect_sphere,
    nearest_distance,
    occluded,
)

_TOL = 1e-9  # float64 closed forms, a few dozen operations (the quadratic loses a few digits near tangency)


def _np_sphere(o, d, c, r):
    """Smallest root t > 1e-4 of |o + t d - c| = r solved with numpy.roots."""
    roots = np.roots([d @ d, 2 * d @ (o - c), (o - c) @ (o - c) - r * r])
    roots = [x.real for x in roots if abs(x.imag) < 1e-12 and x.real > 1e-4]
    return min(roots) if roots else np.inf


def _np_quad(o, d, c, u, v):
    """Solve o + t d = c + a u + b v as a 3x3 linear system; hit when |a|, |b| <= 1 and t > 1e-4."""
    m = np.stack([d, -u, -v], axis=1)
    if abs(np.linalg.det(m)) < 1e-12:
        return np.inf
    t, a, b = np.linalg.solve(m, c - o)
    return t if (t > 1e-4 and abs(a) <= 1 and abs(b) <= 1) else np.inf


def _random_rays(n, seed):
    rng = np.random.default_rng(seed)
    o = rng.uniform(-3, 3, (n, 3))
    target = rng.uniform(-1, 1, (n, 3))
    d = target - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def test_sphere_matches_numpy_roots():
    o, d = _random_rays(200, 0)
    c, r = np.array([0.2, -0.1, 0.3]), 0.8
    got = np.asarray(jax.vmap(intersect_sphere, in_axes=(0, 0, None, None))(o, d, c, r))
    want = np.array([_np_sphere(oi, di, c, r) for oi, di in zip(o, d)])
    assert np.isinf(want).sum() > 10 and np.isfinite(want).sum() > 10  # both cases exercised
    np.testing.assert_array_equal(np.isinf(got), np.isinf(want))
    fin = np.isfinite(want)
    np.testing.assert_allclose(got[fin], want[fin], atol=_TOL)


def test_quad_matches_linear_solve_non_orthogonal():
    o, d = _random_rays(200, 1)
    c, u, v = np.array([0.1, 0.0, -0.2]), np.array([1.0, 0.2, 0.0]), np.array([0.3, 0.1, -0.9])
    got = np.asarray(jax.vmap(intersect_quad, in_axes=(0, 0, None, None, None))(o, d, c, u, v))
    want = np.array([_np_quad(oi, di, c, u, v) for oi, di in zip(o, d)])
    assert np.isinf(want).sum() > 10 and np.isfinite(want).sum() > 10
    np.testing.assert_array_equal(np.isinf(got), np.isinf(want))
    fin = np.isfinite(want)
    np.testing.assert_allclose(got[fin], want[fin], atol=_TOL)


@pytest.mark.parametrize("jit", [False, True])
def test_cast_rays_equals_loop_of_closest_hit(jit):
    o, d = _random_rays(24, 2)
    prims = (Spheres([[0.0, 0.0, 0.0], [0.5, 0.5, 0.0]], [0.6, 0.4], [[1, 0, 0], [0, 1, 0]]),
             Quads([[0.0, -0.5, 0.0]], [[2.0, 0.0, 0.0]], [[0.0, 0.0, 2.0]], [[0, 0, 1]]))
    fn = jax.jit(cast_rays) if jit else cast_rays
    t, n, a = fn(jnp.asarray(o), jnp.asarray(d), prims)
    one = jax.jit(closest_hit)
    for i in range(len(o)):
        ti, ni, ai = one(o[i], d[i], prims)
        want_t = min(_np_sphere(o[i], d[i], np.zeros(3), 0.6), _np_sphere(o[i], d[i], np.array([0.5, 0.5, 0]), 0.4),
                     _np_quad(o[i], d[i], np.array([0, -0.5, 0.0]), np.array([2.0, 0, 0]), np.array([0, 0, 2.0])))
        assert float(t[i]) == pytest.approx(want_t, abs=_TOL) if np.isfinite(want_t) else np.isinf(float(t[i]))
        np.testing.assert_allclose(t[i], ti, atol=_TOL)
        np.testing.assert_allclose(n[i], ni, atol=_TOL)
        np.testing.assert_allclose(a[i], ai, atol=_TOL)
    hit = np.isfinite(np.asarray(t))
    np.testing.assert_allclose(np.linalg.norm(np.asarray(n)[hit], axis=1), 1.0, atol=_TOL)


def test_cast_rays_with_many_primitives_equals_closest_hit():
    """Past SHORT_AXIS primitives `hit_attributes` gathers instead of selecting: 20 spheres and two
    quads against the one-ray `closest_hit` (vmapped), misses included."""
    o, d = _random_rays(300, 5)
    rng = np.random.default_rng(6)
    prims = (Spheres(rng.uniform(-1, 1, (20, 3)), rng.uniform(0.1, 0.3, 20), rng.uniform(0, 1, (20, 3))),
             Quads([[0.0, -0.5, 0.0], [0.0, 0.0, -1.0]], [[2.0, 0.0, 0.0], [1.0, 0.0, 0.0]],
                   [[0.0, 0.0, 2.0], [0.0, 1.0, 0.0]], [[0, 0, 1], [1, 1, 0]]))
    t, n, a = jax.jit(cast_rays)(jnp.asarray(o), jnp.asarray(d), prims)
    want = jax.jit(jax.vmap(closest_hit, in_axes=(0, 0, None)))(jnp.asarray(o), jnp.asarray(d), prims)
    hit = np.isfinite(np.asarray(want[0]))
    assert 10 < hit.sum() < len(o) - 10
    np.testing.assert_array_equal(np.isfinite(np.asarray(t)), hit)
    np.testing.assert_allclose(np.asarray(t)[hit], np.asarray(want[0])[hit], atol=_TOL)
    for got, ref in ((n, want[1]), (a, want[2])):
        np.testing.assert_allclose(np.asarray(got), np.asarray(ref), atol=_TOL)


@pytest.mark.parametrize("n_spheres", [3, 20])  # written-out column minimum, and jnp.min past SHORT_AXIS
def test_nearest_distance_is_numpy_minimum_and_drives_occluded(n_spheres):
    o, d = _random_rays(300, 3)
    rng = np.random.default_rng(4)
    centres, radii = rng.uniform(-1, 1, (n_spheres, 3)), rng.uniform(0.1, 0.4, n_spheres)
    quad = (np.array([0.0, -0.5, 0.0]), np.array([2.0, 0.0, 0.0]), np.array([0.0, 0.0, 2.0]))
    prims = (Spheres(centres, radii), Quads([quad[0]], [quad[1]], [quad[2]]))
    got = np.asarray(jax.jit(nearest_distance)(jnp.asarray(o), jnp.asarray(d), prims))
    want = np.array([min([_np_sphere(oi, di, c, r) for c, r in zip(centres, radii)] + [_np_quad(oi, di, *quad)])
                     for oi, di in zip(o, d)])
    assert np.isinf(want).sum() > 10 and np.isfinite(want).sum() > 10
    np.testing.assert_array_equal(np.isinf(got), np.isinf(want))
    np.testing.assert_allclose(got[np.isfinite(want)], want[np.isfinite(want)], atol=_TOL)
    # the same t as cast_rays (to float64 rounding: jitted vs eager fusion); occluded agrees with it
    np.testing.assert_allclose(got, np.asarray(cast_rays(jnp.asarray(o), jnp.asarray(d), prims)[0]), rtol=1e-12)
    fin = np.isfinite(got)
    for scale, blocked in ((1.01, 1.0), (0.99, 0.0)):
        occ = np.asarray(occluded(jnp.asarray(o[fin]), jnp.asarray(d[fin]), jnp.asarray(got[fin] * scale), prims))
        np.testing.assert_array_equal(occ, blocked)


def test_occluded_and_empty_groups():
    prims = (Spheres([[0.0, 0.0, 0.0]], [0.5]), Quads(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3))))
    o = jnp.array([[0.0, 0.0, -2.0], [0.0, 0.0, -2.0], [2.0, 0.0, -2.0]])
    d = jnp.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    got = occluded(o, d, jnp.array([5.0, 1.0, 5.0]), prims)  # blocked; stops short of the sphere; misses
    np.testing.assert_array_equal(np.asarray(got), [1.0, 0.0, 0.0])


def test_no_nan_gradients_on_miss_and_tangency():
    def loss(o):
        d = jnp.array([0.0, 0.0, 1.0])
        t_miss = intersect_sphere(o + jnp.array([5.0, 0.0, 0.0]), d, jnp.zeros(3), 1.0)
        t_tan = intersect_sphere(o + jnp.array([1.0, 0.0, 0.0]), d, jnp.zeros(3), 1.0)
        t_par = intersect_quad(o, jnp.array([1.0, 0.0, 0.0]), jnp.zeros(3), jnp.array([1.0, 0, 0]),
                               jnp.array([0, 1.0, 0]))
        safe = lambda t: jnp.where(jnp.isfinite(t), t, 0.0)  # noqa: E731
        return safe(t_miss) + safe(t_tan) + safe(t_par)

    g = jax.grad(loss)(jnp.array([0.0, 0.0, -3.0]))
    assert np.all(np.isfinite(np.asarray(g)))

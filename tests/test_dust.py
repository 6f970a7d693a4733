"""Sand dust (paper 001 eq. 7) against a float64 numpy loop reference with the same noise,
closed-form drift, and billboard sizes from the ripple heights."""

import math

import jax
import jax.numpy as jnp
import numpy as np

from sims import DustParams, advect_dust, dust_sizes, init_dust, simulate_dust

_TOL = 1e-12  # float64, a handful of operations per particle and step


def _bilinear_periodic(f, x, y):
    h, w = f.shape
    x0, y0 = math.floor(x), math.floor(y)
    fx, fy = x - x0, y - y0
    v = lambda i, j: f[i % h, j % w]  # noqa: E731
    return ((1 - fy) * ((1 - fx) * v(y0, x0) + fx * v(y0, x0 + 1))
            + fy * ((1 - fx) * v(y0 + 1, x0) + fx * v(y0 + 1, x0 + 1)))


def test_eq7_matches_loop_reference():
    key = jax.random.key(0)
    dune = np.asarray(jax.random.uniform(jax.random.key(1), (6, 9))) * 3
    xy0 = init_dust(key, 5, (6, 9))
    steps = 12
    noise = jax.random.normal(jax.random.key(2), (steps, 5, 3))
    params = DustParams(drift=0.7, lift=0.25, jitter=(0.2, 0.1, 0.05), wind_deg=30.0)
    ours = np.asarray(advect_dust(key, xy0, dune, steps=steps, params=params, noise=noise))
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    eps = np.asarray(noise)
    for p in range(5):
        x, y = map(float, np.asarray(xy0)[p])
        for t in range(steps):
            ax, ay, az = eps[t, p] * np.array([0.2, 0.1, 0.05])
            along, across = 0.7 + ax, ay
            x, y = x + c * along - s * across, y + s * along + c * across
            z = _bilinear_periodic(dune, x, y) + 0.25 + az
            np.testing.assert_allclose(ours[t, p], [x, y, z], atol=_TOL, rtol=0)


def test_drift_and_spread_statistics():
    params = DustParams(drift=0.5, lift=0.2, jitter=(0.1, 0.2, 0.0))
    flat = jnp.full((8, 8), 1.5)
    n, steps = 4000, 50
    xy0 = jnp.zeros((n, 2))
    pos = np.asarray(advect_dust(jax.random.key(3), xy0, flat, steps=steps, params=params))
    np.testing.assert_allclose(pos[..., 2], 1.7, atol=_TOL)  # z = H + dz on flat sand, no z jitter
    dx, dy = pos[-1, :, 0], pos[-1, :, 1]
    # mean advance steps * dx; std sqrt(steps) * sigma; 5 standard errors of the sample means
    assert abs(dx.mean() - 25.0) < 5 * 0.1 * math.sqrt(steps / n)
    assert abs(dy.mean()) < 5 * 0.2 * math.sqrt(steps / n)
    assert abs(dx.std() / (0.1 * math.sqrt(steps)) - 1) < 0.05
    assert abs(dy.std() / (0.2 * math.sqrt(steps)) - 1) < 0.05


def test_sizes_follow_ripple_height_and_determinism():
    ripple = jax.random.uniform(jax.random.key(4), (4, 5), minval=-1.0, maxval=2.0)
    # positions at ripple texel centres of dune cell 0 (tiling 1: one ripple field per dune cell)
    jj, ii = np.meshgrid(np.arange(5), np.arange(4))
    xy = jnp.asarray(np.stack([(jj + 0.5) / 5, (ii + 0.5) / 4], axis=-1))
    sizes = np.asarray(dust_sizes(xy, ripple, size_scale=0.8))
    r = np.asarray(ripple)
    np.testing.assert_allclose(sizes, 0.8 * (r - r.min()) / (r.max() - r.min()), atol=_TOL)
    dune = jnp.ones((8, 8))
    a = simulate_dust(jax.random.key(5), dune, ripple, n_particles=16, steps=7)
    b = simulate_dust(jax.random.key(5), dune, ripple, n_particles=16, steps=7)
    c = simulate_dust(jax.random.key(6), dune, ripple, n_particles=16, steps=7)
    assert a[0].shape == (7, 16, 3) and a[1].shape == (7, 16)
    np.testing.assert_array_equal(np.asarray(a[0]), np.asarray(b[0]))
    assert not np.allclose(np.asarray(a[0]), np.asarray(c[0]))
    assert float(jnp.min(a[1])) >= 0.0 and float(jnp.max(a[1])) <= 0.5 + _TOL

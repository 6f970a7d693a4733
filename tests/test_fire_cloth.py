"""Procedural flames and the Verlet cloth."""

import jax
import jax.numpy as jnp
import numpy as np

from sims.cloth import cloth_springs, drape_cloth, simulate_cloth
from sims.fire import fire_frames, gradient_noise, permutation_table

_STRAIN_MEAN_TOL = 0.05   # stiff structural springs: mean stretch under the garment's weight below 5 %
_ENERGY_RISE_TOL = 1e-6   # J; damped Verlet may wobble by round-off but must not gain energy
_UV_TOL = 1e-12           # the uv grid's corners are its end points, exact up to float64 rounding


def test_noise_is_zero_on_lattice_and_bounded():
    noise = jax.jit(gradient_noise)
    perm = permutation_table(jax.random.key(0))
    lattice = jnp.asarray(np.random.default_rng(0).integers(-20, 20, (50, 3)), dtype=float)
    np.testing.assert_allclose(noise(lattice, perm), 0.0, atol=1e-12)
    p = jnp.asarray(np.random.default_rng(1).uniform(-10, 10, (2000, 3)))
    n = np.asarray(noise(p, perm))
    assert np.all(np.abs(n) <= 1.1) and n.std() > 0.1
    # periodic when asked for
    per = jnp.asarray([4, 4, 4], dtype=jnp.int32)
    np.testing.assert_allclose(noise(p, perm, period=per),
                               noise(p + jnp.asarray([[4.0, -8.0, 12.0]]), perm, period=per), atol=1e-9)


def test_fire_frames_deterministic_nonnegative_and_flicker():
    a = np.asarray(fire_frames(jax.random.key(1), frames=4, height=16, width=8))
    b = np.asarray(fire_frames(jax.random.key(1), frames=4, height=16, width=8))
    c = np.asarray(fire_frames(jax.random.key(2), frames=4, height=16, width=8))
    assert a.shape == (4, 16, 8, 3)
    np.testing.assert_array_equal(a, b)
    assert np.all(a >= 0) and np.all(np.isfinite(a))
    assert not np.allclose(a, c)
    for f in range(3):  # consecutive frames differ (the flame moves)
        assert np.abs(a[f + 1] - a[f]).mean() > 0.01 * a.mean()
    # flame shape: brighter at the base (bottom rows) than at the top, warm (red >= blue)
    assert a[:, -4:].mean() > a[:, :4].mean()
    assert a[..., 0].sum() > a[..., 2].sum()


def _small_setup():
    rows, cols = 6, 5
    u, v = np.meshgrid(np.linspace(0, 1, cols), np.linspace(0, 1, rows))
    rest = np.stack([(u - 0.5) * 0.4, 1.0 - v * 0.5, np.zeros_like(u)], axis=-1)
    x0 = rest.copy()
    x0[..., 2] = 0.02 * np.sin(3 * u)  # a small out-of-plane start
    springs = cloth_springs(jnp.asarray(rest), k_structural=800.0, k_shear=200.0, k_bend=10.0)
    pinned = np.zeros((rows, cols))
    pinned[0, 0] = pinned[0, -1] = 1
    return jnp.asarray(x0.reshape(-1, 3)), springs, jnp.asarray(pinned.reshape(-1))


def test_cloth_pins_stay_energy_decays_springs_near_rest():
    x0, springs, pinned = _small_setup()
    x, xp, energy = jax.jit(lambda a, s, p: simulate_cloth(a, s, p, steps=4000, dt=5e-4, mass=0.01, damping=3.0,
                                                           record_every=200))(x0, springs, pinned)
    pins = np.asarray(pinned) > 0
    np.testing.assert_array_equal(np.asarray(x)[pins], np.asarray(x0)[pins])
    e = np.asarray(energy)
    assert np.all(np.diff(e) <= _ENERGY_RISE_TOL), e
    assert e[-1] < e[0]
    # settled: residual kinetic energy < 1e-4 J (gravitational energy of the sheet is ~1.5 J)
    v = (np.asarray(x) - np.asarray(xp)) / 5e-4
    assert 0.5 * 0.01 * np.sum(v * v) < 1e-4
    structural = np.asarray(springs.kind) == 0
    d = np.asarray(x)[np.asarray(springs.j)] - np.asarray(x)[np.asarray(springs.i)]
    strain = np.linalg.norm(d, axis=-1) / np.asarray(springs.rest) - 1
    assert np.abs(strain[structural]).mean() < _STRAIN_MEAN_TOL
    assert np.all(np.isfinite(np.asarray(x)))


def test_drape_cloth_outputs():
    m = drape_cloth(rows=8, cols=6, width=0.6, height=0.6, shoulder_span=0.3, body_radius=0.05, steps=3000)
    assert m.vertices.shape == (8, 6, 3) and m.uv.shape == (8, 6, 2) and m.triangles.shape == (2 * 7 * 5, 3)
    v = np.asarray(m.vertices)
    assert np.all(np.isfinite(v))
    # the two pinned shoulder points are 0.3 m apart at the top; everything else hangs below them
    top = v[0, [1, 4]]
    np.testing.assert_allclose(np.linalg.norm(top[0] - top[1]), 0.3, rtol=0.05)
    assert v[1:, :, 1].max() < top[:, 1].max()
    n = np.asarray(m.normals)
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-9)
    assert np.mean(n[..., 2]) > 0.3  # facing the viewer (+z) on average
    # uv spans the unit square corner to corner (two asserts: `and` between them skipped the second)
    np.testing.assert_allclose(np.asarray(m.uv[0, 0]), [0.0, 0.0], atol=_UV_TOL)
    np.testing.assert_allclose(np.asarray(m.uv[-1, -1]), [1.0, 1.0], atol=_UV_TOL)


def test_fire_quad_light_sampling_is_unbiased():
    """Textured quads sampled by emitted power: the mean estimate of sum_k L cos_y / (r^2 p_A K)
    at a point equals a brute-force integral over every texel (5 standard errors)."""
    from jaxrender.lights import QuadLights, quad_light_radiance_at, sample_quad_lights

    frames = fire_frames(jax.random.key(1), frames=4, height=16, width=8)  # same compile as above
    emission = jnp.stack([frames[0], frames[2] * 0.5])
    lights = QuadLights(jnp.asarray([[0.0, 1.0, 0.0], [1.0, 0.5, -0.5]]),
                        jnp.asarray([[0.2, 0.0, 0.0], [0.0, 0.0, 0.3]]),
                        jnp.asarray([[0.0, 0.4, 0.0], [0.0, 0.25, 0.0]]), emission)
    x = jnp.asarray([[0.3, 0.2, 1.0]])

    @jax.jit
    def estimate(key):
        s = sample_quad_lights(lights, key, 20)
        _, w = quad_light_radiance_at(s, x)
        return jnp.sum(w[0], axis=0)

    est = jax.vmap(estimate)(jax.random.split(jax.random.key(0), 3000))
    # brute force: each texel split 8 x 8, midpoint rule
    sub = 8
    truth = np.zeros(3)
    e = np.asarray(emission)
    for f in range(2):  # two quads
        c, u, v = (np.asarray(a[f]) for a in (lights.center, lights.u, lights.v))
        n = np.cross(u, v) / np.linalg.norm(np.cross(u, v))
        s = (np.arange(8 * sub) + 0.5) / (8 * sub)
        t = (np.arange(16 * sub) + 0.5) / (16 * sub)
        tt, ss = np.meshgrid(t, s, indexing="ij")
        y = c + (2 * ss - 1)[..., None] * u + (1 - 2 * tt)[..., None] * v
        d = y - np.asarray(x[0])
        r2 = np.sum(d * d, -1)
        g = np.abs(np.sum(d * n, -1)) / np.sqrt(r2) / r2
        dA = 4 * np.linalg.norm(np.cross(u, v)) / (8 * sub * 16 * sub)
        rad = e[f][(tt * 16).astype(int), (ss * 8).astype(int)]
        truth += np.sum(rad * (g * dA)[..., None], axis=(0, 1))
    mean = np.asarray(est).mean(0)
    stderr = np.asarray(est).std(0) / np.sqrt(est.shape[0])
    assert np.all(np.abs(mean - truth) < 5 * stderr + 1e-9), (mean, truth, stderr)
    assert np.all(stderr < 0.03 * truth)

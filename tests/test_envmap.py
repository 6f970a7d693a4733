"""Environment map: Mitsuba orientation, pdf normalisation, chi-square, unbiased estimator."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats
from capture_helpers import write_foreign_exr

from jaxrender.io import InputError, write_exr
from jaxrender.lights import EnvMap, env_pdf, env_radiance, envmap_direction, envmap_uv, load_envmap, sample_envmap

_H, _W = 8, 16
_PDF_TOL = 1e-9            # float64 sum of a piecewise-constant pdf over an aligned grid: round-off only
_ORIENT_TOL = 1e-4         # Mitsuba scalar_rgb evaluates in float32
_CHI2_MIN_P = 1e-3         # chi-square goodness of fit: fail only if the fit is very unlikely
_UNBIASED_SIGMAS = 5.0     # |mean - truth| within 5 standard errors of the Monte Carlo mean

_sample = jax.jit(sample_envmap, static_argnums=2)   # shared compiled kernels (compile time dominates)
_pdf = jax.jit(env_pdf)


def _test_map(h=_H, w=_W, seed=0):
    rng = np.random.default_rng(seed)
    img = rng.uniform(0.05, 1.0, (h, w, 3))
    img[1, 3] = (30.0, 25.0, 20.0)  # a sun
    img[h - 1, :] = 0.0           # a black row: never sampled
    return jnp.asarray(img)


def test_uv_direction_round_trip_and_axes():
    uv = jnp.asarray([[0.0, 0.5], [0.25, 0.5], [0.5, 0.5], [0.75, 0.5], [0.3, 0.0001], [0.3, 0.9999]])
    d = envmap_direction(uv)
    np.testing.assert_allclose(d[:4], [[0, 0, -1], [1, 0, 0], [0, 0, 1], [-1, 0, 0]], atol=1e-12)
    assert d[4, 1] > 0.999 and d[5, 1] < -0.999  # v = 0 zenith (+y), v = 1 nadir
    np.testing.assert_allclose(envmap_uv(d)[1:], uv[1:], atol=1e-9)


def test_orientation_matches_mitsuba():
    import mitsuba as mi
    mi.set_variant("scalar_rgb")
    rng = np.random.default_rng(1)
    img = rng.uniform(0.1, 2.0, (_H, _W, 3)).astype(np.float32)
    emitter = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(img)})
    env = EnvMap.from_array(jnp.asarray(img, dtype=jnp.float64))
    dirs = rng.normal(size=(40, 3))
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    ours = np.asarray(env_radiance(env, jnp.asarray(dirs), filter="mitsuba"))
    theirs = []
    for d in dirs:
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*(-d))  # Mitsuba: wi points from the sky back toward the scene
        theirs.append(np.asarray(emitter.eval(si)))
    np.testing.assert_allclose(ours, np.asarray(theirs), rtol=_ORIENT_TOL, atol=_ORIENT_TOL)
    # and the piecewise-constant lighting map agrees at texel centres away from row interpolation:
    # a map constant along each column must give Mitsuba's value at any direction's column centre.
    cols = np.repeat(img[:1], _H, axis=0)
    emitter = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(cols)})
    env = EnvMap.from_array(jnp.asarray(cols, dtype=jnp.float64))
    uv = np.stack([(np.arange(_W) + 0.5) / _W, np.full(_W, 0.37)], axis=-1)
    d = np.asarray(envmap_direction(jnp.asarray(uv)))
    ours = np.asarray(env_radiance(env, jnp.asarray(d)))
    theirs = []
    for di in d:
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*(-di))
        theirs.append(np.asarray(emitter.eval(si)))
    np.testing.assert_allclose(ours, np.asarray(theirs), rtol=_ORIENT_TOL, atol=_ORIENT_TOL)


def test_pdf_integrates_to_one():
    env = EnvMap.from_array(_test_map())
    # midpoint rule on a grid 4x finer than the texels in (phi, cos theta): pdf is constant per cell
    nu, nv = 4 * _W, 4 * _H
    u = (jnp.arange(nu, dtype=float) + 0.5) / nu
    # rows of texels are bands of theta; subdivide each band uniformly in cos(theta)
    j = jnp.arange(_H, dtype=float)
    c0, c1 = jnp.cos(jnp.pi * j / _H), jnp.cos(jnp.pi * (j + 1) / _H)
    f = (jnp.arange(4, dtype=float) + 0.5) / 4
    cos_t = (c0[:, None] + jnp.outer(c1 - c0, f)).reshape(-1)
    dcos = jnp.repeat((c0 - c1) / 4, 4)
    theta = jnp.arccos(cos_t)
    uu, tt = jnp.meshgrid(u, theta)
    d = envmap_direction(jnp.stack([uu, tt / jnp.pi], axis=-1))
    total = jnp.sum(_pdf(env, d) * dcos[:, None]) * (2 * jnp.pi / nu)
    assert abs(float(total) - 1.0) < _PDF_TOL
    assert nv == cos_t.shape[0]


def test_black_map_samples_uniformly():
    env = EnvMap.from_array(jnp.zeros((_H, _W, 3)))
    s = _sample(env, jax.random.key(0), 40000)
    np.testing.assert_allclose(s.pdf, 1 / (4 * np.pi), rtol=1e-12)
    # uniform on the sphere: mean direction ~ 0 (4 sigma of 1/sqrt(3 * 40000) per axis)
    assert np.all(np.abs(np.mean(np.asarray(s.direction), axis=0)) < 4 / np.sqrt(3 * 40000))


def test_samples_follow_pdf_chi_square():
    img = _test_map()
    env = EnvMap.from_array(img)
    n = 40000
    s = _sample(env, jax.random.key(3), n)
    # the returned pdf is the pdf evaluated at the sample
    np.testing.assert_allclose(s.pdf, _pdf(env, s.direction), rtol=1e-9)
    np.testing.assert_allclose(s.radiance, jax.jit(env_radiance)(env, s.direction), rtol=1e-12)
    # bins: each texel split in 2 along phi and 2 along cos(theta) -> expected count ~ pdf * solid angle
    uv = np.asarray(envmap_uv(s.direction))
    d = np.asarray(s.direction)
    col = np.floor(uv[:, 0] * 2 * _W).astype(int)
    row = np.clip(np.floor(uv[:, 1] * _H).astype(int), 0, _H - 1)
    c0, c1 = np.cos(np.pi * row / _H), np.cos(np.pi * (row + 1) / _H)
    half = ((c0 - d[:, 1]) / (c0 - c1) >= 0.5).astype(int)
    observed = np.zeros((_H, 2, 2 * _W))
    np.add.at(observed, (row, half, col), 1.0)
    lum = 0.2126 * img[..., 0] + 0.7152 * img[..., 1] + 0.0722 * img[..., 2]
    rows = np.arange(_H)
    omega = 2 * np.pi / _W * (np.cos(np.pi * rows / _H) - np.cos(np.pi * (rows + 1) / _H))
    p = np.asarray(lum) * omega[:, None]
    p = p / p.sum()
    expected = np.repeat(p[:, None, :], 2, axis=1).repeat(2, axis=2) / 4 * n
    keep = expected.reshape(-1) > 0
    assert observed.reshape(-1)[~keep].sum() == 0  # black texels are never drawn
    stat = scipy.stats.chisquare(observed.reshape(-1)[keep], expected.reshape(-1)[keep])
    assert stat.pvalue > _CHI2_MIN_P


def _g(d):
    # a smooth, positive, direction-dependent integrand (a cosine lobe + a constant)
    axis = jnp.asarray([0.3, 0.8, -0.52]) / jnp.linalg.norm(jnp.asarray([0.3, 0.8, -0.52]))
    return 0.2 + jnp.maximum(d @ axis, 0.0) ** 3


def test_estimator_is_unbiased_against_brute_force():
    img = _test_map()
    env = EnvMap.from_array(img)
    # brute force over every env texel: each texel subdivided 16 x 16 (midpoint in phi, cos theta)
    sub = 16
    f = (jnp.arange(sub, dtype=float) + 0.5) / sub
    j = jnp.arange(_H, dtype=float)
    c0, c1 = jnp.cos(jnp.pi * j / _H), jnp.cos(jnp.pi * (j + 1) / _H)
    cos_t = (c0[:, None] + jnp.outer(c1 - c0, f)).reshape(-1)
    dcos = jnp.repeat((c0 - c1) / sub, sub)
    u = (jnp.arange(_W * sub, dtype=float) + 0.5) / (_W * sub)
    uu, tt = jnp.meshgrid(u, jnp.arccos(cos_t) / jnp.pi)
    d = envmap_direction(jnp.stack([uu, tt], axis=-1))
    rad = img[jnp.clip((tt * _H).astype(int), 0, _H - 1), jnp.clip((uu * _W).astype(int), 0, _W - 1)]
    truth = jnp.sum(rad * (_g(d) * dcos[:, None] * (2 * jnp.pi / (_W * sub)))[..., None], axis=(0, 1))

    @jax.jit
    def estimate(key):
        s = sample_envmap(env, key, 20)
        return jnp.mean(s.radiance * (_g(s.direction) / s.pdf)[:, None], axis=0)

    keys = jax.random.split(jax.random.key(7), 4000)
    est = jax.vmap(estimate)(keys)
    mean = jnp.mean(est, axis=0)
    stderr = jnp.std(est, axis=0) / math.sqrt(est.shape[0])
    assert np.all(np.abs(np.asarray(mean - truth)) < _UNBIASED_SIGMAS * np.asarray(stderr))
    assert np.all(np.asarray(stderr) < 0.02 * np.asarray(truth))  # the test has power


def test_jit_matches_no_jit_and_is_deterministic():
    env = EnvMap.from_array(_test_map())
    a = sample_envmap(env, jax.random.key(11), 20)          # no jit
    b = _sample(env, jax.random.key(11), 20)
    np.testing.assert_allclose(a.direction, b.direction, atol=1e-12)
    c = _sample(env, jax.random.key(12), 20)
    assert not np.allclose(a.direction, c.direction)


def test_load_envmap(tmp_path):
    img = np.asarray(_test_map(), dtype=np.float32)
    write_exr(tmp_path / "sky.exr", img)
    env = load_envmap(tmp_path / "sky.exr")
    np.testing.assert_allclose(env.radiance, img, rtol=1e-6)
    bad = img.copy()
    bad[0, 0, 0] = np.nan
    write_foreign_exr(tmp_path / "nan.exr", bad)
    with pytest.raises(InputError, match="nan.exr"):
        load_envmap(tmp_path / "nan.exr")
    (tmp_path / "junk.exr").write_bytes(b"not an exr")
    with pytest.raises(InputError, match="junk.exr"):
        load_envmap(tmp_path / "junk.exr")

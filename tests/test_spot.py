"""Spot light (design.md contract / Mitsuba 3 `spot`) against an independent float64 transcription."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrender.lights import SpotLight, stack_spotlights, unstack_spotlights

_TOL = 1e-7  # float64; the falloff's polynomial arctan is accurate to 2e-7 rad (Cephes atanf)


def _frame(pos, target, up):
    z = (target - pos) / np.linalg.norm(target - pos)
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    return x, np.cross(z, x), z


def _reference(pos, target, up, cutoff_deg, beam_deg, intensity, lmap, p):
    """intensity * falloff * bilinear(light map, uv) toward p, written from design.md with numpy."""
    x, y, z = _frame(pos, target, up)
    w = p - pos
    w = w / np.linalg.norm(w)
    lx, ly, lz = w @ x, w @ y, w @ z
    cut, beam = np.radians(cutoff_deg), np.radians(beam_deg)
    if lz <= np.cos(cut):
        return np.zeros(3)
    theta = np.arccos(np.clip(lz, -1, 1))
    fall = 1.0 if theta <= beam else (cut - theta) / (cut - beam)
    u = 0.5 + 0.5 * lx / (lz * np.tan(cut))
    v = 0.5 + 0.5 * ly / (lz * np.tan(cut))
    h, wd = lmap.shape[:2]
    fx = np.clip(u * wd - 0.5, 0, wd - 1)
    fy = np.clip(v * h - 0.5, 0, h - 1)
    x0, y0 = int(np.floor(fx)), int(np.floor(fy))
    x1, y1 = min(x0 + 1, wd - 1), min(y0 + 1, h - 1)
    ax, ay = fx - x0, fy - y0
    val = (lmap[y0, x0] * (1 - ax) * (1 - ay) + lmap[y0, x1] * ax * (1 - ay)
           + lmap[y1, x0] * (1 - ax) * ay + lmap[y1, x1] * ax * ay)
    return intensity * fall * val


def _light(seed=0):
    rng = np.random.default_rng(seed)
    lmap = rng.uniform(0.1, 1.0, (5, 7, 3))
    args = dict(pos=np.array([0.3, 4.0, -0.2]), target=np.array([0.0, 0.0, 0.5]), up=np.array([0.0, 0.0, 1.0]),
                cutoff_deg=25.0, beam_deg=15.0, intensity=np.array([10.0, 20.0, 30.0]), lmap=lmap)
    light = SpotLight(args["pos"], args["target"], args["up"], 25.0, 15.0, args["intensity"], lmap)
    return light, args


@pytest.mark.parametrize("jit", [False, True])
def test_radiant_intensity_matches_reference(jit):
    light, args = _light()
    rng = np.random.default_rng(1)
    pts = np.concatenate([rng.uniform([-2, -1, -2], [2, 1, 2], (300, 3)), [[0.0, -1.0, 0.45]]])  # last ~on axis
    fn = jax.jit(lambda p: light.radiant_intensity(p)[0]) if jit else (lambda p: light.radiant_intensity(p)[0])
    got = np.asarray(fn(jnp.asarray(pts)))
    want = np.stack([_reference(p=p, **args) for p in pts])
    assert (want[:, 0] == 0).sum() > 20 and (want[:, 0] > 0).sum() > 20  # inside and outside the cone
    np.testing.assert_allclose(got, want, atol=_TOL * 30)  # 30 = largest intensity


def test_frame_is_mitsuba_look_at_and_default_beam():
    light = SpotLight([0.0, 4.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 20.0)
    x, y, z = (np.asarray(a) for a in light.frame())
    np.testing.assert_allclose(z, [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(x, np.cross([0, 0, 1], z), atol=1e-12)  # x = normalize(up x z)
    np.testing.assert_allclose(y, np.cross(z, x), atol=1e-12)
    assert float(light.beam_width_deg) == pytest.approx(15.0)  # 0.75 * cutoff, as Mitsuba


def test_uv_texel_convention():
    """A point along the local direction through texel (i, j)'s centre reads exactly that texel."""
    lmap = np.zeros((4, 6, 3))
    lmap[1, 4] = [1.0, 2.0, 3.0]
    light = SpotLight([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0], 30.0, 30.0, 1.0, lmap)
    x, y, z = (np.asarray(a) for a in light.frame())
    u, v = (4 + 0.5) / 6, (1 + 0.5) / 4
    t = np.tan(np.radians(30.0))
    local = np.array([(2 * u - 1) * t, (2 * v - 1) * t, 1.0])
    p = local[0] * x + local[1] * y + local[2] * z
    np.testing.assert_allclose(np.asarray(light.uv(light.to_local(p))), [u, v], atol=1e-12)
    val = np.asarray(light.map_value(light.uv(light.to_local(p))))
    np.testing.assert_allclose(val, [1.0, 2.0, 3.0], atol=1e-12)


def test_stacked_batch_vmap_equals_loop():
    lights = [_light(s)[0] for s in range(3)]
    stacked = stack_spotlights(lights)
    pts = jnp.asarray(np.random.default_rng(5).uniform(-1, 1, (10, 3)))
    one = jax.jit(lambda L: L.radiant_intensity(pts)[0])
    batched = jax.jit(jax.vmap(one))(stacked)
    for i, light in enumerate(unstack_spotlights(stacked)):
        np.testing.assert_allclose(batched[i], one(lights[i]), atol=1e-12)


def test_no_nan_gradient_on_axis_edge_and_at_the_light():
    light, _ = _light()

    def loss(pos, pts):
        L = SpotLight(pos, light.target, light.up, 25.0, 15.0, light.intensity, light.light_map)
        I, s, _ = L.radiant_intensity(pts)
        return jnp.sum(I) + jnp.sum(s)

    pos = light.position
    axis = np.asarray(light.frame()[2])
    edge_dir = np.cos(np.radians(25)) * axis + np.sin(np.radians(25)) * np.asarray(light.frame()[0])
    pts = jnp.stack([pos + 2.0 * axis, pos + 2.0 * edge_dir, pos, pos - axis])
    gp, gx = jax.jit(jax.grad(loss, argnums=(0, 1)))(pos, pts)
    assert np.all(np.isfinite(np.asarray(gp))) and np.all(np.isfinite(np.asarray(gx)))


ATAN_TOL = 2e-7  # Cephes atanf's polynomial: |error| < 2e-7 rad over x >= 0


@pytest.mark.parametrize("jit", [False, True])
def test_atan_nonneg_value_and_derivative_match_numpy(jit):
    """The polynomial arctan against numpy's, and its (custom) derivative against central
    differences of numpy's arctan, over the range-reduction intervals and far out."""
    from jaxrender.maths import atan_nonneg

    x = np.concatenate([np.linspace(0.0, 3.0, 301), np.geomspace(3.0, 1e4, 50)])
    f = jax.jit(atan_nonneg) if jit else atan_nonneg
    np.testing.assert_allclose(np.asarray(f(jnp.asarray(x))), np.arctan(x), atol=ATAN_TOL)
    grad = jax.vmap(jax.grad(atan_nonneg))
    grad = jax.jit(grad) if jit else grad
    h = 1e-6
    fd = (np.arctan(x + h) - np.arctan(np.maximum(x - h, 0.0))) / (x + h - np.maximum(x - h, 0.0))
    np.testing.assert_allclose(np.asarray(grad(jnp.asarray(x))), fd, rtol=1e-6, atol=1e-9)

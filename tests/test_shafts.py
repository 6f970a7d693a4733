"""Light shafts (paper 000): ray march vs. an independent float64 quadrature, plane method vs. ray
march as planes and sub-planes grow, 8-bit emulation, gradients vs. central differences, no NaN
gradients on the cone's axis and edge, jit vs. no-jit, no retracing."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrender.camera import Camera
from jaxrender.geometry import Quads, Spheres
from jaxrender.lights import SpotLight
from jaxrender.shafts import Medium, RenderSettings, ShaftsScene, cone_interval, render_planes, render_raymarch

_QUAD_TOL = 1e-4  # 600 midpoint samples inside the cone vs. 400 000 over the whole ray (kinked falloff)
_CONVERGED_TOL = 0.01  # planes 48 x 8, g per pixel, float: shadow-map texels (128^2) vs. exact shadow rays
_DEFAULT_TOL = 0.03  # paper defaults (30 x 6, tables + 15x10 mesh), float mode, vs. the ray march
_FD_RTOL = 2e-4  # float64 central differences, h = 1e-5 relative, on a smooth configuration
_EXACT = 1e-9  # same computation, float64

W, H = 24, 16


def _scene(*, width=W, height=H, sphere=True, light_map=None, eye=(0.0, 1.5, 6.0), target=(0.0, 1.0, 0.0),
           intensity=(40.0, 30.0, 20.0), position=(0.0, 4.0, 0.0), rho=1.0, kappa=0.1, K=0.003, shadow_map=128):
    cam = Camera(eye, target, (0.0, 1.0, 0.0), 40.0, width=width, height=height)
    light = SpotLight(position, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 20.0, 15.0, intensity, light_map)
    spheres = Spheres([[0.0, 1.0, 0.0]], [0.5], [[0.8, 0.7, 0.6]]) if sphere else None
    floor = Quads([[0.0, 0.0, 0.0]], [[3.0, 0.0, 0.0]], [[0.0, 0.0, -3.0]], [[0.5, 0.5, 0.5]])
    render = RenderSettings(shadow_map=shadow_map, s_min=jnp.asarray(0.5), s_max=jnp.asarray(10.0),
                            t_max=jnp.asarray(12.0))
    return ShaftsScene(cam, Medium(rho, kappa, K), [light], spheres, floor, render)


_raymarch = jax.jit(render_raymarch, static_argnames=("samples", "batch_size"))
_planes = jax.jit(render_planes, static_argnames=("planes", "subplanes", "quantize_bits", "mesh", "g_per_pixel",
                                                  "tables", "tile", "plane_chunk", "prune", "surface_shadows"))


def _rel(a, b):
    return float(jnp.linalg.norm(a - b) / jnp.linalg.norm(b))


def _quadrature_scene(**render) -> ShaftsScene:
    """One spot light, no objects: the scene of `_quadrature_inscattering`."""
    return ShaftsScene(Camera((0.5, 1.5, 5.0), (0.0, 1.5, 0.0), (0.0, 1.0, 0.0), 40.0, width=6, height=4),
                       Medium(1.3, 0.2, 0.004),
                       [SpotLight((0.0, 4.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 25.0, 15.0, (30.0, 20.0, 10.0))],
                       render=RenderSettings(s_max=jnp.asarray(8.0), **render))


def _quadrature_inscattering(scene: ShaftsScene) -> np.ndarray:
    """I_s of eq. 2 per pixel of `_quadrature_scene` by a dense float64 numpy midpoint rule (400 000
    points over the whole ray, not just the cone), written from the model's equations, not the
    renderer's code."""
    eye = np.array([0.5, 1.5, 5.0])
    dirs = np.asarray(scene.camera.primary_rays(), np.float64)
    L, axis = np.array([0.0, 4.0, 0.0]), np.array([0.0, -1.0, 0.0])
    cut, beam = np.radians(25.0), np.radians(15.0)
    rho, kappa, K = 1.3, 0.2, 0.004
    n, t_end = 400_000, 14.0
    t = (np.arange(n) + 0.5) / n * t_end
    out = np.zeros(dirs.shape[:2] + (3,))
    for row in range(dirs.shape[0]):
        for col in range(dirs.shape[1]):
            d = dirs[row, col]
            w = eye + t[:, None] * d - L
            s = np.linalg.norm(w, axis=1)
            theta = np.arccos(np.clip(w @ axis / s, -1, 1))
            fall = np.where(theta <= beam, 1.0, (cut - theta) / (cut - beam))
            fall = np.where((theta < cut) & (s <= 8.0), fall, 0.0)  # lit volume cut at the reach (s_max)
            alpha = np.arccos(np.clip(-(w / s[:, None]) @ d, -1, 1))  # 0: light travels straight at the eye
            F = K * (1 + 9 * np.cos(alpha / 2) ** 16)
            val = np.sum(fall * rho * F * np.exp(-rho * kappa * (s + t)) / s**2) * t_end / n
            out[row, col] = val * np.array([30.0, 20.0, 10.0])
    return out


def test_raymarch_matches_float64_quadrature_without_occluders():
    scene = _quadrature_scene()
    ref = _quadrature_inscattering(scene)
    np.testing.assert_allclose(np.asarray(_raymarch(scene, samples=600)), ref, rtol=_QUAD_TOL, atol=1e-12)
    assert np.count_nonzero(ref[..., 0] > 0) >= 8


def test_planes_converge_to_raymarch_as_planes_and_subplanes_grow():
    scene = _scene()
    ref = _raymarch(scene, samples=256)
    errs = []
    for n, m in ((4, 1), (12, 2), (48, 8)):
        img = _planes(scene, planes=n, subplanes=m, g_per_pixel=True, tables=False, surface_shadows="rays")
        errs.append(_rel(img, ref))
    assert errs[0] > errs[1] > errs[2], errs
    assert errs[2] < _CONVERGED_TOL, errs
    default = _planes(scene)
    assert _rel(default, ref) < _DEFAULT_TOL


def test_eight_bit_mode_frame_buffer_steps_and_error():
    scene = _scene()
    img = np.asarray(_planes(scene, quantize_bits=8))
    np.testing.assert_allclose(img * 255, np.round(img * 255), atol=1e-6)  # frame buffer in 1/255 steps
    assert img.max() <= 1.0 + 1e-12
    flt = np.asarray(_planes(scene))
    rms_levels = np.sqrt(np.mean((img - np.clip(flt, 0, 1)) ** 2)) * 255
    assert 0.0 < rms_levels < 8.0  # a few of 256 levels: the paper's 2.6 % is 6.7 levels


def test_light_map_pruning_changes_nothing():
    """Tiles and plane chunks outside the cone are skipped: same image as evaluating everything."""
    lmap = np.random.default_rng(0).uniform(0.2, 1.0, (6, 6, 3))
    scene = _scene(width=20, height=12, light_map=lmap, shadow_map=32)
    a = _planes(scene, planes=6, subplanes=2, tile=(4, 4), plane_chunk=2)
    b = _planes(scene, planes=6, subplanes=2, prune=False)
    assert float(jnp.max(a)) > 0
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=_EXACT)


@pytest.mark.parametrize("light_map", ["uniform", "textured"])
def test_pruned_gradient_equals_unpruned(light_map):
    """Reverse mode through the pruned tile loop (lax.map over tiles, lax.cond, a scan over plane
    chunks, each rematerialized): the same gradient as the one vectorized pass without pruning."""
    lmap = None if light_map == "uniform" else np.random.default_rng(0).uniform(0.2, 1.0, (6, 6, 3))
    scene = _scene(width=20, height=12, light_map=lmap, shadow_map=32)
    weights = jnp.asarray(np.random.default_rng(5).uniform(0.5, 1.5, (12, 20, 3)))

    def grad(**kw):
        loss = lambda p: jnp.sum(weights * render_planes(_with(scene, p), planes=6, subplanes=2, **kw))  # noqa: E731
        return jax.jit(jax.grad(loss))(_params(scene))

    pruned, dense = grad(tile=(4, 4), plane_chunk=2), grad(prune=False)
    for name in pruned:
        ref = np.asarray(dense[name])
        assert np.all(np.abs(ref) > 0), name  # every parameter reaches the image
        np.testing.assert_allclose(np.asarray(pruned[name]), ref, rtol=_EXACT, err_msg=name)


@pytest.mark.parametrize("jit", [False, True])
def test_cone_interval_matches_dense_sampling(jit):
    """The per-ray cone interval (pruning and ray-march bounds) against dense point sampling."""
    rng = np.random.default_rng(3)
    apex, axis, cos_c, reach = np.array([0.0, 4.0, 0.0]), np.array([0.0, -1.0, 0.0]), np.cos(np.radians(25)), 5.0
    origins = rng.uniform(-3, 3, (40, 3)) + np.array([0.0, 2.0, 0.0])
    dirs = rng.normal(size=(40, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    fn = jax.jit(cone_interval) if jit else cone_interval
    ts = np.linspace(-12, 12, 24001)
    hits = 0
    for o, d in zip(origins, dirs):
        a, b = (float(x[0]) for x in fn(jnp.asarray(o), jnp.asarray(d[None]), apex, axis, cos_c, reach))
        w = o + ts[:, None] * d - apex
        inside = (w @ axis >= np.linalg.norm(w, axis=1) * cos_c) & (np.linalg.norm(w, axis=1) <= reach)
        if inside.any():
            hits += 1
            assert abs(a - ts[inside].min()) < 2e-3 and abs(b - ts[inside].max()) < 2e-3  # grid step 1e-3
        else:
            assert b <= a + 2e-3
    assert hits >= 5


def test_no_retrace_across_scenes():
    calls = eqx.debug.assert_max_traces(lambda s: render_planes(s, planes=4, subplanes=2), max_traces=1)
    fn = jax.jit(calls)
    for k in (0.002, 0.003, 0.004):
        fn(_scene(width=8, height=6, K=k, shadow_map=32)).block_until_ready()


def _params(scene):
    light = scene.lights[0]
    return dict(rho=scene.medium.rho, kappa=scene.medium.kappa, K=scene.medium.K,
                intensity=light.intensity, position=light.position)


def _with(scene, p):
    scene = eqx.tree_at(lambda s: (s.medium.rho, s.medium.kappa, s.medium.K), scene, (p["rho"], p["kappa"], p["K"]))
    return eqx.tree_at(lambda s: (s.lights[0].intensity, s.lights[0].position), scene, (p["intensity"], p["position"]))


_RENDERERS = {
    "raymarch": lambda s: render_raymarch(s, samples=48),
    # tables=False: with tables the parameter derivative is the closed form's at the looked-up
    # coordinates by design (differs from the table's own slope by its interpolation error)
    "planes": lambda s: render_planes(s, planes=12, subplanes=2, prune=False, tables=False),
}


def _loss(method, p, scene, weights):
    return jnp.sum(weights * _RENDERERS[method](_with(scene, p)))


# module-level jitted functions: the FD test and the NaN test share their compilations
_LOSS = {m: jax.jit(lambda p, s, w, m=m: _loss(m, p, s, w)) for m in _RENDERERS}
_GRAD = {m: jax.jit(jax.grad(lambda p, s, w, m=m: _loss(m, p, s, w))) for m in _RENDERERS}


def _central_differences(loss, p0: dict, name: str) -> np.ndarray:
    """d loss / d p0[name] by float64 central differences, entry by entry."""
    base = np.asarray(p0[name], dtype=float)
    fd = np.zeros_like(base)
    for idx in np.ndindex(base.shape):
        h = 1e-5 * max(abs(base[idx]), 1.0)
        plus, minus = base.copy(), base.copy()
        plus[idx] += h
        minus[idx] -= h
        up, down = float(loss({**p0, name: jnp.asarray(plus)})), float(loss({**p0, name: jnp.asarray(minus)}))
        fd[idx] = (up - down) / (2 * h)
    return fd


@pytest.mark.parametrize("method", ["raymarch", "planes"])
def test_gradients_match_central_differences(method):
    """Smooth configuration (design.md): beam width < cutoff, no occluder (no hard shadow edge);
    the floor catches the cone, so surface shading, extinction and falloff all contribute."""
    scene = _scene(sphere=False, width=13, height=9, shadow_map=64)
    weights = jnp.asarray(np.random.default_rng(1).uniform(0.5, 1.5, (9, 13, 3)))
    p0 = _params(scene)
    grad = _GRAD[method](p0, scene, weights)
    for name in ("rho", "kappa", "K", "intensity", "position"):
        fd = _central_differences(lambda p: _LOSS[method](p, scene, weights), p0, name)
        np.testing.assert_allclose(np.asarray(grad[name]), fd, rtol=_FD_RTOL, atol=1e-8 * abs(fd).max(), err_msg=name)


@pytest.mark.parametrize("method", ["raymarch", "planes"])
def test_no_nan_in_image_gradient_on_cone_axis_and_edge(method):
    """Camera on the cone's axis looking at the light: the centre pixel's ray IS the axis, and the
    image contains the cone's edge; every pixel's gradient must be finite, for both methods."""
    # odd size (13 x 9, as the FD test: shared compilation): pixel (4, 6)'s centre ray is the axis
    scene = _scene(width=13, height=9, eye=(0.0, 0.3, 0.0), target=(0.0, 4.0, 0.0), sphere=False, shadow_map=64)
    scene = eqx.tree_at(lambda s: s.camera.up, scene, jnp.array([0.0, 0.0, 1.0]))
    cot = jnp.asarray(np.random.default_rng(2).uniform(0.5, 1.5, (9, 13, 3)))
    onehot = jnp.zeros((9, 13, 3)).at[4, 6].set(1.0)  # the pixel on the axis
    assert _LOSS[method](_params(scene), scene, onehot) > 0  # it sees the light's shaft
    for weights in (cot, onehot):
        grad = _GRAD[method](_params(scene), scene, weights)
        for name, g in grad.items():
            assert np.all(np.isfinite(np.asarray(g))), name

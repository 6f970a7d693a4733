"""The fast single-scattering method (`render_equiangular`, the default of `shafts.render`):
convergence to the ray march (exact shadow rays, uniform steps: an independent quadrature) as its
samples grow, in float64 and float32; unshadowed single scattering against an independent float64
numpy quadrature; pruning changes nothing; gradients vs. float64 central differences; no NaN
gradient on the cone's axis and edge; no retrace when light or medium values change."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_shafts import _central_differences, _params, _quadrature_inscattering, _quadrature_scene, _scene, _with

from jaxrender.shafts import render, render_equiangular, render_raymarch
from jaxrender.shafts._equiangular import map_active_runs

_SMOOTH_TOL = 3e-3  # 32 angle steps, no occluder: second-order midpoint error of the smooth integrand
_SHADOW_TOL = 0.012  # 32 steps, sphere shadow + 6x6 random light map: step error at shadow/map edges
_F32_TOL = 2e-4  # float32 vs float64 of the same method (32 samples summed, polynomial trig)
_QUAD_TOL = 1e-3  # 64 angle steps vs 400 000-point float64 midpoint rule, no shadows
_FD_RTOL = 2e-4  # float64 central differences, h = 1e-5 relative, smooth configuration
_EXACT = 1e-9  # the same computation, float64

_eq = jax.jit(render_equiangular, static_argnames=("samples", "shadow_map", "surface_shadows", "chunk", "prune",
                                                   "return_parts"))
_rm = jax.jit(render_raymarch, static_argnames=("samples", "batch_size", "return_parts"))


def _rel(a, b):
    return float(jnp.linalg.norm(a - b) / jnp.linalg.norm(b))


def _fog(scene_fn, **kw):
    """In-scattered part only (the error figure of design.md)."""
    return scene_fn(return_parts=True, **kw)[1][1]


def _map():
    return np.random.default_rng(0).uniform(0.2, 1.0, (6, 6, 3))


def test_matches_float64_quadrature_without_occluders():
    """No objects, one light: eq. 2 per pixel by a 400 000-point float64 numpy midpoint rule over
    the whole ray (`test_shafts._quadrature_inscattering`, not the renderer's code)."""
    scene = _quadrature_scene(shadow_map=64)
    ref = _quadrature_inscattering(scene)
    np.testing.assert_allclose(np.asarray(_eq(scene, samples=64, prune=False)), ref, rtol=_QUAD_TOL, atol=1e-9)
    assert np.count_nonzero(ref[..., 0] > 0) >= 8


@pytest.mark.parametrize("occluded", [False, True])
def test_converges_to_raymarch_as_samples_grow(occluded):
    """Against a 1024-sample ray march (shadow rays, exact light-map lookups)."""
    scene = _scene(width=24, height=16, sphere=occluded, light_map=_map() if occluded else None, shadow_map=512)
    ref = _fog(lambda **k: _rm(scene, samples=1024, **k))
    errs = [_rel(_fog(lambda **k: _eq(scene, samples=n, prune=False, **k))[0], ref) for n in (4, 8, 32)]
    assert errs[0] > errs[1] > errs[2], errs
    assert errs[2] < (_SHADOW_TOL if occluded else _SMOOTH_TOL), errs


def test_float32_matches_float64():
    scene64 = _scene(width=24, height=16, light_map=_map(), shadow_map=128)
    img64 = np.asarray(_eq(scene64, samples=32, shadow_map=128, prune=False))
    with jax.enable_x64(False):
        scene32 = _scene(width=24, height=16, light_map=_map(), shadow_map=128)
        img32 = jax.jit(lambda s: render_equiangular(s, samples=32, shadow_map=128, prune=False))(scene32)
        assert img32.dtype == jnp.float32
        img32 = np.asarray(img32, dtype=np.float64)
    assert np.all(np.isfinite(img32))
    assert np.linalg.norm(img32 - img64) / np.linalg.norm(img64) < _F32_TOL


def test_pruning_changes_nothing():
    scene = _scene(width=20, height=12, light_map=_map(), shadow_map=64)
    a = _eq(scene, samples=8, shadow_map=64, chunk=16)
    b = _eq(scene, samples=8, shadow_map=64, prune=False)
    assert float(jnp.max(a)) > 0
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=_EXACT)


def test_render_entry_point_dispatches_and_rejects_unknown_method():
    scene = _scene(width=8, height=6, shadow_map=32)
    got = jax.jit(lambda s: render(s, method="equiangular", samples=8, shadow_map=32, prune=False))(scene)
    np.testing.assert_allclose(np.asarray(got), np.asarray(_eq(scene, samples=8, shadow_map=32, prune=False)),
                               atol=_EXACT)
    with pytest.raises(ValueError, match="unknown shafts method"):
        render(scene, method="magic")


def test_no_retrace_when_light_or_medium_values_change():
    calls = eqx.debug.assert_max_traces(lambda s: render_equiangular(s, samples=4, shadow_map=32, chunk=16),
                                        max_traces=1)
    fn = jax.jit(calls)
    for k, rho, pos in ((0.002, 1.0, (0.0, 4.0, 0.0)), (0.003, 1.2, (0.3, 4.2, 0.1)), (0.004, 0.8, (-0.2, 3.9, 0.0))):
        fn(_scene(width=8, height=6, K=k, rho=rho, position=pos, intensity=(10.0 * rho, 5.0, 3.0),
                  shadow_map=32)).block_until_ready()


def _loss(p, scene, weights):
    return jnp.sum(weights * render_equiangular(_with(scene, p), samples=12, shadow_map=64, prune=False))


_LOSS = jax.jit(_loss)
_GRAD = jax.jit(jax.grad(_loss))


def test_gradients_match_central_differences():
    """Smooth configuration (design.md): beam width < cutoff, no occluder; the floor catches the
    cone, so surface shading, extinction and falloff all contribute."""
    scene = _scene(sphere=False, width=13, height=9, shadow_map=64)
    weights = jnp.asarray(np.random.default_rng(1).uniform(0.5, 1.5, (9, 13, 3)))
    p0 = _params(scene)
    grad = _GRAD(p0, scene, weights)
    for name in ("rho", "kappa", "K", "intensity", "position"):
        fd = _central_differences(lambda p: _LOSS(p, scene, weights), p0, name)
        assert np.all(np.abs(fd) > 0), name
        np.testing.assert_allclose(np.asarray(grad[name]), fd, rtol=_FD_RTOL, atol=1e-8 * abs(fd).max(), err_msg=name)


def test_no_nan_in_image_gradient_on_cone_axis_and_edge():
    """Camera on the cone's axis looking at the light: the centre pixel's ray IS the axis and
    passes through the light (h = 0); the image contains the cone's edge."""
    scene = _scene(width=13, height=9, eye=(0.0, 0.3, 0.0), target=(0.0, 4.0, 0.0), sphere=False, shadow_map=64)
    scene = eqx.tree_at(lambda s: s.camera.up, scene, jnp.array([0.0, 0.0, 1.0]))
    cot = jnp.asarray(np.random.default_rng(2).uniform(0.5, 1.5, (9, 13, 3)))
    onehot = jnp.zeros((9, 13, 3)).at[4, 6].set(1.0)
    assert _LOSS(_params(scene), scene, onehot) > 0
    for weights in (cot, onehot):
        grad = _GRAD(_params(scene), scene, weights)
        for name, g in grad.items():
            assert np.all(np.isfinite(np.asarray(g))), name


def test_pruned_gradient_equals_dense_gradient():
    """The compacted evaluation (`active_rays_map`: gather, chunks under cond, scatter back) is
    differentiated like the dense one: same gradients w.r.t. every parameter."""
    scene = _scene(sphere=False, width=13, height=9, shadow_map=64)
    weights = jnp.asarray(np.random.default_rng(3).uniform(0.5, 1.5, (9, 13, 3)))

    def loss(p, prune):
        return jnp.sum(weights * render_equiangular(_with(scene, p), samples=12, shadow_map=64, prune=prune, chunk=16))

    dense = jax.grad(loss)(_params(scene), False)
    pruned = jax.jit(jax.grad(loss), static_argnums=1)(_params(scene), True)
    for name in dense:
        np.testing.assert_allclose(np.asarray(pruned[name]), np.asarray(dense[name]), rtol=1e-9, err_msg=name)


def test_chunk_loop_pulls_back_exactly_what_is_differentiated():
    """The chunk loop's written-out reverse pass (`map_active_runs`) pulls back only the inputs
    being differentiated: the chunks' rows, a value they close over, the buffer they add into,
    each alone and all at once, equal the gradients of the same sum written densely (the buffer's
    too when nothing the chunks read is differentiated)."""
    rng = np.random.default_rng(5)
    rows, const, into, weights = (jnp.asarray(rng.normal(size=s)) for s in ((10, 4), (4,), (10, 4), (10, 4)))
    active = jnp.asarray(rng.uniform(size=10) < 0.6)
    assert 0 < int(active.sum()) < 10

    def chunked(rows, const, into):
        def fn(valid, r):
            return jnp.where(valid[:, None], jnp.sin(r) * const[None], 0.0)

        return jnp.sum(weights * map_active_runs(fn, active, (rows,), chunk_runs=3, into=into))

    def dense(rows, const, into):
        return jnp.sum(weights * (into + jnp.where(active[:, None], jnp.sin(rows) * const[None], 0.0)))

    for argnums in ((0,), (1,), (2,), (0, 1, 2)):
        got, want = jax.grad(chunked, argnums)(rows, const, into), jax.grad(dense, argnums)(rows, const, into)
        for k, g, w in zip(argnums, got, want):
            np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=_EXACT, atol=_EXACT, err_msg=str(k))


def test_lit_surfaces_equal_every_point_and_their_gradients():
    """The surfaces' pass evaluates each light only on the runs of pixels inside its cone
    (`lit_surfaces`): the same image and gradients as every pixel (`surface_term`), with a light
    map, a light whose cone misses the view, a last run cut by the image's end (60 x 39 pixels, runs
    of 7: a run wholly in the falloff's outer ring must still be evaluated) and chunks smaller than
    the lit runs."""
    from jaxrender.shafts._equiangular import MAP_DETAIL, lit_surfaces, pixel_angle, primary_hits
    from jaxrender.shafts._model import surface_light, surface_radiance, surface_term
    from jaxrender.shafts._raymarch import surface_visibility
    from jaxrender.shafts._scene import shadow_maps

    base = _scene(width=60, height=39, light_map=_map(), shadow_map=64)
    away = eqx.tree_at(lambda light: light.target, base.lights[0], jnp.asarray([0.0, 8.0, -3.0]))
    scene = eqx.tree_at(lambda s: s.lights, base, [base.lights[0], away])
    weights = jnp.asarray(np.random.default_rng(5).uniform(0.5, 1.5, (39, 60, 3)))

    def surfaces(p, compact):
        s = _with(scene, p)
        _, t, normals, albedo, points = primary_hits(s)
        visibility = surface_visibility(s, shadow_maps(s, resolution=64), "map")
        footprint = pixel_angle(s) * jnp.where(jnp.isfinite(t), t, 0.0) / MAP_DETAIL
        if not compact:
            return surface_term(s, points, normals, albedo, t, visibility, footprint=footprint)
        lit = lit_surfaces(s, points, normals, jnp.isfinite(t), footprint,
                           lambda i, *a, **k: surface_light(s, i, *a, visibility=visibility, **k), chunk=28,
                           block=7)
        return surface_radiance(s, albedo, t, lit)

    p0 = _params(scene)
    dense, compact = surfaces(p0, False), jax.jit(surfaces, static_argnums=1)(p0, True)
    assert float(jnp.max(dense)) > 0 and float(jnp.mean(dense > 0)) < 0.9   # lit and unlit pixels
    np.testing.assert_allclose(np.asarray(compact), np.asarray(dense), rtol=_EXACT, atol=_EXACT * float(dense.max()))
    grads = [jax.grad(lambda p, c=c: jnp.sum(weights * surfaces(p, c)))(p0) for c in (False, True)]
    for name in p0:
        np.testing.assert_allclose(np.asarray(grads[1][name]), np.asarray(grads[0][name]), rtol=1e-9,
                                   atol=1e-12, err_msg=name)

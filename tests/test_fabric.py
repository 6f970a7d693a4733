"""Fabric shading: NaN safety, gradients vs float64 central differences, mip selection,
level blending of shading results, and the rasterizer vs a brute-force ray caster."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxrender.brdf import BTFTexel, Lobe
from jaxrender.camera import Camera
from jaxrender.fabric import (
    camera_pinhole,
    mip_level,
    raster_window,
    rasterize,
    shade_fabric,
    shade_samples,
    stack_materials,
)

_GRAD_RTOL = 1e-5     # float64 central differences with h = 1e-6 on a smooth configuration
_GRAD_ATOL = 1e-8
_MIP_TOL = 1e-9       # exact arithmetic on an affine mapping, float64
_DEPTH_TOL = 1e-9     # two float64 ray-triangle intersections of the same ray


def _texel(n=1, *, two=True, sigma=0.2, weight=0.3):
    rng = np.random.default_rng(0)
    normal0 = np.tile([0.1, -0.05, 1.0], (n, 1))
    normal1 = np.tile([-0.3, 0.2, 1.0], (n, 1))
    l0 = Lobe(jnp.asarray(rng.uniform(0.2, 0.8, (n, 3))),
              jnp.asarray(normal0 / np.linalg.norm(normal0, axis=-1, keepdims=True)),
              jnp.full((n,), sigma), jnp.full((n,), 1.5 * sigma))
    l1 = Lobe(jnp.asarray(rng.uniform(0.2, 0.8, (n, 3))),
              jnp.asarray(normal1 / np.linalg.norm(normal1, axis=-1, keepdims=True)),
              jnp.full((n,), 1.3 * sigma), jnp.full((n,), 0.8 * sigma))
    return BTFTexel(jnp.asarray(rng.uniform(0.05, 0.5, (n, 3))), l0, l1, jnp.full((n,), weight if two else 0.0))


def _dirs(k, seed=1, z_min=0.2):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(k, 3))
    d[:, 2] = np.abs(d[:, 2]) + z_min
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def _frame(n):
    return jnp.tile(jnp.eye(3)[None], (n, 1, 1))


def test_no_nan_grazing_zero_sigma_zero_weight():
    k = 6
    wi = np.stack([[1.0, 0.0, 0.0], [0.0, 1.0, 1e-9], [0.0, 0.6, -0.8], [0.6, 0.0, 0.8], [0.0, 0.0, 1.0],
                   [-0.999999, 0.0, 0.00141]])
    wo_cases = [np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), np.array([0.6, 0.0, 0.8])]
    def loss(t, wo):
        out = shade_samples(t, _frame(1), wo[None], jnp.asarray(wi)[None], jnp.ones((1, k, 3)))
        return jnp.sum(out)

    value_and_grad = jax.jit(jax.value_and_grad(loss))
    for sigma, weight in [(1e-9, 0.0), (1e-9, 1.0), (0.2, 0.0), (0.0, 0.5)]:
        for wo in wo_cases:
            t = _texel(sigma=sigma, weight=weight)
            value, grads = value_and_grad(t, jnp.asarray(wo))
            assert np.isfinite(float(value))
            assert all(np.all(np.isfinite(np.asarray(g))) for g in jax.tree_util.tree_leaves(grads))


def _one_material(levels):
    return stack_materials([levels])


def test_gradient_of_rendered_pixel_matches_central_differences():
    # a two-level pyramid (2x2 two-lobe texels, then 1x1), a pixel between the levels (lambda = 0.4)
    lvl0 = jax.tree_util.tree_map(lambda a: a.reshape((2, 2) + a.shape[1:]), _texel(4))
    lvl1 = jax.tree_util.tree_map(lambda a: a[:1].reshape((1, 1) + a.shape[1:]), _texel(1, weight=0.6))
    wi = jnp.asarray(_dirs(4))[None]
    wo = jnp.asarray(_dirs(1, seed=5))
    weight = jnp.asarray(np.random.default_rng(2).uniform(0.5, 1.5, (1, 4, 3)))
    uv = jnp.asarray([[0.3, 0.7]])
    dx = jnp.asarray([[2 ** 0.4 / 2, 0.0]])   # one pixel step = 2^0.4 texels of a 2x2 level
    dy = jnp.asarray([[0.0, 0.5 / 2]])

    @jax.jit
    def pixel(t0, t1):
        mats = _one_material([t0, t1])
        return jnp.sum(shade_fabric(mats, jnp.zeros((1,), jnp.int32), uv, dx, dy, _frame(1), wo, wi, weight))

    grads = jax.jit(jax.grad(pixel, argnums=(0, 1)))(lvl0, lvl1)
    # directional derivatives along random directions in the space of ALL parameters of both
    # levels (the check_grads approach): g . v vs (f(x + h v) - f(x - h v)) / 2h
    from jax.flatten_util import ravel_pytree

    x, unravel = ravel_pytree((lvl0, lvl1))
    g, _ = ravel_pytree(grads)
    f = jax.jit(lambda flat: pixel(*unravel(flat)))
    rng = np.random.default_rng(7)
    h = 1e-6
    for _ in range(4):
        v = jnp.asarray(rng.normal(size=x.shape))
        numeric = (float(f(x + h * v)) - float(f(x - h * v))) / (2 * h)
        np.testing.assert_allclose(float(jnp.dot(g, v)), numeric, rtol=_GRAD_RTOL, atol=_GRAD_ATOL)
    # the pixel does depend on both levels and on lobe 1 (the test has power)
    assert np.abs(np.asarray(grads[0].lobe1.rho_s)).max() > 1e-3
    assert np.abs(np.asarray(grads[1].rho_d)).max() > 1e-3


def test_mip_level_closed_form():
    rng = np.random.default_rng(3)
    dx, dy = rng.normal(size=(20, 2)) * 0.01, rng.normal(size=(20, 2)) * 0.01
    size = np.array([[64, 128]] * 20)   # rows, cols
    expected = np.log2(np.maximum(np.hypot(dx[:, 0] * 128, dx[:, 1] * 64), np.hypot(dy[:, 0] * 128, dy[:, 1] * 64)))
    np.testing.assert_allclose(mip_level(jnp.asarray(dx), jnp.asarray(dy), jnp.asarray(size)), expected, atol=_MIP_TOL)


def test_mip_level_from_rasterized_affine_mapping():
    # a quad parallel to the image plane: uv is an affine function of the pixel, du/dx = 1 / (quad width in pixels)
    cam = Camera((0.0, 0.0, 2.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 40.0, width=48, height=32)
    ph = camera_pinhole(cam)
    verts = jnp.asarray([[-0.5, -0.4, 0.0], [0.5, -0.4, 0.0], [0.5, 0.4, 0.0], [-0.5, 0.4, 0.0]])
    uv = jnp.asarray([[0.0, 1.0], [3.0, 1.0], [3.0, 0.0], [0.0, 0.0]])   # u repeats 3 times across
    tris = jnp.asarray([[0, 1, 2], [0, 2, 3]], dtype=jnp.int32)
    window = raster_window(ph, verts, tris)
    gb = jax.jit(lambda v: rasterize(ph, v, tris, uv, window=window))(verts)
    hit = np.asarray(gb.hit) > 0
    width_px = 1.0 * ph.fx / 2.0     # 1 m wide at 2 m
    height_px = 0.8 * ph.fy / 2.0
    np.testing.assert_allclose(np.asarray(gb.duv_dx)[hit], np.tile([3.0 / width_px, 0.0], (hit.sum(), 1)), atol=1e-9)
    np.testing.assert_allclose(np.asarray(gb.duv_dy)[hit], np.tile([0.0, 1.0 / height_px], (hit.sum(), 1)), atol=1e-9)
    lam = mip_level(gb.duv_dx[hit], gb.duv_dy[hit], jnp.asarray([[256, 256]] * int(hit.sum())))
    expected = np.log2(max(256 * 3.0 / width_px, 256 * 1.0 / height_px))
    np.testing.assert_allclose(lam, expected, atol=_MIP_TOL)
    # the covered pixels are those whose centres fall inside the projected quad
    cols = (np.arange(48) + 0.5 - ph.cx) / ph.fx * 2.0
    rows = (np.arange(32) + 0.5 - ph.cy) / ph.fy * 2.0
    inside = (np.abs(rows)[:, None] < 0.4) & (np.abs(cols)[None, :] < 0.5)
    np.testing.assert_array_equal(hit, inside)


def test_levels_blend_shading_results_not_parameters():
    lvl0 = jax.tree_util.tree_map(lambda a: a.reshape((1, 1) + a.shape[1:]), _texel(1, weight=0.0))
    lvl1 = jax.tree_util.tree_map(lambda a: a.reshape((1, 1) + a.shape[1:]), _texel(1, weight=0.9, sigma=0.05))
    mats = _one_material([lvl0, lvl1])
    wi = jnp.asarray(_dirs(5))[None]
    wo = jnp.asarray(_dirs(1, seed=9))
    w = jnp.ones((1, 5, 3))
    uv = jnp.asarray([[0.5, 0.5]])
    dy = jnp.zeros((1, 2))
    zero = jnp.zeros((1,), jnp.int32)

    @jax.jit
    def at(lam):
        return shade_fabric(mats, zero, uv, jnp.asarray([[2.0 ** lam, 0.0]]), dy, _frame(1), wo, wi, w)

    shade = jax.jit(shade_samples)
    a = shade(jax.tree_util.tree_map(lambda x: x[0], lvl0), _frame(1), wo, wi, w)
    b = shade(jax.tree_util.tree_map(lambda x: x[0], lvl1), _frame(1), wo, wi, w)
    np.testing.assert_allclose(at(0.0), a, rtol=1e-12)
    np.testing.assert_allclose(at(1.0), b, rtol=1e-12)
    np.testing.assert_allclose(at(0.25), 0.75 * a + 0.25 * b, rtol=1e-12)
    np.testing.assert_allclose(at(5.0), b, rtol=1e-12)   # clamped to the coarsest level


def test_rasterizer_matches_brute_force_ray_caster():
    from sims.cloth import drape_cloth

    m = drape_cloth(rows=6, cols=5, width=0.6, height=0.6, shoulder_span=0.4, body_radius=0.05, steps=1500, top=1.0)
    verts, tris = m.vertices.reshape(-1, 3), m.triangles
    cam = Camera((0.4, 0.8, 1.6), (0.0, 0.7, 0.0), (0.0, 1.0, 0.0), 40.0, width=40, height=30)
    ph = camera_pinhole(cam)
    window = raster_window(ph, verts, tris)
    gb = jax.jit(lambda v: rasterize(ph, v, tris, m.uv.reshape(-1, 2), window=window))(verts)
    # brute force: every pixel ray against every triangle (numpy float64 Moller-Trumbore)
    px = np.stack(np.meshgrid(np.arange(40) + 0.5, np.arange(30) + 0.5), -1)
    d = np.asarray(ph.ray(jnp.asarray(px)))[:, :, None, :]
    v, t = np.asarray(verts), np.asarray(tris)
    p0, p1, p2 = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
    e1, e2 = p1 - p0, p2 - p0
    pv = np.cross(d, e2)
    det = np.sum(e1 * pv, -1)
    tv = np.asarray(cam.eye) - p0
    b1 = np.sum(tv * pv, -1) / det
    qv = np.cross(tv, e1)
    b2 = np.sum(d * qv, -1) / det
    dist = np.sum(e2 * qv, -1) / det
    ok = (b1 >= 0) & (b2 >= 0) & (b1 + b2 <= 1) & (dist > 0)
    dist = np.where(ok, dist, np.inf)
    nearest = dist.min(-1)
    hit = np.isfinite(nearest)
    ours = np.asarray(gb.hit) > 0
    # pixels whose centre lies (numerically) on a shared edge may go either way: allow a few
    assert np.sum(hit != ours) <= 2 and hit.sum() > 100
    both = hit & ours
    np.testing.assert_allclose(np.asarray(gb.distance)[both], nearest[both], atol=_DEPTH_TOL)


def test_single_lobe_shading_equals_full_brdf_for_one_lobe_texels():
    from jaxrender.fabric import shade_single_lobe

    t = _texel(3, two=False)
    wi = jnp.asarray(np.stack([_dirs(5, seed=s, z_min=-0.3) for s in range(3)]))
    wo = jnp.asarray(_dirs(3, seed=7))
    w = jnp.asarray(np.random.default_rng(4).uniform(0.5, 1.5, (3, 5, 3)))
    frame = _frame(3)
    np.testing.assert_allclose(jax.jit(shade_single_lobe)(t, frame, wo, wi, w),
                               jax.jit(shade_samples)(t, frame, wo, wi, w), rtol=1e-12, atol=1e-15)

"""The polished floor's glossy planar reflection (jaxrender.fabric._reflection)."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxrender.camera import Camera
from jaxrender.fabric import (
    camera_pinhole,
    fresnel_schlick,
    glossy_blur_pixels,
    glossy_reflection,
    mirror_mesh,
    raster_window,
    rasterize,
    reflect_directions,
    reflect_points,
)

_GEOM_TOL = 1e-9      # float64 geometry of a few metres: a handful of roundings
_SUM_TOL = 1e-9       # relative: the box pyramid and bilinear upsampling keep the sum of an interior image

_glossy = jax.jit(glossy_reflection, static_argnames="levels")


def _camera(w=96, h=64):
    return Camera((0.9, 1.2, 3.4), (0.0, 0.82, 0.0), (0.0, 1.0, 0.0), 40.0, width=w, height=h)


def test_a_point_and_its_reflection():
    """The camera ray toward the mirror image P' crosses the floor at Q, and the mirrored ray from Q
    passes through P, |Q - P| = |Q - P'| (the reflected surface's distance beyond the floor)."""
    rng = np.random.default_rng(0)
    ph = camera_pinhole(_camera())
    eye = np.asarray(ph.origin)
    for point, normal in (((0.0, 0.0, 0.0), (0.0, 1.0, 0.0)), ((0.0, 0.3, 0.0), (0.0, 1.0, 0.0))):
        p = rng.uniform([-1, 0.5, -1], [1, 1.8, 1], (50, 3))
        p2 = np.asarray(reflect_points(jnp.asarray(p), jnp.asarray(point), jnp.asarray(normal)))
        np.testing.assert_allclose(p2[:, 1], 2 * point[1] - p[:, 1], atol=_GEOM_TOL)
        np.testing.assert_allclose(p2[:, [0, 2]], p[:, [0, 2]], atol=_GEOM_TOL)
        pix, _ = ph.project(jnp.asarray(p2))
        d = np.asarray(ph.ray(pix))
        t = (point[1] - eye[1]) / d[:, 1]
        q = eye + t[:, None] * d
        r = np.asarray(reflect_directions(jnp.asarray(d), jnp.asarray(normal)))
        to_p = p - q
        np.testing.assert_allclose(np.cross(to_p, r), 0.0, atol=_GEOM_TOL)   # P on the mirrored ray
        assert np.all(np.sum(to_p * r, -1) > 0)                             # ahead of Q, not behind
        np.testing.assert_allclose(np.linalg.norm(to_p, axis=-1), np.linalg.norm(p2 - q, axis=-1), atol=_GEOM_TOL)
        np.testing.assert_allclose(np.linalg.norm(p2 - eye, axis=-1), t + np.linalg.norm(to_p, axis=-1), atol=_GEOM_TOL)
    # a tilted plane: reflecting twice is the identity, and the plane's own points stay put
    n = np.asarray([0.3, 0.9, -0.2]) / np.linalg.norm([0.3, 0.9, -0.2])
    x = jnp.asarray(rng.normal(size=(20, 3)))
    back = reflect_points(reflect_points(x, jnp.asarray([0.1, 0.2, 0.3]), jnp.asarray(n)), jnp.asarray([0.1, 0.2, 0.3]),
                          jnp.asarray(n))
    np.testing.assert_allclose(back, x, atol=_GEOM_TOL)


def test_rasterized_mirror_mesh_shows_what_the_floor_reflects():
    """Rasterize a mirrored triangle with the camera: at every covered pixel, the mirrored ray from
    the floor hits the ORIGINAL triangle (numpy Moller-Trumbore) at the mirror image of the
    G-buffer's position."""
    cam = _camera()
    ph = camera_pinhole(cam)
    verts = jnp.asarray([[-0.4, 0.3, 0.2], [0.5, 0.5, -0.1], [0.0, 1.0, 0.3]])
    normals = jnp.asarray([[0.0, 0.0, 1.0]] * 3)
    tris = jnp.asarray([[0, 1, 2]], dtype=jnp.int32)
    origin, up = jnp.asarray([0.0, 0.0, 0.0]), jnp.asarray([0.0, 1.0, 0.0])
    mv, mn, mt = mirror_mesh(verts, normals, tris, origin, up)
    np.testing.assert_array_equal(np.asarray(mt), [[2, 1, 0]])
    np.testing.assert_allclose(mn, [[0.0, 0.0, 1.0]] * 3, atol=0)
    uv = jnp.zeros((3, 2))
    window = raster_window(ph, mv, mt)
    gb = jax.jit(lambda v, t: rasterize(ph, v, t, uv, window=window))(mv, mt)
    hit = np.asarray(gb.hit) > 0
    assert hit.sum() > 20
    eye = np.asarray(ph.origin)
    rows, cols = np.nonzero(hit)
    d = np.asarray(ph.ray(jnp.stack([jnp.asarray(cols + 0.5), jnp.asarray(rows + 0.5)], -1)))
    q = eye + (-eye[1] / d[:, 1])[:, None] * d
    r = d * np.asarray([1.0, -1.0, 1.0])
    v = np.asarray(verts)
    e1, e2 = v[1] - v[0], v[2] - v[0]
    pv = np.cross(r, e2)
    det = pv @ e1
    tv = q - v[0]
    b1 = np.sum(tv * pv, -1) / det
    qv = np.cross(tv, e1)
    b2 = np.sum(r * qv, -1) / det
    s = qv @ e2 / det
    inside = (b1 >= -1e-6) & (b2 >= -1e-6) & (b1 + b2 <= 1 + 1e-6) & (s > 0)
    assert np.all(inside)
    hit_point = q + s[:, None] * r
    mirrored_back = np.asarray(gb.position)[rows, cols] * np.asarray([1.0, -1.0, 1.0])
    np.testing.assert_allclose(mirrored_back, hit_point, atol=1e-7)


def test_fresnel_schlick_limits():
    c = jnp.linspace(0.0, 1.0, 101)
    f = np.asarray(fresnel_schlick(c, 0.04))
    np.testing.assert_allclose(f[-1], 0.04, atol=1e-15)   # normal incidence
    np.testing.assert_allclose(f[0], 1.0, atol=1e-15)     # grazing
    assert np.all(np.diff(f) <= 0) and np.all((f >= 0.04) & (f <= 1.0))


def test_reflection_is_never_brighter_than_what_it_reflects_times_the_reflectance():
    rng = np.random.default_rng(2)
    h, w = 48, 64
    for dtype in (jnp.float64, jnp.float32):
        img = jnp.asarray(rng.exponential(size=(h, w, 3)) * (rng.uniform(size=(h, w, 1)) > 0.9), dtype)
        blur = jnp.asarray(rng.uniform(0.0, 40.0, (h, w)), dtype)
        cos = jnp.asarray(rng.uniform(0.0, 1.0, (h, w)), dtype)
        out = _glossy(img, blur, cos, f0=0.04)
        assert out.dtype == dtype
        f = np.asarray(fresnel_schlick(cos, 0.04))[..., None]
        bound = f * np.asarray(img).max(axis=(0, 1))
        assert np.all(np.asarray(out) <= bound * (1 + 1e-6) + 1e-30)
        assert np.all(np.asarray(out) >= 0)
        # a uniform scene is reflected at exactly F times its radiance, whatever the blur
        const = jnp.full((h, w, 3), 2.5, dtype)
        np.testing.assert_allclose(_glossy(const, blur, cos), 2.5 * f * np.ones((1, 1, 3)),
                                   rtol=1e-6 if dtype == jnp.float32 else 1e-12)
    # energy: a bright spot away from the border, blurred by a whole mip level, keeps its sum times F
    spot = np.zeros((64, 64, 3))
    spot[30:34, 28:32] = 7.0
    for level in range(4):
        out = _glossy(jnp.asarray(spot), jnp.full((64, 64), 2.0 ** level), jnp.ones((64, 64)), f0=0.04)
        np.testing.assert_allclose(np.sum(np.asarray(out)), 0.04 * spot.sum(), rtol=_SUM_TOL)
        assert np.asarray(out).max() <= 0.04 * 7.0 * (1 + 1e-12)
        if level >= 2:
            assert np.asarray(out).max() < 0.04 * 7.0 * 0.9   # blurred: the peak went down


def test_blur_width_and_its_gradient():
    # a mirror does not blur; the blur grows with the distance beyond the floor toward roughness focal
    np.testing.assert_allclose(glossy_blur_pixels(0.0, 1.0, 2.0, 500.0), 0.0)
    np.testing.assert_allclose(glossy_blur_pixels(0.1, 1.0, 3.0, 400.0), 400.0 * 0.1 * 1.0 / 4.0, rtol=1e-12)
    assert float(glossy_blur_pixels(0.1, 100.0, 3.0, 400.0)) < 40.0
    rng = np.random.default_rng(4)
    img = jnp.asarray(rng.uniform(size=(32, 32, 3)))

    def f(rough):
        blur = glossy_blur_pixels(rough, jnp.full((32, 32), 1.5), jnp.full((32, 32), 2.0), 300.0)
        return jnp.sum(glossy_reflection(img, blur, jnp.full((32, 32), 0.4)) ** 2)

    g = jax.jit(jax.grad(f))(0.05)
    f = jax.jit(f)
    eps = 1e-7
    fd = (f(0.05 + eps) - f(0.05 - eps)) / (2 * eps)
    np.testing.assert_allclose(float(g), float(fd), rtol=1e-5)
    assert abs(float(g)) > 0

"""PCSS against a brute-force area-light visibility integral; hard-shadow limit; our depth maps
agree with SHAFTS's shadow-map renderer."""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from jaxrender.fabric import depth_map, raster_window, spot_pinhole
from jaxrender.geometry import Quads
from jaxrender.lights import SpotLight
from jaxrender.shadows import ShadowMap, pcss, render_shadow_map, shadow_test

_LIGHT = 0.4          # side of the square light (m)
_Z_OCC, _Z_RECV = 1.0, 2.5   # occluder and receiver planes below the light (parallel to it)
_MEAN_TOL = 0.04      # mean |PCSS - truth| over a line crossing the penumbra: 6x6 PCF grid + 128^2 map
_MAX_TOL = 0.12       # worst point: one PCF grid step (1/6) discretisation of a linear ramp, less
_DEPTH_TOL = 1e-3     # m: two ray casters (ours rasterizes triangles, SHAFTS intersects quads) in float64


@functools.lru_cache(maxsize=1)
def _setup():
    # the light at the origin looking down -y; occluder: a half-plane-like big quad covering x < 0
    light = SpotLight(position=(0.0, 0.0, 0.0), target=(0.0, -1.0, 0.0), up=(0.0, 0.0, 1.0), cutoff_deg=40.0)
    occ = Quads(center=[[-1.0, -_Z_OCC, 0.0]], u=[[1.0, 0.0, 0.0]], v=[[0.0, 0.0, 2.0]])
    sm = jax.jit(lambda li, oc: render_shadow_map(li, oc, resolution=128))(light, [occ])
    return light, occ, sm


def _brute_force(points, n=128):
    """Fraction of the light square whose segment to the point misses the occluder (x < 0 at
    depth _Z_OCC, |z| < 2)."""
    s = (np.arange(n) + 0.5) / n - 0.5
    qx, qz = np.meshgrid(s * _LIGHT, s * _LIGHT)
    vis = []
    for p in points:
        t = _Z_OCC / (-p[1])  # fraction of the way from the light point to p at the occluder plane
        x = qx + (p[0] - qx) * t
        z = qz + (p[2] - qz) * t
        blocked = (x > -2.0) & (x < 0.0) & (np.abs(z) < 2.0)
        vis.append(1 - blocked.mean())
    return np.asarray(vis)


def test_depth_map_matches_shafts_shadow_map():
    light, occ, sm = _setup()
    c, u, v = occ.center[0], occ.u[0], occ.v[0]
    verts = jnp.stack([c - u - v, c + u - v, c + u + v, c - u + v])
    tris = jnp.asarray([[0, 1, 2], [0, 2, 3]], dtype=jnp.int32)
    ph = spot_pinhole(light.position, light.rotation(), float(jnp.tan(jnp.deg2rad(40.0))), 128)
    win = raster_window(ph, verts, tris)
    ours = np.asarray(jax.jit(lambda v: depth_map(ph, v, tris, window=win))(verts))
    theirs = np.asarray(sm.depth)
    both = np.isfinite(ours) & np.isfinite(theirs)
    # coverage agrees except along the occluder's edge column (a texel centre exactly on the edge)
    assert np.mean(np.isfinite(ours) != np.isfinite(theirs)) < 2 / 128
    np.testing.assert_allclose(ours[both], theirs[both], atol=_DEPTH_TOL)


def test_pcss_matches_brute_force_area_light():
    _, _, sm = _setup()
    xs = np.linspace(-0.6, 0.6, 49)
    pts = np.stack([xs, np.full_like(xs, -_Z_RECV), np.full_like(xs, 0.1)], axis=-1)
    ours = np.asarray(jax.jit(lambda p: pcss(sm, p, light_size=_LIGHT, near=0.05, bias=0.01))(jnp.asarray(pts)))
    truth = _brute_force(pts)
    assert truth.min() == 0.0 and truth.max() == 1.0 and np.sum((truth > 0.05) & (truth < 0.95)) >= 10
    print('pcss mean/max error', np.mean(np.abs(ours - truth)), np.max(np.abs(ours - truth)))
    assert np.mean(np.abs(ours - truth)) < _MEAN_TOL
    assert np.max(np.abs(ours - truth)) < _MAX_TOL


def test_pcss_hard_shadow_limit():
    _, _, sm = _setup()
    xs = np.linspace(-0.6, 0.6, 25)
    xs = xs[np.abs(xs) > 0.05]   # away from the edge texel
    pts = jnp.asarray(np.stack([xs, np.full_like(xs, -_Z_RECV), np.full_like(xs, 0.1)], axis=-1))
    soft = np.asarray(jax.jit(lambda p: pcss(sm, p, light_size=1e-6, bias=0.01))(pts))
    hard = np.asarray(jax.jit(lambda p: shadow_test(sm, p, bias=0.01))(pts))
    np.testing.assert_array_equal(soft, hard)
    assert soft.min() == 0.0 and soft.max() == 1.0


def test_pcss_no_occluder_is_lit_and_finite():
    sm = ShadowMap(depth=jnp.full((8, 8), jnp.inf), position=jnp.zeros(3), rotation=jnp.eye(3),
                   tan_cutoff=jnp.asarray(0.5))
    pts = jnp.asarray([[0.1, 0.0, 1.0], [0.0, 0.0, -1.0], [5.0, 0.0, 1.0]])
    np.testing.assert_array_equal(jax.jit(lambda p: pcss(sm, p, light_size=0.3))(pts), 1.0)

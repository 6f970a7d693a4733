"""Shadow maps from a spot light: texel layout and depths against numpy, lookups with bias."""

import jax
import jax.numpy as jnp
import numpy as np

from jaxrender.geometry import Quads, Spheres
from jaxrender.lights import SpotLight
from jaxrender.shadows import render_shadow_map, shadow_test, shadow_uv_distance

_TOL = 1e-9  # float64 closed-form ray-sphere distances


def _scene():
    light = SpotLight([0.0, 4.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 30.0)
    prims = (Spheres([[0.3, 1.5, 0.0]], [0.6]), Quads([[0.0, 0.0, 0.0]], [[5.0, 0, 0]], [[0, 0, -5.0]]))
    return light, prims


def test_depths_match_numpy_per_texel():
    light, prims = _scene()
    n = 16
    sm = jax.jit(lambda L: render_shadow_map(L, prims, resolution=n))(light)
    x, y, z = (np.asarray(a) for a in light.frame())
    t = np.tan(np.radians(30.0))
    pos = np.asarray(light.position)
    for row in range(n):
        for col in range(n):
            u, v = (col + 0.5) / n, (row + 0.5) / n
            d = (2 * u - 1) * t * x + (2 * v - 1) * t * y + z
            d /= np.linalg.norm(d)
            oc = pos - np.array([0.3, 1.5, 0.0])
            b, c = oc @ d, oc @ oc - 0.36
            want = -b - np.sqrt(b * b - c) if b * b - c > 0 else -pos[1] / d[1]  # sphere, else the floor
            assert abs(float(sm.depth[row, col]) - want) < _TOL
    # the texel grid is the light map's uv: a point on a texel ray projects onto that texel centre
    p = pos + 2.0 * ((2 * 0.71875 - 1) * t * x + (2 * 0.28125 - 1) * t * y + z)
    uv, dist, front = shadow_uv_distance(sm, jnp.asarray(p))
    np.testing.assert_allclose(np.asarray(uv), [0.71875, 0.28125], atol=1e-12)
    assert bool(front)


def test_shadow_test_above_below_and_outside():
    light, prims = _scene()
    sm = jax.jit(lambda L: render_shadow_map(L, prims, resolution=64))(light)
    pts = jnp.array([[0.3, 2.5, 0.0],    # between light and sphere: lit
                     [0.3, 0.5, 0.0],    # under the sphere: shadowed
                     [2.0, 0.0, 0.0],    # on the floor, outside the sphere's shadow: lit (bias)
                     [0.3, 0.0, 0.0],    # on the floor in the shadow
                     [0.0, 6.0, 0.0]])   # behind the light: lit (outside the cone)
    got = np.asarray(jax.jit(lambda m, p: shadow_test(m, p, bias=0.01))(sm, pts))
    np.testing.assert_array_equal(got, [1.0, 0.0, 1.0, 0.0, 1.0])

"""Footprints pressed into sand and relaxed to the angle of repose (sims.footprints)."""

import math

import jax
import jax.numpy as jnp
import numpy as np

from sims.footprints import (
    FootParams,
    press_footprint,
    press_trail,
    relax_to_repose,
    repose_excess,
    sole_shape,
    trail_steps,
)

_SPACING = 1.0 / 64          # ripple texels of a 64-texel dune quad
_F64_MASS_TOL = 1e-13        # float64: what rounding of a few hundred additions leaves
_REF_TOL_F64 = 1e-12         # JAX float64 vs the loop reference: same arithmetic, different order
_REF_TOL_F32 = 2e-6          # float32 vs float64 after 300 slides of heights ~0.03: ~100 ulps accumulated
_REPOSE_TOL = 1e-3           # tan of the slope above the angle of repose left after the iterations (1e-3 of 0.67)


def _f32_mass_tol(h) -> float:
    """Each cell's update rounds once per step: a bound of cells x eps x the largest height, per step."""
    return h.size * float(np.finfo(np.float32).eps) * float(np.max(np.abs(h)))


def _ripples(shape, dtype=jnp.float64, seed=0):
    rng = np.random.default_rng(seed)
    y, x = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    h = 0.004 * np.sin(2 * np.pi * (x + 0.3 * y) / 9.0) + 0.001 * rng.standard_normal(shape)
    return jnp.asarray(h, dtype)


def _relax_reference(h, *, spacing, tan_repose, iterations, rate):
    """Float64 loops over cells and neighbour pairs: the synchronous slide of the module docstring."""
    h = np.array(h, np.float64)
    rows, cols = h.shape
    pairs = [(0, 1, spacing), (1, 0, spacing), (1, 1, spacing * math.sqrt(2)), (1, -1, spacing * math.sqrt(2))]
    for _ in range(iterations):
        delta = np.zeros_like(h)
        for i in range(rows):
            for j in range(cols):
                for di, dj, dist in pairs:
                    k, m = i + di, j + dj
                    if not (0 <= k < rows and 0 <= m < cols):
                        continue
                    diff = h[i, j] - h[k, m]
                    excess = max(abs(diff) - tan_repose * dist, 0.0)
                    moved = rate * math.copysign(excess, diff)
                    delta[i, j] -= moved
                    delta[k, m] += moved
        h = h + delta
    return h


def _max_pair_slope(h, spacing):
    """Independent check of the slopes (numpy): the steepest edge or diagonal neighbour pair."""
    h = np.asarray(h, np.float64)
    e = max(np.abs(np.diff(h, axis=0)).max(), np.abs(np.diff(h, axis=1)).max()) / spacing
    d = max(np.abs(h[1:, 1:] - h[:-1, :-1]).max(), np.abs(h[1:, :-1] - h[:-1, 1:]).max()) / (spacing * math.sqrt(2))
    return max(e, d)


def test_press_footprint_conserves_sand_and_makes_a_print():
    foot = FootParams()
    for dtype in (jnp.float64, jnp.float32):
        h = _ripples((48, 64), dtype)
        centre, heading = jnp.asarray([0.5, 0.37], dtype), jnp.asarray(0.4, dtype)
        p = jax.jit(lambda a: press_footprint(a, centre, heading, foot, spacing=_SPACING))(h)
        assert p.dtype == dtype
        before, after = np.sum(np.asarray(h, np.float64)), np.sum(np.asarray(p, np.float64))
        tol = _F64_MASS_TOL if dtype == jnp.float64 else _f32_mass_tol(np.asarray(h))
        assert abs(after - before) <= tol, (dtype, after - before, tol)
        # the shape: the flat of the sole lies `depth` below the mean sand height under the sole, the rim
        # rose, and sand away from the print is untouched
        y, x = np.meshgrid((np.arange(48) + 0.5) * _SPACING, (np.arange(64) + 0.5) * _SPACING, indexing="ij")
        sole, rim = (np.asarray(a) for a in sole_shape(jnp.asarray(x), jnp.asarray(y), centre.astype(jnp.float64),
                                                      heading.astype(jnp.float64), foot))
        hn, pn = np.asarray(h, np.float64), np.asarray(p, np.float64)
        flat = sole >= 1.0
        assert flat.sum() > 20
        np.testing.assert_allclose(pn[flat], hn[sole > 0].mean() - foot.depth, atol=1e-6)
        assert np.all(pn[rim > 0] >= hn[rim > 0] - 1e-7) and (pn - hn)[rim > 0].sum() > 0
        far = (sole == 0) & (rim == 0)
        np.testing.assert_array_equal(pn[far], hn[far])
    # jitted and not jitted agree
    h = _ripples((24, 32))
    a = press_footprint(h, jnp.asarray([0.25, 0.2]), jnp.asarray(0.0), foot, spacing=_SPACING)
    b = jax.jit(press_footprint, static_argnames="spacing")(h, jnp.asarray([0.25, 0.2]), jnp.asarray(0.0), foot,
                                                             spacing=_SPACING)
    np.testing.assert_allclose(a, b, atol=1e-15)


def test_relaxation_matches_a_float64_loop_reference():
    """A pit and a spike on a small field, 300 slides: JAX (float64 and float32) vs the loop reference."""
    rng = np.random.default_rng(3)
    h = 0.002 * rng.standard_normal((10, 12))
    h[3:6, 4:7] -= 0.03   # a pressed pit with vertical walls
    h[7, 2] += 0.02       # a spike
    kw = dict(spacing=_SPACING, tan_repose=FootParams().tan_repose, iterations=300, rate=0.1)
    ref = _relax_reference(h, **kw)
    got64 = np.asarray(jax.jit(lambda a: relax_to_repose(a, **kw))(jnp.asarray(h)))
    got32 = np.asarray(jax.jit(lambda a: relax_to_repose(a, **kw))(jnp.asarray(h, jnp.float32)))
    np.testing.assert_allclose(got64, ref, atol=_REF_TOL_F64)
    np.testing.assert_allclose(got32, ref, atol=_REF_TOL_F32)
    assert np.abs(ref - h).max() > 0.005  # the reference did move sand (the comparison is not vacuous)
    assert _max_pair_slope(ref, _SPACING) <= kw["tan_repose"] + _REPOSE_TOL


def test_trail_relaxes_to_the_angle_of_repose_and_conserves_sand():
    foot = FootParams()
    centres, headings = trail_steps(jnp.asarray([[0.15, 0.35], [1.3, 0.45]]), stride=0.7, gait=0.16)
    for dtype in (jnp.float64, jnp.float32):
        h = _ripples((48, 96), dtype, seed=1)
        out = jax.jit(lambda a: press_trail(a, centres.astype(dtype), headings.astype(dtype), foot, spacing=_SPACING,
                                            iterations=300))(h)
        pressed = jax.jit(lambda a: press_trail(a, centres.astype(dtype), headings.astype(dtype), foot,
                                                spacing=_SPACING, iterations=0))(h)
        before, after = np.sum(np.asarray(h, np.float64)), np.sum(np.asarray(out, np.float64))
        tol = _F64_MASS_TOL if dtype == jnp.float64 else 300 * _f32_mass_tol(np.asarray(h))
        assert abs(after - before) <= tol, (dtype, after - before, tol)
        # pressing made walls far steeper than the angle of repose; relaxing brought every slope back
        assert _max_pair_slope(pressed, _SPACING) > 2 * foot.tan_repose
        assert _max_pair_slope(out, _SPACING) <= foot.tan_repose + _REPOSE_TOL
        assert float(repose_excess(out, spacing=_SPACING, tan_repose=foot.tan_repose)) <= _REPOSE_TOL
        # the prints are still there: each centre lies well below the sand around the trail
        o = np.asarray(out, np.float64)
        cells = np.floor(np.asarray(centres) / _SPACING).astype(int)
        assert np.all(o[cells[:, 1], cells[:, 0]] < np.asarray(h, np.float64).mean() - 0.5 * foot.depth)


def test_trail_steps_alternate_along_the_path():
    centres, headings = trail_steps(jnp.asarray([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0]]), stride=0.8, gait=0.2)
    c, hd = np.asarray(centres), np.asarray(headings)
    assert c.shape[0] == int((4.0 - 0.2) / 0.4) + 1
    first_leg = c[:, 0] < 1.9
    np.testing.assert_allclose(hd[first_leg], 0.0, atol=1e-12)
    np.testing.assert_allclose(np.abs(c[first_leg, 1]), 0.1, atol=1e-12)               # gait / 2 either side
    assert np.all(np.sign(c[first_leg, 1][:-1]) != np.sign(c[first_leg, 1][1:]))      # left, right, left, ...
    np.testing.assert_allclose(np.diff(c[first_leg, 0]), 0.4, atol=1e-12)             # half a stride apart
    np.testing.assert_allclose(hd[c[:, 1] > 0.3], np.pi / 2, atol=1e-12)               # the second leg turns north


def test_relaxation_gradient_matches_finite_differences():
    """Piecewise linear in the heights: the JVP equals central differences away from the kinks."""
    rng = np.random.default_rng(5)
    h = jnp.asarray(0.002 * rng.standard_normal((8, 9)) - 0.03 * (rng.uniform(size=(8, 9)) > 0.8))
    v = jnp.asarray(rng.standard_normal((8, 9)))

    def f(a):
        return jnp.sum(relax_to_repose(a, spacing=_SPACING, iterations=40) ** 2)

    _, jvp = jax.jvp(f, (h,), (v,))
    eps = 1e-9
    fd = (f(h + eps * v) - f(h - eps * v)) / (2 * eps)
    np.testing.assert_allclose(float(jvp), float(fd), rtol=1e-5)
    g = jax.grad(f)(h)
    np.testing.assert_allclose(float(jnp.sum(g * v)), float(jvp), rtol=1e-10)


def _terrain(texels=16, levels=2):
    from jaxrender.terrain import build_terrain_maps

    rng = np.random.default_rng(7)
    y, x = np.meshgrid(np.arange(8), np.arange(8), indexing="ij")
    dune = 0.8 * np.sin(2 * np.pi * x / 8) * np.cos(2 * np.pi * y / 8) + 0.05 * rng.standard_normal((8, 8))
    ry, rx = np.meshgrid(np.arange(16), np.arange(16), indexing="ij")
    ripple = 0.006 * np.sin(2 * np.pi * (rx + 0.25 * ry) / 8.0)
    return build_terrain_maps(jnp.asarray(dune), jnp.asarray(ripple), key=jax.random.key(0), spacing=1.0,
                              texels=texels, levels=levels), jnp.asarray(ripple)


def _shade(maps, level):
    from jaxrender.lights import Sun, sun_direction_z_up

    sun = Sun(jnp.asarray(sun_direction_z_up(12.0, 200.0)), jnp.asarray([3.0, 2.8, 2.5]))
    visible = jnp.ones(maps.quads, bool)
    lev = jnp.full(maps.quads, level, jnp.int32)
    count = maps.quads[0] * maps.quads[1]
    caps = tuple(count if i == level else 0 for i in range(maps.levels))
    tiles, _ = _shade_jit(maps, visible, lev, sun, jnp.asarray([0.6, 0.36, 0.18]), jnp.asarray([0.3, 0.4, 0.6]),
                          capacities=caps, shadow_steps=8)
    return np.asarray(tiles[level])


def _shade_jit(*args, **kwargs):
    from jaxrender.terrain import shade_quads

    global _SHADE
    if _SHADE is None:
        _SHADE = jax.jit(shade_quads, static_argnames=("capacities", "shadow_steps"))
    return _SHADE(*args, **kwargs)


_SHADE = None


def test_footprint_detail_window_is_shaded_like_the_ripples_until_pressed():
    """A detail window holding the very ripples it covers shades exactly as without it; with a
    print pressed in, only the window's quad changes, at both levels of detail, and under a low
    sun the print's walls cast horizon-map shadows. (One 16 x 16-texel quad: the horizon map
    compiles once for the ripple map and the window.)"""
    from jaxrender.shadows import horizon_light
    from jaxrender.terrain import build_detail_maps, window_ripples, with_detail

    maps, ripple = _terrain()
    assert maps.quads == (8, 8)      # the periodic 8 x 8 dune field closed into 8 x 8 quads
    origin, quads = (2, 3), (1, 1)
    plain = window_ripples(ripple, origin, quads, texels=16)
    np.testing.assert_array_equal(plain, ripple)  # a 16-texel quad shows one whole ripple period
    detail = build_detail_maps(plain, origin, spacing=1.0, texels=16, levels=2)
    foot = FootParams(length=0.6, width=0.25, depth=0.05, rim=0.1)
    pressed = jax.jit(lambda h: relax_to_repose(press_footprint(h, jnp.asarray([0.5, 0.5]), jnp.asarray(0.3), foot,
                                                                spacing=1 / 16), spacing=1 / 16, iterations=300))(plain)
    printed = build_detail_maps(pressed, origin, spacing=1.0, texels=16, levels=2)
    window = np.zeros((8, 8), bool)  # quads (row qj, column qi) inside the window
    window[3, 2] = True
    base = _shade(maps, 0)
    np.testing.assert_allclose(_shade(with_detail(maps, detail), 0), base, atol=1e-12)
    for level in (0, 1):
        ref = _shade(with_detail(maps, detail), level)
        prints = _shade(with_detail(maps, printed), level)
        ref, prints = (a.reshape((8, 8) + a.shape[1:]) for a in (ref, prints))
        np.testing.assert_array_equal(prints[~window], ref[~window])
        assert np.abs(prints[window] - ref[window]).max() > 0.05 * ref.max()
    # shadows: the lit fraction (horizon test alone, sun 12 deg up) drops once the print is there
    light = jnp.asarray([np.cos(np.radians(12)), 0.0, np.sin(np.radians(12))])

    def lit(d):
        return np.asarray(horizon_light(jnp.moveaxis(d.horizon[0], -1, 0), jnp.moveaxis(d.horizon_band[0], -1, 0),
                                        jnp.broadcast_to(light, d.horizon[0].shape[:2] + (3,))))

    assert lit(printed).mean() < lit(detail).mean() - 0.01


def test_desert_scene_carries_the_trail():
    """`desert_scene(footprints=True)`: the trail's window in front of the camera, its relief the
    window's ripples with the prints pressed in (same sand), in the maps it renders."""
    from jaxrender.app.scenes.desert import desert_scene
    from jaxrender.app.scenes.footprints import footprint_detail, trail_window
    from jaxrender.terrain import window_ripples

    rng = np.random.default_rng(11)
    dune = rng.uniform(2, 4, (16, 16))
    ry, rx = np.meshgrid(np.arange(16), np.arange(16), indexing="ij")
    ripple = np.sin(2 * np.pi * rx / 8.0) + 0.1 * rng.standard_normal((16, 16))
    scene = desert_scene(dune_field=dune, ripple_field=ripple, texels=16, footprints=True)
    origin, size = trail_window(16)
    assert scene.maps.detail is not None
    assert scene.maps.detail.origin == origin and scene.maps.detail.quads == size
    assert desert_scene(dune_field=dune, ripple_field=ripple, texels=16).maps.detail is None
    detail, pressed = footprint_detail(scene.ripple_height, 16, texels=16, levels=4)
    plain = np.asarray(window_ripples(scene.ripple_height, origin, size, texels=16), np.float64)
    p = np.asarray(pressed, np.float64)
    assert abs(p.sum() - plain.sum()) <= 300 * _f32_mass_tol(plain) + _F64_MASS_TOL
    assert np.abs(p - plain).max() > 0.5 * FootParams().depth   # the prints are there
    np.testing.assert_allclose(detail.normals[0], scene.maps.detail.normals[0], atol=1e-12)

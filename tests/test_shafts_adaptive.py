"""The default light-shaft method (`render_adaptive`): in-scattering on a coarse grid of rays,
interpolated, and evaluated per pixel where it changes fast or a silhouette crosses a lit cell;
and the light maps' mip pyramids every fast method reads.

- The image is the equiangular method's own (same samples and taps, at every pixel) at the
  nodes and in every refined cell, to rounding; elsewhere it is an interpolation of it.
- No halo: within 2 pixels of a depth edge (a silhouette against a beam) the in-scattered light
  stays within the 2 % target of a 256-sample ray march (independent quadrature, shadow rays),
  and is the equiangular method's own there.
- Gradients (rho, kappa, K, intensity, light position; in grid fog also the grid values, along a
  random direction) against float64 central differences, with cells refined and interpolated.
- Mip pyramids against numpy: box levels, the bilinear magnification of a small map, gray maps
  kept in one channel, the level a footprint picks.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_shafts import _params, _scene, _with

from jaxrender.lights import SpotLight
from jaxrender.shafts import DensityGrid, Medium, render_adaptive, render_equiangular, render_raymarch
from jaxrender.shafts._equiangular import primary_hits
from jaxrender.textures import pack_mips

_EXACT = 1e-9  # the same computation, float64 (sums in another order)
_TARGET = 0.02  # the interactive frames' 2 % error target: relative RMS of the in-scattered light
_FD_RTOL = 1e-5  # float64 central differences, h = 1e-6 relative, smooth configuration
_FD_GRID_RTOL = 1e-4  # the same in grid fog (the volumes' tables add rounding to the differences)
_EDGE_JUMP = 0.05  # a depth edge: depth off the mean of its two neighbours by more than 5 % (a row or column)
_MIP_TOL = 1e-12  # float64 box averages and bilinear weights, summed in another order

W, H = 96, 64  # 24 x 16 cells of 4 x 4 pixels: silhouettes cross several cells

_ad = jax.jit(render_adaptive, static_argnames=("samples", "map_taps", "cell", "tolerance", "shadow_map", "chunk",
                                                "return_parts", "return_refined"))
_eq = jax.jit(render_equiangular, static_argnames=("samples", "map_taps", "shadow_map", "prune", "return_parts"))


def _fog(out):
    return sum(out[1][1])


@functools.cache
def _edge_scene():
    """A sphere inside the spot's beam seen from the side: its silhouette against the lit fog."""
    return _scene(width=W, height=H, eye=(1.5, 1.0, 5.0), shadow_map=512)


@functools.cache
def _renders():
    scene = _edge_scene()
    ad, (_, parts), refined = _ad(scene, return_parts=True, return_refined=True)
    eq = _fog(_eq(scene, map_taps=2, return_parts=True))
    ref = jax.jit(lambda s: render_raymarch(s, samples=256, return_parts=True)[1][1])(scene)
    return np.asarray(sum(parts)), np.asarray(eq), np.asarray(ref), np.asarray(refined)[..., 0]


def _depth_edge_band(scene, reach: int = 2) -> np.ndarray:
    """Pixels within `reach` pixels of a depth edge (a pixel whose depth is off the mean of its two
    neighbours along a row or a column by more than _EDGE_JUMP, relative; misses count as far)."""
    _, t, *_ = primary_hits(scene)
    t = np.where(np.isfinite(np.asarray(t)), np.asarray(t), 1e6)
    edge = np.zeros(t.shape, bool)
    edge[1:-1, :] |= np.abs(t[:-2, :] - 2 * t[1:-1, :] + t[2:, :]) > _EDGE_JUMP * t[1:-1, :]
    edge[:, 1:-1] |= np.abs(t[:, :-2] - 2 * t[:, 1:-1] + t[:, 2:]) > _EDGE_JUMP * t[:, 1:-1]
    band = np.zeros_like(edge)
    for dy in range(-reach, reach + 1):
        for dx in range(-reach, reach + 1):
            band[max(dy, 0):H + min(dy, 0), max(dx, 0):W + min(dx, 0)] |= \
                edge[max(-dy, 0):H + min(-dy, 0), max(-dx, 0):W + min(-dx, 0)]
    return band


def _rel(a, b, mask=None):
    mask = np.ones(a.shape[:2], bool) if mask is None else mask
    return float(np.linalg.norm((a - b)[mask]) / np.linalg.norm(b[mask]))


def test_equiangular_values_at_nodes_and_refined_cells():
    """Where the image is not interpolated it is the equiangular method's (to rounding): at the
    nodes (pixels (4i, 4j)) and at every pixel of a refined cell; and cells are both refined
    and interpolated in this image."""
    ad, eq, _, refined = _renders()
    np.testing.assert_allclose(ad[::4, ::4], eq[::4, ::4], rtol=_EXACT, atol=_EXACT * np.abs(eq).max())
    cells = np.kron(refined, np.ones((4, 4), bool))[:H, :W]
    np.testing.assert_allclose(ad[cells], eq[cells], rtol=_EXACT, atol=_EXACT * np.abs(eq).max())
    assert 0 < refined.mean() < 1, refined.mean()
    assert np.abs(ad[~cells] - eq[~cells]).max() > 0  # interpolated pixels exist: the test has teeth


def test_no_halo_at_silhouettes():
    """Within 2 pixels of a depth edge the in-scattered light is within the 2 % target of the
    256-sample ray march, and it is the equiangular method's own there (silhouette cells are
    evaluated, not interpolated across the jump); the whole image is within the target too."""
    ad, eq, ref, _ = _renders()
    band = _depth_edge_band(_edge_scene())
    assert band.sum() > 300 and np.linalg.norm(ref[band]) > 0.2 * np.linalg.norm(ref)  # lit silhouettes
    assert _rel(ad, ref, band) <= _TARGET, _rel(ad, ref, band)
    np.testing.assert_allclose(ad[band], eq[band], rtol=_EXACT, atol=_EXACT * np.abs(eq).max())
    assert _rel(ad, ref) <= _TARGET, _rel(ad, ref)


def test_no_halo_at_silhouettes_float32():
    """The same in float32 (the benchmarks' precision): within 2 pixels of a depth edge the
    in-scattered light is within the target of the float64 ray march, and every pixel of the band
    lies in a refined cell (the depth-jump test sees the silhouette in float32 too)."""
    _, _, ref, _ = _renders()
    band = _depth_edge_band(_edge_scene())
    with jax.enable_x64(False):
        scene32 = _scene(width=W, height=H, eye=(1.5, 1.0, 5.0), shadow_map=512)
        out = jax.jit(lambda s: render_adaptive(s, return_parts=True, return_refined=True))(scene32)
        assert out[0].dtype == jnp.float32
        fog32, refined32 = np.asarray(sum(out[1][1]), np.float64), np.asarray(out[2])[..., 0]
    assert np.all(np.isfinite(fog32))
    assert _rel(fog32, ref, band) <= _TARGET, _rel(fog32, ref, band)
    cells = np.kron(refined32, np.ones((4, 4), bool))[:H, :W]
    lit_band = band & (np.abs(ref).max(axis=-1) > 1e-3 * np.abs(ref).max())
    assert lit_band.sum() > 100 and np.all(cells[lit_band]), (lit_band.sum(), (~cells[lit_band]).sum())


def test_interpolation_error_stays_within_its_tolerance():
    """Against the equiangular method at every pixel (the same rays), the interpolated cells cost
    less than the tolerance's share: with the default 5 % of the RMS per cell, a fraction of that
    over the image; with nothing refined (an infinite tolerance) far more."""
    scene = _edge_scene()
    ad, eq, _, _ = _renders()
    loose = np.asarray(_fog(_ad(scene, tolerance=1e9, return_parts=True)))
    assert _rel(ad, eq) < 0.25 * 0.05
    assert _rel(loose, eq) > 4 * _rel(ad, eq)


def _loss(p, scene, weights):
    return jnp.sum(weights * render_adaptive(_with(scene, p), samples=12, shadow_map=64, chunk=64, tolerance=1.0))


_LOSS = jax.jit(_loss)
_GRAD = jax.jit(jax.grad(_loss))


def _central(loss, p0: dict, name: str, h_rel: float = 1e-6) -> np.ndarray:
    base = np.asarray(p0[name], dtype=float)
    fd = np.zeros_like(base)
    for idx in np.ndindex(base.shape):
        h = h_rel * max(abs(base[idx]), 1.0)
        plus, minus = base.copy(), base.copy()
        plus[idx] += h
        minus[idx] -= h
        up, down = float(loss({**p0, name: jnp.asarray(plus)})), float(loss({**p0, name: jnp.asarray(minus)}))
        fd[idx] = (up - down) / (2 * h)
    return fd


def test_gradients_match_central_differences():
    """Smooth configuration (no occluder, no light map), 32 x 24 pixels, a loose tolerance: 8 x 6
    cells, some refined (the floor's far edge, the cone's rim) and some lit ones interpolated; the
    written-out VJP of the node and refinement chunks (several chunks: chunk=64) against float64
    central differences (h = 1e-6: at 1e-5 a shadow-map texel flips inside the step)."""
    scene = _scene(sphere=False, width=32, height=24, shadow_map=64)
    weights = jnp.asarray(np.random.default_rng(1).uniform(0.5, 1.5, (24, 32, 3)))
    image, refined = jax.jit(lambda s: render_adaptive(s, samples=12, shadow_map=64, chunk=64, tolerance=1.0,
                                                       return_refined=True))(scene)
    every_pixel = render_equiangular(scene, samples=12, shadow_map=64, prune=False)
    assert 0 < float(jnp.mean(refined)) < 1
    assert float(jnp.abs(image - every_pixel).max()) > 1e-3 * float(jnp.abs(every_pixel).max())  # interpolated
    p0 = _params(scene)
    grad = _GRAD(p0, scene, weights)
    for name in ("rho", "kappa", "K", "intensity", "position"):
        fd = _central(lambda p: _LOSS(p, scene, weights), p0, name)
        assert np.all(np.abs(fd) > 0), name
        np.testing.assert_allclose(np.asarray(grad[name]), fd, rtol=_FD_RTOL, atol=1e-8 * abs(fd).max(), err_msg=name)


def _grid_scene():
    """The smooth configuration in a fog bank: a 3 x 4 x 5 density grid over the cone and the floor."""
    scene = _scene(sphere=False, width=32, height=24, shadow_map=64)
    grid = DensityGrid(np.random.default_rng(7).uniform(0.3, 1.8, (3, 4, 5)), (-2.0, -0.2, -2.5), (2.5, 3.2, 1.5))
    m = scene.medium
    return eqx.tree_at(lambda s: s.medium, scene, Medium(m.rho, m.kappa, m.K, grid))


def _grid_loss(p, scene, weights):
    s = eqx.tree_at(lambda s: s.medium.density.values, _with(scene, p), p["values"])
    return jnp.sum(weights * render_adaptive(s, samples=12, shadow_map=64, chunk=64, tolerance=1.0))


def test_grid_fog_gradients_match_central_differences():
    """Grid fog, default method: d/d(rho, kappa, K, light position) and the derivative along a
    random direction of the grid values (every value at once: the written-out trilinear VJP and
    the chunk loop's) against float64 central differences, cells refined and interpolated."""
    scene = _grid_scene()
    weights = jnp.asarray(np.random.default_rng(2).uniform(0.5, 1.5, (24, 32, 3)))
    refined = jax.jit(lambda s: render_adaptive(s, samples=12, shadow_map=64, chunk=64, tolerance=1.0,
                                                return_refined=True)[1])(scene)
    assert 0 < float(jnp.mean(refined)) < 1
    p0 = {**_params(scene), "values": scene.medium.density.values}
    loss = jax.jit(_grid_loss)
    grad = jax.jit(jax.grad(_grid_loss))(p0, scene, weights)
    for name in ("rho", "kappa", "K", "position"):
        fd = _central(lambda p: loss(p, scene, weights), p0, name)
        assert np.all(np.abs(fd) > 0), name
        np.testing.assert_allclose(np.asarray(grad[name]), fd, rtol=_FD_GRID_RTOL, atol=1e-8 * abs(fd).max(),
                                   err_msg=name)
    direction = np.random.default_rng(3).normal(size=p0["values"].shape)
    h = 1e-6
    up = float(loss({**p0, "values": p0["values"] + h * direction}, scene, weights))
    down = float(loss({**p0, "values": p0["values"] - h * direction}, scene, weights))
    along = float(np.sum(np.asarray(grad["values"]) * direction))
    assert np.count_nonzero(np.asarray(grad["values"])) >= 30  # most of the 60 values reach the image
    np.testing.assert_allclose(along, (up - down) / (2 * h), rtol=_FD_GRID_RTOL)


# -- mip pyramids ---------------------------------------------------------------------------------------------
def _numpy_bilinear(tex: np.ndarray, n: int) -> np.ndarray:
    """tex sampled bilinearly (clamped, texel centres at (i + 1/2) / size) at the centres of an n x n grid."""
    h, w = tex.shape[:2]
    c = (np.arange(n) + 0.5) / n
    y, x = c * h - 0.5, c * w - 0.5
    y0, x0 = np.floor(y).astype(int), np.floor(x).astype(int)
    fy, fx = (y - y0)[:, None, None], (x - x0)[None, :, None]
    ya, yb = np.clip(y0, 0, h - 1), np.clip(y0 + 1, 0, h - 1)
    xa, xb = np.clip(x0, 0, w - 1), np.clip(x0 + 1, 0, w - 1)
    top = tex[ya][:, xa] * (1 - fx) + tex[ya][:, xb] * fx
    bottom = tex[yb][:, xa] * (1 - fx) + tex[yb][:, xb] * fx
    return top * (1 - fy) + bottom * fy


def test_mip_pyramid_matches_numpy():
    """A 6 x 5 RGB map packed with min_side 16: level 0 is its bilinear reconstruction on 16 x 16,
    level k the means of 2^k x 2^k blocks of level 0; `index` reads texel (row, col) of level k at
    uv inside it, `level_for` is floor(log2) clamped."""
    tex = np.random.default_rng(0).uniform(0.0, 1.0, (6, 5, 3))
    mips = pack_mips(tex, min_side=16)
    assert (mips.side, mips.levels, mips.channels) == (16, 5, 3)
    level0 = _numpy_bilinear(tex, 16)
    for k in range(5):
        n = 16 >> k
        expect = level0.reshape(n, 2**k, n, 2**k, 3).mean(axis=(1, 3))
        rows, cols = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        u, v = (cols + 0.5) / n, (rows + 0.5) / n
        got = mips.fetch(mips.index(jnp.asarray(u), jnp.asarray(v), jnp.full(u.shape, k, jnp.int32)))
        np.testing.assert_allclose(np.asarray(got), expect, atol=_MIP_TOL, err_msg=f"level {k}")
    footprints = np.array([0.3, 1.0, 1.99, 2.0, 3.5, 4.0, 15.9, 16.0, 1e6])
    np.testing.assert_array_equal(np.asarray(mips.level_for(jnp.asarray(footprints))),
                                  np.clip(np.floor(np.log2(np.maximum(footprints, 1.0))), 0, 4).astype(int))


def test_gray_map_keeps_one_channel_and_light_builds_its_pyramid():
    """A gray map is stored once (a third of the gathers) and reads back the same as RGB; a light
    builds its pyramid when made, `with_light_map` rebuilds it, a uniform light has none."""
    gray = np.repeat(np.random.default_rng(1).uniform(0.0, 1.0, (8, 8, 1)), 3, axis=-1)
    mips = pack_mips(gray, min_side=8)
    assert mips.channels == 1
    idx = jnp.arange(8 * 8)
    np.testing.assert_allclose(np.asarray(mips.fetch(idx))[:, 0], gray[..., 0].reshape(-1), atol=_MIP_TOL)
    light = SpotLight((0.0, 4.0, 0.0), (0.0, 0.0, 0.0), light_map=gray)
    assert light.mips is not None and light.mips.side == 512 and light.mips.channels == 1
    other = light.with_light_map(np.ones((4, 4, 3)) * np.array([1.0, 0.5, 0.25]))
    assert other.mips.channels == 3 and float(other.mips.texels[0, 1]) == 0.5
    assert SpotLight((0.0, 4.0, 0.0), (0.0, 0.0, 0.0)).mips is None


@pytest.mark.parametrize("size", [64, 256])
def test_light_map_fetch_matches_bilinear_lookup(size):
    """Where the pixel needs the finest level, the pyramid's nearest fetch is the map's bilinear
    lookup to within half a fine texel's slope: a smooth map, uv all over it."""
    y, x = np.meshgrid(*(np.linspace(0, 1, size),) * 2, indexing="ij")
    tex = np.stack([0.5 + 0.5 * np.sin(3 * x + 2 * y), 0.5 + 0.4 * np.cos(4 * y), 0.3 + 0.2 * x * y], axis=-1)
    light = SpotLight((0.0, 4.0, 0.0), (0.0, 0.0, 0.0), light_map=tex)
    uv = jnp.asarray(np.random.default_rng(2).uniform(0.0, 1.0, (500, 2)))
    bilinear = np.asarray(light.map_value(uv))
    fetched = np.asarray(light.map_value(uv, footprint=jnp.full((500,), 1e-6)))
    slope = 5.0 / light.mips.side  # the map's largest slope (per unit uv) times a fine texel
    assert np.abs(fetched - bilinear).max() <= slope

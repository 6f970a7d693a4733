"""Desert rendering (paper 001 sections 3.2-3.7): normal maps, mip averaging, culling, LOD."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrender.app.scenes.desert import desert_frame, desert_scene, to_display
from jaxrender.camera import Camera
from jaxrender.shadows import triangle_height
from jaxrender.terrain import (
    billboard_alpha,
    normal_pyramid,
    plan_quads,
    quad_capacities,
    ray_cast_coherent,
    ray_cast_heightfield,
    ripple_normal_map,
    sand_grain_texture,
)

CENTRAL_DIFF_TOL = 2e-3  # O((k t)^2 / 6) of central differences: k t = 2 pi / 32 -> slope error ~0.6 %
LOD_MEAN_DIFF_MAX = 3.92 / 255  # the paper's mean |LOD - full| over the image (section 4)
EXACT_TOL = 1e-12
RAY_AGREE_MIN = 0.995  # the coherent cast may miss features thinner than its 4-pixel stride
RAY_T_TOL = 1e-3  # both bisect 10 times, from brackets of different widths: relative distance error < 1e-3
SAME_IMAGE_TOL = 1e-9  # float64: the same texels shaded in buffers of other shapes round differently (~1e-14)


def test_normal_map_matches_analytic_sinusoid():
    n, texel, amp = 64, 0.25, 0.3
    x = (np.arange(n) * texel)[None, :] * np.ones((n, 1))
    y = (np.arange(n) * texel)[:, None] * np.ones((1, n))
    k = 2 * np.pi / (n * texel) * 2  # two periods across: periodic
    h = amp * np.sin(k * x) * np.cos(k * y)
    got = np.asarray(ripple_normal_map(jnp.asarray(h), texel_size=texel))
    dx = amp * k * np.cos(k * x) * np.cos(k * y)
    dy = -amp * k * np.sin(k * x) * np.sin(k * y)
    ref = np.stack([-dx, -dy, np.ones_like(h)], -1)
    ref /= np.linalg.norm(ref, axis=-1, keepdims=True)
    np.testing.assert_allclose(got, ref, atol=CENTRAL_DIFF_TOL)
    np.testing.assert_allclose(np.linalg.norm(got, axis=-1), 1.0, atol=EXACT_TOL)


def test_mip_pyramid_averages_four_normals():
    rng = np.random.default_rng(0)
    v = rng.standard_normal((16, 16, 3)) + [0, 0, 3]
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    pyr = normal_pyramid(jnp.asarray(v), levels=4)
    assert [p.shape[0] for p in pyr] == [16, 8, 4, 2]
    ref = v
    for level in pyr[1:]:
        ref = ref[0::2, 0::2] + ref[1::2, 0::2] + ref[0::2, 1::2] + ref[1::2, 1::2]
        ref /= np.linalg.norm(ref, axis=-1, keepdims=True)
        np.testing.assert_allclose(np.asarray(level), ref, atol=EXACT_TOL)


def test_sand_grain_texture_deterministic():
    a = sand_grain_texture(jax.random.key(3), 32)
    b = sand_grain_texture(jax.random.key(3), 32)
    c = sand_grain_texture(jax.random.key(4), 32)
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert not np.allclose(np.asarray(a), np.asarray(c))
    assert abs(float(jnp.mean(a)) - 1.0) < 1e-9 and float(jnp.std(a)) > 0.01


def test_billboard_alpha_profile():
    rho = jnp.asarray([0.0, 0.5, 1.0, 1.5])
    a = np.asarray(billboard_alpha(rho, jnp.asarray(0.8)))
    ref = 1 - np.exp(-0.8 * np.maximum(1 - np.asarray(rho) ** 2, 0) ** 1.5)
    np.testing.assert_allclose(a, ref, atol=EXACT_TOL)
    assert a[0] > a[1] > a[2] == 0.0


@pytest.fixture(scope="module")
def small_desert():
    n = 8
    y, x = np.mgrid[0:n, 0:n] / n * 2 * np.pi
    dunes = 3.0 * np.maximum(np.sin(x + 0.4 * np.sin(y)), 0.0) ** 2 + 0.3 * np.cos(2 * y)
    r = 16
    ry, rx = np.mgrid[0:r, 0:r] / r * 2 * np.pi
    ripples = np.sin(3 * rx + 0.5 * np.sin(ry)) + 0.2 * np.sin(6 * rx)
    scene = desert_scene(dune_field=dunes, ripple_field=ripples, texels=16, seed=1)
    camera = Camera((-1.0, 2.5, 2.2), (5.0, 4.5, 0.0), (0.0, 0.0, 1.0), 45.0, width=96, height=64)
    return scene, camera


def test_coherent_ray_cast_matches_full_march(small_desert):
    scene, camera = small_desert
    dirs = camera.primary_rays()
    t_full, hit_full = jax.jit(lambda d: ray_cast_heightfield(scene.maps.z, camera.eye, d, n_steps=96))(dirs)
    t_coh, hit_coh = jax.jit(lambda d: ray_cast_coherent(scene.maps.z, camera.eye, d))(dirs)
    hit_full, hit_coh = np.asarray(hit_full), np.asarray(hit_coh)
    t_full, t_coh = np.where(hit_full, np.asarray(t_full), 1.0), np.where(hit_coh, np.asarray(t_coh), 1.0)
    assert hit_full.any() and (~hit_full).any()
    assert np.mean(hit_full == hit_coh) >= RAY_AGREE_MIN
    both = hit_full & hit_coh
    err = np.abs(t_full - t_coh)[both] / t_full[both]
    assert np.percentile(err, 99) < RAY_T_TOL
    p = np.asarray(camera.eye)[None, None] + np.asarray(dirs) * np.where(hit_coh, t_coh, 0.0)[..., None]
    surf = np.asarray(triangle_height(scene.maps.z, jnp.asarray(p[..., :2])))
    assert np.max(np.abs(p[..., 2] - surf)[hit_coh]) < RAY_T_TOL  # hits lie on the surface


def test_culling_removes_quads_and_keeps_image(small_desert):
    scene, camera = small_desert
    visible, _ = plan_quads(scene.maps, camera, lod=False, culling=True)
    assert 0 < int(np.sum(np.asarray(visible))) < visible.size  # culling has work to save here
    kw = dict(sun_elevation=15.0, sun_azimuth=200.0, dust=False, dune_shadows=False, ripple_shadows=False)
    full = np.asarray(desert_frame(scene, camera, lod=False, culling=False, **kw))
    culled = np.asarray(desert_frame(scene, camera, lod=False, culling=True, **kw))
    assert np.all(np.isfinite(full)) and np.all(np.isfinite(culled))
    np.testing.assert_allclose(culled, full, atol=SAME_IMAGE_TOL, rtol=0)  # culled quads are never seen
    lod = np.asarray(desert_frame(scene, camera, lod=True, culling=True, **kw))
    caps_lod = quad_capacities(*plan_quads(scene.maps, camera, lod=True), scene.maps.levels)
    assert sum(caps_lod[1:]) > 0  # some quads really are at coarser levels
    diff = np.mean(np.abs(to_display(lod) - to_display(full)))
    assert 0 < diff <= LOD_MEAN_DIFF_MAX, diff


def test_cli_bad_input_exits_2(tmp_path, capsys):
    from jaxrender.app.cli.programs import jaxrender_main as main

    assert main(["desert", "--out", str(tmp_path / "frame.txt")]) == 2
    assert "frame.txt" in capsys.readouterr().err
    assert main(["desert", "--out", str(tmp_path / "missing" / "frame.png")]) == 2
    assert main(["desert", "--out", str(tmp_path / "frame.png"), "--texels", "12"]) == 2
    assert not list(tmp_path.iterdir())  # no partial output

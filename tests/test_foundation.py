"""Shared building blocks against independent references: textures, quantization, camera, I/O."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrender import io, textures
from jaxrender.camera import Camera, look_at_frame

_TOL = 1e-12  # float64 arithmetic on a handful of operations


def _bilinear_reference(tex, u, v):
    """Brute force per the design contract: texel centres at (i + 1/2)/W, clamped border."""
    h, w, _ = tex.shape
    x, y = u * w - 0.5, v * h - 0.5
    out = np.zeros(tex.shape[2])
    for j in range(h):
        for i in range(w):
            wx = max(0.0, 1 - abs(np.clip(x, 0, w - 1) - i))
            wy = max(0.0, 1 - abs(np.clip(y, 0, h - 1) - j))
            out += wx * wy * tex[j, i]
    return out


@pytest.mark.parametrize("jit", [False, True])
def test_bilinear_matches_brute_force(jit):
    rng = np.random.default_rng(0)
    tex = rng.random((5, 7, 3))
    uv = rng.uniform(-0.2, 1.2, (40, 2))
    fn = jax.jit(textures.bilinear) if jit else textures.bilinear
    got = np.asarray(fn(jnp.asarray(tex), jnp.asarray(uv)))
    want = np.stack([_bilinear_reference(tex, u, v) for u, v in uv])
    np.testing.assert_allclose(got, want, atol=_TOL)


def test_bilinear_texel_centres_and_repeat():
    tex = jnp.arange(12.0).reshape(3, 4, 1)
    centres = jnp.array([[(1 + 0.5) / 4, (2 + 0.5) / 3]])
    assert float(textures.bilinear(tex, centres)[0, 0]) == pytest.approx(9.0, abs=_TOL)
    # repeat: u = 0 lies halfway between the last and the first column
    got = textures.bilinear(tex, jnp.array([[0.0, 0.5 / 3]]), wrap="repeat")[0, 0]
    assert float(got) == pytest.approx(0.5 * (0.0 + 3.0), abs=_TOL)


def test_vmap_equals_loop():
    tex = jnp.asarray(np.random.default_rng(1).random((4, 4, 2)))
    uvs = jnp.asarray(np.random.default_rng(2).random((6, 2)))
    batched = jax.vmap(lambda uv: textures.bilinear(tex, uv))(uvs)
    looped = jnp.stack([textures.bilinear(tex, uv) for uv in uvs])
    np.testing.assert_allclose(batched, looped, atol=_TOL)


def test_mip_pyramid_sizes_and_means():
    tex = jnp.asarray(np.random.default_rng(3).random((9, 6, 3)))
    pyr = textures.mip_pyramid(tex)
    assert [p.shape[:2] for p in pyr] == [(9, 6), (5, 3), (3, 2), (2, 1), (1, 1)]
    np.testing.assert_allclose(pyr[1][0, 0], np.asarray(tex[:2, :2]).mean(axis=(0, 1)), atol=_TOL)
    # trilinear at an integer level is that level's bilinear lookup
    uv = jnp.array([[0.3, 0.6]])
    np.testing.assert_allclose(textures.trilinear(pyr, uv, jnp.array([1.0])), textures.bilinear(pyr[1], uv), atol=_TOL)


def test_quantize_levels_and_straight_through():
    x = jnp.linspace(-0.1, 1.2, 50)
    q = textures.quantize(x, 8)
    np.testing.assert_allclose(q * 255, np.round(q * 255), atol=1e-9)
    assert float(jnp.max(jnp.abs(q - jnp.clip(x, 0, 1)))) <= 0.5 / 255 + 1e-12
    grad = jax.grad(lambda v: textures.quantize(v, 8, scale=2.0))(jnp.array(0.77))
    assert float(grad) == pytest.approx(1.0, abs=_TOL)
    assert textures.quantize(x, 0) is x or np.array_equal(textures.quantize(x, 0), x)


def test_camera_centre_ray_and_projection_round_trip():
    cam = Camera([0.0, 1.5, 6.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], 40.0, width=9, height=7)
    d = cam.ray_direction(jnp.array([4.5, 3.5]))
    want = np.array([0.0, -0.5, -6.0]) / np.linalg.norm([0.0, -0.5, -6.0])
    np.testing.assert_allclose(d, want, atol=1e-12)
    rays = cam.primary_rays()
    px, depth = cam.project(cam.eye[None, None, :] + 2.5 * rays)
    np.testing.assert_allclose(px, cam.pixel_centers()[:, :, 0, :], atol=1e-9)
    # top-left pixel looks up and to the left (image row 0 at the top, Mitsuba's x mirroring)
    right, up, _ = cam.frame()
    assert float(rays[0, 0] @ up) > 0 and float(rays[0, 0] @ right) < 0
    x, y, z = look_at_frame(jnp.zeros(3), jnp.array([0.0, 0.0, 1.0]), jnp.array([0.0, 1.0, 0.0]))
    np.testing.assert_allclose(np.stack([x, y, z]), np.eye(3), atol=1e-12)


def test_exr_png_round_trip(tmp_path):
    img = np.random.default_rng(4).random((6, 5, 3)).astype(np.float32) * 4
    io.write_exr(tmp_path / "a.exr", img)
    np.testing.assert_array_equal(io.read_image(tmp_path / "a.exr"), img)
    io.write_png(tmp_path / "a.png", img / 4)
    back = io.read_image(tmp_path / "a.png")
    assert np.max(np.abs(back - img / 4)) < 0.01  # 8-bit sRGB steps are at most ~0.013 in linear near 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.exr", "a.png"]  # no temporaries left


def test_srgb_round_trip_and_reference_points():
    x = jnp.linspace(0, 1, 101)
    np.testing.assert_allclose(io.srgb_to_linear(io.linear_to_srgb(x)), x, atol=1e-12)
    assert float(io.linear_to_srgb(0.5)) == pytest.approx(0.7353569830524495, abs=1e-12)


def test_unreadable_files_raise_input_error(tmp_path):
    bad = tmp_path / "bad.exr"
    bad.write_text("not an exr")
    with pytest.raises(io.InputError, match="bad.exr"):
        io.read_image(bad)
    with pytest.raises(io.InputError, match="no such file"):
        io.read_image(tmp_path / "missing.png")

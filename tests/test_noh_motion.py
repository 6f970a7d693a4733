"""The Noh garment in motion with the polished floor's reflection (jaxrender.app.scenes.noh.motion),
at a small size: the cloth continues frame to frame, what depends on the geometry follows it,
and the floor reflects the garment and the flames without gaining light."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrender.app.scenes.noh import default_btfs, noh_scene
from jaxrender.app.scenes.noh.motion import STAGE_F0, moving_frame_jit, prepare_motion
from jaxrender.app.scenes.noh.scene import garment_rig
from jaxrender.fabric import fresnel_schlick
from sims import BodyMotion, advance_cloth

_ROWS, _COLS = 10, 8


@pytest.fixture(autouse=True, scope="module")
def _implicit_rank_promotion():
    """The Noh scene's own helpers (procedural brocade, flame billboards in `prepare`) broadcast
    (3,) vectors against images implicitly; the strict setting of conftest is relaxed here only."""
    with jax.numpy_rank_promotion("allow"):
        yield


@pytest.fixture(scope="module")
def setup(_implicit_rank_promotion):
    btfs = default_btfs(size=8, pyramid="none")
    scene = noh_scene(width=96, height=64, frames=3, btfs=btfs, cloth_rows=_ROWS, cloth_cols=_COLS, flame_size=(16, 8))
    cloth = garment_rig(_ROWS, _COLS)
    motion = BodyMotion(turn=0.6, turn_period=1.0, sway=0.1, sway_period=0.8, ramp=0.05, axis_z=-0.16)
    rig = prepare_motion(scene, cloth, motion, key=jax.random.key(0), shadow_resolution=64, frame_dt=0.1)
    return scene, cloth, rig


def test_frames_follow_the_moving_garment(setup):
    scene, cloth, rig = setup
    state = cloth.state
    images, masks = [], []
    for i in range(3):
        image, new_state, counts = moving_frame_jit(scene, rig, state, scene.flames[:, i], jax.random.key(i))
        assert int(counts.garment) <= rig.capacity and int(counts.reflection) <= rig.reflection_capacity
        # the cloth continued from the previous frame's state by one frame's steps of the dance
        expected = advance_cloth(cloth, state, rig.motion, steps=rig.steps)
        np.testing.assert_allclose(new_state.x, expected.x, atol=1e-6)
        state = new_state
        images.append(np.asarray(image))
        masks.append(np.asarray(counts.garment_mask))
    assert all(np.all(np.isfinite(im)) and np.all(im >= 0) for im in images)
    # the garment moved on screen (its pixels changed), and with it the shading
    assert np.sum(masks[0] != masks[2]) > 20
    assert np.abs(images[2] - images[0])[masks[0] & masks[2]].mean() > 0


def test_floor_reflection_adds_the_mirrored_scene_within_fresnel(setup):
    """Against the same frame with a matte floor (no coat): the stage in front of the garment gets
    the reflection, never more than F x the brightest radiance it could reflect, while the diffuse
    part loses F."""
    scene, cloth, rig = setup
    matte = dataclasses.replace(rig, floor_coat=jnp.zeros_like(rig.floor_coat))
    args = (scene.flames[:, 0], jax.random.key(5))
    shiny, _, counts = moving_frame_jit(scene, rig, cloth.state, *args)
    dull, _, _ = moving_frame_jit(scene, matte, cloth.state, *args)
    shiny, dull = np.asarray(shiny), np.asarray(dull)
    stage = np.asarray(rig.floor_coat) > 0
    floor = stage & ~np.asarray(counts.garment_mask)
    assert int(counts.reflection) > 0                                  # the garment is mirrored in the stage
    cos = np.clip(-np.asarray(rig.rays)[..., 1], 0, 1)
    f = np.asarray(fresnel_schlick(jnp.asarray(cos), STAGE_F0))[..., None] * stage[..., None]
    # shiny = dull (1 - F) + reflection, reflection in [0, F max(scene radiance)]
    reflection = shiny - dull * (1 - f)
    brightest = max(float(np.max(dull)), float(np.max(np.asarray(scene.flames[:, 0]))),
                    float(np.max(np.asarray(rig.mirrored_sky))))
    assert np.all(reflection[floor] >= -1e-5)
    assert np.all(reflection[floor] <= f[floor] * brightest * (1 + 1e-5))
    assert np.mean(reflection[floor]) > 0
    off = ~stage & ~np.asarray(counts.garment_mask)
    np.testing.assert_allclose(shiny[off], dull[off], atol=1e-6)      # the gravel and the sky do not reflect


def test_half_resolution_floor_firelight_matches_full_resolution(setup):
    """The floor's firelight from its irradiance on 2 x 2 blocks (PCSS there), read back
    bilinearly and times rho_d per pixel (`floor_firelight`), against the general path at every
    floor pixel: PCSS at the pixel and the floor's BRDF (`shade_floor`) under the same samples.
    The same light up to the blur of one block at the shadows' soft edges."""
    from jaxrender.app.scenes.noh.frame import fire_light
    from jaxrender.app.scenes.noh.motion import floor_firelight
    from jaxrender.app.scenes.noh.prepare import fire_visibility
    from jaxrender.app.scenes.noh.shading import shade_floor
    from jaxrender.fabric import depth_map, raster_window, spot_pinhole
    from jaxrender.lights import sample_quad_lights
    from jaxrender.shadows import ShadowMap

    scene, cloth, rig = setup
    x = cloth.state.x
    maps = []
    for q in range(rig.light_position.shape[0]):
        sp = spot_pinhole(rig.light_position[q], rig.light_rotation[q], rig.tan_cutoff, rig.shadow_resolution)
        maps.append(ShadowMap(depth=depth_map(sp, x, cloth.triangles, window=raster_window(sp, x, cloth.triangles)),
                              position=sp.origin, rotation=sp.rotation, tan_cutoff=jnp.asarray(rig.tan_cutoff)))
    samples = sample_quad_lights(scene.fires, jax.random.key(3), 16)
    full_vis = fire_visibility(maps, rig.floor.position, rig.near)
    assert np.any(np.asarray(full_vis) < 0.5)                    # the garment does shadow the floor
    ref = np.asarray(shade_floor(rig.floor, fire_light(samples, rig.floor.position, full_vis, len(maps))))
    got = np.asarray(floor_firelight(rig, samples, fire_visibility(maps, rig.shadow_points, rig.near)))
    err = np.abs(got - ref).sum(-1) / np.mean(ref.sum(-1))      # relative to the floor's mean firelight
    print("floor firelight error: mean", err.mean(), "p99", np.percentile(err, 99), "max", err.max())
    assert ref.max() > 0
    assert np.mean(err) < 0.02                                   # block-sized blur at the soft edges only
    assert np.mean(err > 0.25) < 0.01


def test_split_depth_maps_equal_one_pass(setup):
    """The fires' depth maps rasterized in two windows (most triangles in a small one, the few
    large ones compacted into a large one, `_fire_depth_maps`) against one `depth_map` pass with a
    window covering every triangle, on a pose where some triangles are large: the same map."""
    from jaxrender.app.scenes.noh.motion import _fire_depth_maps
    from jaxrender.fabric import depth_map, raster_window, spot_pinhole

    scene, cloth, rig = setup
    # stretch the garment toward fire 0 so that a few triangles outgrow the small window
    x = np.asarray(cloth.state.x).copy()
    x[: _COLS * 2] += 0.5 * (np.asarray(rig.light_position[0]) - x[: _COLS * 2])
    x = jnp.asarray(x)
    small = dataclasses.replace(rig, shadow_window=4, large_window=64, large_capacity=128)
    maps, largest, most = _fire_depth_maps(small, x, cloth.triangles)
    assert int(most) > 0 and int(most) <= small.large_capacity and float(largest) <= small.large_window
    for q, sm in enumerate(maps):
        sp = spot_pinhole(rig.light_position[q], rig.light_rotation[q], rig.tan_cutoff, rig.shadow_resolution)
        ref = np.asarray(depth_map(sp, x, cloth.triangles, window=raster_window(sp, x, cloth.triangles)))
        got = np.asarray(sm.depth)
        assert np.isfinite(ref).sum() > 50
        np.testing.assert_array_equal(np.isfinite(got), np.isfinite(ref))
        fin = np.isfinite(ref)
        np.testing.assert_allclose(got[fin], ref[fin], rtol=1e-6)   # the same triangle's exact ray hit


def test_garment_boxes_give_the_full_image_frame(setup):
    """The G-buffers rasterized in the boxes around the garment and its mirror image against the
    same frame rasterized over the whole image: the same picture; a box the garment leaves is
    widened by `grown`."""
    from jaxrender.app.scenes.noh.motion import grown

    scene, cloth, rig = setup
    w, h = rig.pinhole.width, rig.pinhole.height
    assert rig.view_box != (0, 0, w, h)                                # the boxes do crop at this size
    full = dataclasses.replace(rig, view_box=(0, 0, w, h), mirror_box=(0, 0, w, h))
    args = (cloth.state, scene.flames[:, 0], jax.random.key(2))
    boxed, _, counts = moving_frame_jit(scene, rig, *args)
    whole, _, _ = moving_frame_jit(scene, full, *args)
    np.testing.assert_allclose(np.asarray(boxed), np.asarray(whole), rtol=1e-5, atol=1e-6)
    same = grown(rig, counts) or rig                                   # (other buffers may grow)
    assert (same.view_box, same.mirror_box) == (rig.view_box, rig.mirror_box)
    tight = dataclasses.replace(rig, view_box=(w // 2, h // 2, 2, 2))
    wider = grown(tight, counts)
    x0, y0, bw, bh = wider.view_box
    b = np.asarray(counts.bounds)[:4]
    assert x0 <= max(b[0], 0) and y0 <= max(b[1], 0) and x0 + bw >= min(b[2], w) and y0 + bh >= min(b[3], h)

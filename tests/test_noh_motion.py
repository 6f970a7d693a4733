"""The Takigi Noh frame (jaxrender.app.scenes.noh.motion) at a small size: the robe continues frame
to frame and what depends on it follows, the same in the sequence loop that simulates the next
frame's robe while a frame renders; the polished floor reflects without gaining light; the
fires' depth maps and the G-buffer in two windows (and a box) equal one pass; the stage's
unit fire irradiance against a dense float64 quadrature; its half-resolution shadows against PCSS
at every pixel."""

import concurrent.futures
import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxrender.app.scenes.noh import default_btfs, noh_scene
from jaxrender.app.scenes.noh.motion import (
    STAGE_F0,
    _cropped,
    fire_depth_maps,
    fire_shadows,
    in_callers_config,
    noh_frame_jit,
    sequence_frames,
    split_rasterize,
)
from jaxrender.app.scenes.noh.performer import performer_mesh
from jaxrender.app.scenes.noh.rig import large_shadow_window, prepare_rig
from jaxrender.app.scenes.noh.stage import FLAME_BASE, FLAME_SIZE, cast_stage
from jaxrender.fabric import depth_map, fresnel_schlick, raster_window, rasterize, spot_pinhole
from jaxrender.shadows import pcss
from sims import advance_costume, noh_dance

_ROBE = dict(rows=12, cols=12, sleeve_rows=4, sleeve_cols=8, settle_steps=400)
_mesh = eqx.filter_jit(performer_mesh)    # the helpers below jitted: eager op-by-op dispatch compiles every op
_depth_maps = eqx.filter_jit(fire_depth_maps)
_split = eqx.filter_jit(split_rasterize)
_shadows = eqx.filter_jit(fire_shadows)
_cast = eqx.filter_jit(cast_stage)
_depth_map = eqx.filter_jit(depth_map)
_rasterize = eqx.filter_jit(rasterize)

UNIT_RTOL = 0.05        # 4 x 2 points over a flame quad against a 64 x 64 quadrature, >= 1 m away
SHADOW_MEAN_TOL = 0.02  # half-resolution PCSS read back bilinearly: a block's blur at the soft edges


@pytest.fixture(autouse=True, scope="module")
def _implicit_rank_promotion():
    """The Noh scene's helpers broadcast (3,) vectors against images implicitly; the strict
    setting of conftest is relaxed here only."""
    with jax.numpy_rank_promotion("allow"):
        yield


@pytest.fixture(scope="module")
def setup(_implicit_rank_promotion):
    # the built-in dance in 1.5 s: it moves from the first frames on
    scene = noh_scene(width=96, height=64, frames=3, btfs=default_btfs(size=8, pyramid="none"), robe=_ROBE,
                      flame_size=(16, 8), motion=noh_dance(duration=1.5), duration=0.6)
    rig = prepare_rig(scene, key=jax.random.key(0), shadow_resolution=64, frame_dt=0.1)
    return scene, rig


def test_frames_follow_the_moving_performer(setup):
    scene, rig = setup
    performer = scene.performer
    state = performer.costume.state
    images, masks, states = [], [], []
    for i in range(3):
        image, new_state, counts = noh_frame_jit(scene, rig, state, scene.flames[:, i], jax.random.key(i))
        assert int(counts.performer) <= rig.capacity and int(counts.reflection) <= rig.reflection_capacity
        expected = advance_costume(performer.costume, state, performer.motion, steps=rig.steps)
        np.testing.assert_allclose(np.asarray(new_state.x), np.asarray(expected.x), atol=1e-9)
        state = new_state
        images.append(np.asarray(image))
        masks.append(np.asarray(counts.performer_mask))
        states.append(np.asarray(state.x))
    # the sequence loop (the next frame's robe simulated in a second thread) makes the same frames
    piped = list(sequence_frames(scene, rig, performer.costume.state, 3,
                                 lambda i: (scene.flames[:, i], jax.random.key(i))))
    assert len(piped) == 3 and all(f.regrown == 0 for f in piped)
    for f, image, x in zip(piped, images, states):
        np.testing.assert_allclose(np.asarray(f.state.x), x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.asarray(f.image), image, rtol=1e-9, atol=1e-12)
    assert all(np.all(np.isfinite(im)) and np.all(im >= 0) for im in images)
    assert masks[0].sum() > 50                                   # the performer is in the picture
    assert np.sum(masks[0] != masks[2]) > 5                       # ... and moved
    assert np.abs(images[2] - images[0]).mean() > 0


def test_the_robe_thread_runs_under_the_callers_jax_configuration():
    """JAX's configuration contexts hold per thread: the sequence loop's worker takes the caller's."""
    def dtype_in_thread(fn):
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            return pool.submit(fn).result()

    probe = lambda: (jnp.zeros(1) + 1.0).dtype  # noqa: E731
    with jax.enable_x64(False):
        assert dtype_in_thread(probe) == jnp.float64          # the tests' global setting, not the context's
        assert dtype_in_thread(in_callers_config(probe)) == jnp.float32
    assert dtype_in_thread(in_callers_config(probe)) == jnp.float64


def test_floor_reflection_adds_the_mirrored_scene_within_fresnel(setup):
    """Against the same frame with a matte floor: the polished floor gets the reflection, never
    more than F x the brightest radiance it could reflect, while its diffuse part loses F."""
    scene, rig = setup
    matte = dataclasses.replace(rig, stage=dataclasses.replace(rig.stage, coat=jnp.zeros_like(rig.stage.coat)))
    state = scene.performer.costume.state
    args = (scene.flames[:, 0], jax.random.key(5))
    shiny, _, counts = noh_frame_jit(scene, rig, state, *args)
    dull, _, _ = noh_frame_jit(scene, matte, state, *args)
    shiny, dull = np.asarray(shiny), np.asarray(dull)
    polished = np.asarray(rig.stage.coat) > 0
    floor = polished & ~np.asarray(counts.performer_mask)
    assert floor.sum() > 100
    cos = np.clip(-np.asarray(rig.rays)[..., 1], 0, 1)
    f = np.asarray(fresnel_schlick(jnp.asarray(cos), STAGE_F0))[..., None] * polished[..., None]
    reflection = shiny - dull * (1 - f)
    brightest = max(float(np.max(dull)), float(np.max(np.asarray(scene.flames[:, 0]))),
                    float(np.max(np.asarray(rig.mirror.env))), float(np.max(np.asarray(rig.mirrored_sky))))
    assert np.all(reflection[floor] >= -1e-6)
    assert np.all(reflection[floor] <= f[floor] * brightest * (1 + 1e-5))
    assert np.mean(reflection[floor]) > 0
    off = ~polished & ~np.asarray(counts.performer_mask)
    np.testing.assert_allclose(shiny[off], dull[off], atol=1e-6)   # the gravel, walls and sky do not reflect


def test_split_depth_maps_equal_one_pass(setup):
    """Most triangles in a small window, the large ones compacted into a large one, combined by
    their minimum, against one `depth_map` pass whose window covers every triangle."""
    scene, rig = setup
    mesh = _mesh(scene.performer, scene.performer.costume.state)
    small = dataclasses.replace(rig, shadow_window=4, large_window=64, large_capacity=mesh.triangles.shape[0])
    maps, largest, most = _depth_maps(small, mesh.vertices, mesh.triangles)
    assert 0 < int(most) <= small.large_capacity and float(largest) <= small.large_window
    for q in range(rig.light_position.shape[0]):
        sp = spot_pinhole(rig.light_position[q], rig.light_rotation[q], rig.tan_cutoff, rig.shadow_resolution)
        ref = np.asarray(_depth_map(sp, mesh.vertices, mesh.triangles,
                                    window=raster_window(sp, mesh.vertices, mesh.triangles)))
        got = np.asarray(maps.depth[q])
        assert np.isfinite(ref).sum() > 20
        np.testing.assert_array_equal(np.isfinite(got), np.isfinite(ref))
        fin = np.isfinite(ref)
        np.testing.assert_allclose(got[fin], ref[fin], rtol=1e-6)


def test_boxed_split_g_buffer_equals_one_full_image_pass(setup):
    """The performer's G-buffer as a frame makes it (in the box around its path, most triangles in a
    small window and the large ones in a large one, merged by distance) against one `rasterize`
    over the whole image with a window covering every triangle: the same pixels."""
    scene, rig = setup
    mesh = _mesh(scene.performer, scene.performer.costume.state)
    x0, y0, bw, bh = rig.view_box
    assert (bw, bh) != (rig.pinhole.width, rig.pinhole.height)          # the box does crop at this size
    got, largest, n_large = _split(_cropped(rig.pinhole, rig.view_box), mesh.vertices, mesh.triangles, mesh.uv,
                                   window=4, large_window=64, large_capacity=mesh.triangles.shape[0])
    assert int(n_large) > 0 and float(largest) <= 64
    ref = _rasterize(rig.pinhole, mesh.vertices, mesh.triangles, mesh.uv,
                     window=raster_window(rig.pinhole, mesh.vertices, mesh.triangles))
    crop = (slice(y0, y0 + bh), slice(x0, x0 + bw))
    assert float(np.asarray(ref.hit).sum()) == float(np.asarray(got.hit).sum()) > 50   # all of it inside the box
    np.testing.assert_array_equal(np.asarray(got.hit), np.asarray(ref.hit)[crop])
    hit = np.asarray(got.hit) > 0
    np.testing.assert_array_equal(np.asarray(got.triangle)[hit], np.asarray(ref.triangle)[crop][hit])
    np.testing.assert_allclose(np.asarray(got.position)[hit], np.asarray(ref.position)[crop][hit], atol=1e-9)


def test_stage_unit_fire_irradiance_matches_a_dense_quadrature(setup):
    """Each fire's irradiance per unit radiance at the stage's pixels (summed over the flame's
    cells, times the stage's shadow toward the flame's centre) against 64 x 64 points in float64,
    where the fire is not hidden: at the points above the baskets' rim (which no basket hides a
    flame from: the flames are above the rim too)."""
    scene, rig = setup
    st = rig.stage
    pos = np.asarray(rig.pinhole.origin)[None] + np.asarray(st.t).reshape(-1)[np.asarray(st.index)][:, None] * \
        np.asarray(rig.rays).reshape(-1, 3)[np.asarray(st.index)]
    hits = _cast(scene.stage, jnp.broadcast_to(rig.pinhole.origin, (pos.shape[0], 3)),
                      jnp.asarray(np.asarray(rig.rays).reshape(-1, 3)[np.asarray(st.index)]))
    normal = np.asarray(hits.normal, np.float64)
    fl = scene.fires
    s = (np.arange(64) + 0.5) / 64 * 2 - 1
    ss, tt = np.meshgrid(s, s)
    checked = 0
    for q in range(fl.center.shape[0]):
        y = np.asarray(fl.center[q]) + ss.reshape(-1, 1) * np.asarray(fl.u[q]) + tt.reshape(-1, 1) * np.asarray(fl.v[q])
        d = y[None] - pos[:, None]
        r2 = np.sum(d * d, -1)
        cos = np.maximum(np.einsum("nmk,nk->nm", d, normal), 0) / np.sqrt(r2)
        ref = np.sum(cos / r2, -1) * (FLAME_SIZE[0] * FLAME_SIZE[1] / 64 ** 2)
        got = np.asarray(st.fire_unit[:, q], np.float64).sum(axis=(1, 2))
        far = np.min(np.sqrt(r2), -1) > 1.0
        lit = far & (got > 0.5 * ref) & (ref > 1e-4) & (pos[:, 1] >= FLAME_BASE)
        checked += lit.sum()
        np.testing.assert_allclose(got[lit], ref[lit], rtol=UNIT_RTOL)
        assert np.all(got[far] <= ref[far] * (1 + UNIT_RTOL) + 1e-9)   # shadows only take light away
    assert checked > 1000


def test_half_resolution_stage_shadows_match_pcss_at_every_pixel(setup):
    scene, rig = setup
    mesh = _mesh(scene.performer, scene.performer.costume.state)
    maps, _, _ = _depth_maps(rig, mesh.vertices, mesh.triangles)
    _, half = _shadows(rig, maps, mesh.vertices[:4])
    st = rig.stage
    pos = np.asarray(rig.pinhole.origin)[None] + np.asarray(st.t).reshape(-1)[np.asarray(st.index)][:, None] * \
        np.asarray(rig.rays).reshape(-1, 3)[np.asarray(st.index)]
    full = jax.jit(jax.vmap(lambda sm, p: pcss(sm, p, light_size=float(FLAME_SIZE[0]), near=rig.near, bias=0.02),
                            in_axes=(0, None)))(maps, jnp.asarray(pos))
    full, half = np.asarray(full), np.asarray(half)
    assert np.any(full < 0.5)                                     # the performer does shadow the stage
    err = np.abs(half - full)
    print("stage shadow error: mean", err.mean(), "p99", np.percentile(err, 99))
    assert err.mean() < SHADOW_MEAN_TOL and np.mean(err > 0.5) < 0.01


def test_large_triangle_window_never_larger_than_the_map():
    """The depth maps' window for large triangles: the extent's power of two, at most the map's;
    and a map-sized window still draws a triangle that spans the whole map (its window's origin
    is clipped to the map), as a brute-force point-in-triangle test over every texel says."""
    assert large_shadow_window(40.0, 512) == 64 and large_shadow_window(514.0, 512) == 512
    assert large_shadow_window(1500.0, 512) == 512 and large_shadow_window(300.0, 300) == 512
    ph = spot_pinhole(jnp.zeros(3), jnp.eye(3), 1.0, 32)          # looking along +z, 90 degrees
    tri = jnp.asarray([[-40.0, -40.0, 2.0], [40.0, -40.0, 2.0], [0.5, 1.0, 2.0]])   # two corners far beyond the map
    depth = np.asarray(depth_map(ph, tri, jnp.asarray([[0, 1, 2]]), window=large_shadow_window(32.0, 32)))
    px = np.asarray(ph.project(tri)[0])
    y, x = np.mgrid[0:32, 0:32] + 0.5
    side = [(px[j, 0] - px[i, 0]) * (y - px[i, 1]) - (px[j, 1] - px[i, 1]) * (x - px[i, 0])
            for i, j in ((0, 1), (1, 2), (2, 0))]
    inside = np.all([d >= 0 for d in side], axis=0) | np.all([d <= 0 for d in side], axis=0)
    assert 0 < inside.sum() < 32 * 32
    np.testing.assert_array_equal(np.isfinite(depth), inside)

"""One frame of the Takigi Noh sequence, everything that moves redone each frame (`noh_frame`):
the robe's Verlet steps on the skeleton's motion (`advance_robe`), then the frame of the new pose
(`frame_image`): the performer's mesh, its G-buffer and its mirror image's, the fires' depth maps,
PCSS at the performer's points and at the stage's, the shading (BTFs, environment, firelight), the
stage's light, the floors' reflection and the flames; and the sequence loop (`sequence_frames`,
`render_sequence`), which simulates the next frame's robe in a second thread while a frame renders.

How the frame is composed and what keeps it near a second on two cores: docs/noh.md, "A frame"."""

from __future__ import annotations

import concurrent.futures
import dataclasses
import time
from collections.abc import Iterator
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from jaxrender.fabric import (
    GBuffer,
    Pinhole,
    depth_map,
    fresnel_schlick,
    glossy_blur_pixels,
    glossy_reflection,
    mirror_mesh,
    rasterize,
    reflect_directions,
    reflect_points,
    spot_pinhole,
    tangent_frames,
)
from jaxrender.lights import sample_quad_lights
from jaxrender.shadows import ShadowMap, pcss
from jaxrender.textures import bilinear
from sims import ClothState, advance_costume

from .performer import PerformerMesh, performer_mesh
from .rig import (
    FlamePixels,
    NohRig,
    cell_radiance,
    large_shadow_window,
    pixel_box,
    pow2,
    prepare_rig,
    projected_bounds,
    round_up,
)
from .scene import NohScene
from .shading import (
    PerformerPoints,
    fire_light,
    performer_points,
    shade_performer,
    shared_light,
    with_light,
)
from .stage import FLAME_SIZE

STAGE_F0 = 0.04          # reflectance at normal incidence of the waxed hinoki (a coat of index ~1.5)


class FrameCounts(eqx.Module):
    """What a frame needed, for the host to check against the rig's fixed sizes, and where the
    performer is in the image (for the sequence's exposure)."""

    performer_mask: Array
    performer: Array
    reflection: Array
    view_extent: Array      # the largest triangle's extent in pixels, in the view or its mirror image
    view_large: Array       # ... how many triangles outgrew the small window
    shadow_extent: Array
    shadow_large: Array
    bounds: Array           # (x0, y0, x1, y1) in pixels of the performer's vertices, then of its mirror image's


def _extents(ph: Pinhole, vertices: Array, triangles: Array) -> Array:
    """Each triangle's projected bounding box, in pixels (what `raster_window` measures)."""
    px, _ = ph.project(vertices)
    x, y = px[..., 0][triangles], px[..., 1][triangles]
    ext = []
    for c, size in ((x, ph.width), (y, ph.height)):
        lo = jnp.clip(jnp.floor(jnp.min(c, axis=1) - 0.5), 0, size)
        hi = jnp.clip(jnp.ceil(jnp.max(c, axis=1) + 0.5), 0, size)
        ext.append(hi - lo)
    return jnp.maximum(ext[0], ext[1])


def _cropped(ph: Pinhole, box: tuple[int, int, int, int]) -> Pinhole:
    """The camera restricted to the pixel rectangle `box`: the same rays for those pixels."""
    x0, y0, w, h = box
    return Pinhole(ph.origin, ph.rotation, ph.fx, ph.fy, ph.cx - x0, ph.cy - y0, w, h)


def _placed(a: Array, box: tuple[int, int, int, int], ph: Pinhole, fill) -> Array:
    """An image of `box` placed in the full image, `fill` around it."""
    x0, y0, w, h = box
    pad = ((y0, ph.height - y0 - h), (x0, ph.width - x0 - w)) + ((0, 0),) * (a.ndim - 2)
    return jnp.pad(a, pad, constant_values=fill)


def _full_index(index: Array, box: tuple[int, int, int, int], ph: Pinhole) -> Array:
    """Flat pixel indices in `box` as flat indices of the full image (out-of-box padding -> H W)."""
    x0, y0, w, h = box
    full = (index // w + y0) * ph.width + index % w + x0
    return jnp.where(index >= w * h, ph.width * ph.height, full)


def _compact(mask: Array, capacity: int) -> tuple[Array, Array, Array]:
    """(scatter index with out-of-range padding, gather index clipped into range, count)."""
    flat = mask.reshape(-1)
    n = flat.shape[0]
    index = jnp.nonzero(flat, size=capacity, fill_value=n)[0].astype(jnp.int32)
    return index, jnp.minimum(index, n - 1), jnp.sum(flat.astype(jnp.int32))


def split_rasterize(ph: Pinhole, x: Array, triangles: Array, uv: Array, *, window: int, large_window: int,
                    large_capacity: int) -> tuple[GBuffer, Array, Array]:
    """The G-buffer of a mesh with most triangles rasterized in `window` and the few larger ones
    (at most `large_capacity`, compacted) in `large_window`, nearest of the two per pixel (the
    same G-buffer as one pass with the large window; docs/noh.md). Also the largest extent
    and how many triangles were large."""
    ext = _extents(ph, x, triangles)
    large = ext > window
    n_tri = triangles.shape[0]
    padded = jnp.concatenate([triangles, jnp.zeros((1, 3), triangles.dtype)])
    pick = jnp.nonzero(large, size=large_capacity, fill_value=n_tri)[0].astype(triangles.dtype)
    small = rasterize(ph, x, jnp.where(large[:, None], 0, triangles), uv, window=window)
    big = rasterize(ph, x, padded[pick], uv, window=large_window)
    big = eqx.tree_at(lambda g: g.triangle, big, jnp.where(big.hit > 0, pick[jnp.maximum(big.triangle, 0)], -1))
    nearer = big.distance < small.distance
    merged = jax.tree_util.tree_map(
        lambda a, b: jnp.where(nearer.reshape(nearer.shape + (1,) * (a.ndim - 2)), b, a), small, big)
    return merged, jnp.max(ext), jnp.sum(large.astype(jnp.int32))


def fire_depth_maps(rig: NohRig, x: Array, triangles: Array) -> tuple[ShadowMap, Array, Array]:
    """The performer's depth map from each fire (one `ShadowMap` with a leading fire axis), the
    largest triangle extent and the most large triangles (one traced pass, vmapped over fires).

    Most triangles are rasterized in `rig.shadow_window`, the few larger ones (at most
    `rig.large_capacity`, compacted) in `rig.large_window`, the two maps combined by their minimum
    (a z-buffer of the union: the same map as one pass; docs/noh.md). Degenerate triangles
    (0, 0, 0) pad both sets and cover nothing."""
    n_tri = triangles.shape[0]
    padded = jnp.concatenate([triangles, jnp.zeros((1, 3), triangles.dtype)])

    def one(position, rotation):
        sp = spot_pinhole(position, rotation, rig.tan_cutoff, rig.shadow_resolution)
        ext = _extents(sp, x, triangles)
        large = ext > rig.shadow_window
        small = jnp.where(large[:, None], 0, triangles)
        big = padded[jnp.nonzero(large, size=rig.large_capacity, fill_value=n_tri)[0]]
        depth = jnp.minimum(depth_map(sp, x, small, window=rig.shadow_window),
                            depth_map(sp, x, big, window=rig.large_window))
        return depth, jnp.max(ext), jnp.sum(large.astype(jnp.int32))

    depth, largest, most = jax.vmap(one)(rig.light_position, rig.light_rotation)
    tan_c = jnp.full(depth.shape[:1], rig.tan_cutoff, x.dtype)
    return ShadowMap(depth=depth, position=rig.light_position, rotation=rig.light_rotation, tan_cutoff=tan_c), \
        jnp.max(largest), jnp.max(most)


def _mirror_back(points: PerformerPoints, up: Array) -> PerformerPoints:
    """Points rasterized from the mirrored mesh, as the real points they show: position, view
    direction (toward the floor point) and shading frame reflected back."""
    origin = jnp.zeros(3, points.position.dtype)
    frame = tangent_frames(reflect_directions(points.frame[:, 2], up), reflect_directions(points.frame[:, 0], up))
    return eqx.tree_at(lambda p: (p.position, p.wo, p.frame), points,
                       (reflect_points(points.position, origin, up), reflect_directions(points.wo, up), frame))


def _flames(pixels: FlamePixels, emission: Float[Array, "Q Hf Wf 3"], t_stop: Float[Array, "H W"]) -> Array:
    """The flames' radiance at `pixels` where each quad lies before `t_stop` (the surface behind)."""
    stop = t_stop.reshape(-1)[pixels.index]
    out = jnp.zeros(pixels.index.shape + (3,), emission.dtype)
    for q in range(emission.shape[0]):  # four fires: unrolled
        hit = pixels.inside[q] * (pixels.t[q] < stop).astype(emission.dtype)
        out = out + hit[:, None] * bilinear(emission[q], pixels.uv[q], wrap="clamp")
    return out


def fire_shadows(rig: NohRig, maps: ShadowMap, points: Float[Array, "N 3"]
                 ) -> tuple[Float[Array, "N Q"], Float[Array, "Q P"]]:
    """PCSS per fire (one traced pass, vmapped over fires): at the performer's `points`, and at the
    half-resolution stage points inside that fire's frustum, which are read back bilinearly at
    every stage pixel (1 outside the frustum; docs/noh.md)."""
    grid = rig.shadow_grid
    hh, hw = grid.shape
    n = points.shape[0]

    def one(sm, stage_points, cell):
        vis = pcss(sm, jnp.concatenate([points, stage_points]), light_size=float(FLAME_SIZE[0]), near=rig.near,
                   bias=0.02)
        image = jnp.ones((hh * hw,), vis.dtype).at[cell].set(vis[n:], mode="drop").reshape(hh, hw, 1)
        return vis[:n], bilinear(image, rig.stage.shadow_uv)[:, 0]

    at_points, at_stage = jax.vmap(one)(maps, grid.points, grid.cell)
    return at_points.T, at_stage


def noh_frame(scene: NohScene, rig: NohRig, state: ClothState, emission: Float[Array, "Q Hf Wf 3"],
              key: PRNGKeyArray, *, k_fire: int = 20, blend: str = "shading"
              ) -> tuple[Float[Array, "H W 3"], ClothState, FrameCounts]:
    """One frame (module docstring): the robe advanced by a frame on the motion (`advance_robe`),
    then the view, shadows, lighting and reflection of the new pose (`frame_image`). Returns the
    linear image, the robe's new state and the frame's counts."""
    state = advance_robe(scene, state, rig.steps)
    image, counts = frame_image(scene, rig, state, emission, key, k_fire=k_fire, blend=blend)
    return image, state, counts


def advance_robe(scene: NohScene, state: ClothState, steps: int) -> ClothState:
    """The robe `steps` Verlet steps on from `state`, on the performer's motion."""
    return advance_costume(scene.performer.costume, state, scene.performer.motion, steps=steps)


def frame_image(scene: NohScene, rig: NohRig, state: ClothState, emission: Float[Array, "Q Hf Wf 3"],
                key: PRNGKeyArray, *, k_fire: int = 20, blend: str = "shading"
                ) -> tuple[Float[Array, "H W 3"], FrameCounts]:
    """The frame of the robe's `state` (the body at its time): the linear image and its counts."""
    performer = scene.performer
    mesh = performer_mesh(performer, state)
    x, tris = mesh.vertices, mesh.triangles
    dtype = x.dtype
    ph = rig.pinhole
    h, w = ph.height, ph.width
    up = jnp.asarray([0.0, 1.0, 0.0], dtype)
    pick = lambda m, gb, idx: performer_points(ph, m, scene.labels, scene.colours, scene.tiles, gb, idx)  # noqa: E731

    # what the camera sees of the performer, in front of the stage (rasterized in its box)
    vb, mb = rig.view_box, rig.mirror_box
    split = dict(window=rig.window, large_window=rig.large_view_window, large_capacity=rig.large_view_capacity)
    gb, g_extent, g_large = split_rasterize(_cropped(ph, vb), x, tris, mesh.uv, **split)
    in_box = (gb.hit > 0) & (gb.distance < rig.stage.t[vb[1]:vb[1] + vb[3], vb[0]:vb[0] + vb[2]])
    g_scatter, g_gather, g_count = _compact(in_box, rig.capacity)
    points = pick(mesh, gb, g_gather)
    g_scatter = _full_index(g_scatter, vb, ph)
    seen = _placed(in_box, vb, ph, False)
    g_distance = _placed(gb.distance, vb, ph, jnp.inf)

    maps, shadow_extent, shadow_large = fire_depth_maps(rig, x, tris)

    # the mirrored performer: what the polished floors reflect, as real points seen from the floor
    mv, mn, mt = mirror_mesh(x, mesh.normals, tris, jnp.zeros(3, dtype), up)
    gbr, r_extent, r_large = split_rasterize(_cropped(ph, mb), mv, mt, mesh.uv, **split)
    in_mirror = (slice(mb[1], mb[1] + mb[3]), slice(mb[0], mb[0] + mb[2]))
    reflects = (gbr.hit > 0) & (gbr.distance < rig.mirror.stop[in_mirror]) & ~seen[in_mirror]
    r_scatter, r_gather, r_count = _compact(reflects, rig.reflection_capacity)
    mirrored = _mirror_back(pick(PerformerMesh(mv, mn, mesh.uv, mt), gbr, r_gather), up)
    r_scatter = _full_index(r_scatter, mb, ph)
    r_distance = jnp.where(_placed(reflects, mb, ph, False), _placed(gbr.distance, mb, ph, jnp.inf), rig.mirror.stop)

    n_g = points.position.shape[0]
    vis, shade = fire_shadows(rig, maps, jnp.concatenate([points.position, mirrored.position]))

    # light: the environment's samples, the frame's flames
    fires = eqx.tree_at(lambda f: f.emission, scene.fires, emission)
    samples = sample_quad_lights(fires, key, k_fire)
    fire_xz = fires.center[:, jnp.asarray([0, 2])]

    def light(p, v):
        return with_light(shared_light(rig.env_direction, rig.env_weight, p.position.shape[0]),
                          fire_light(samples, p.position, v, fire_xz))

    g_rad = shade_performer(scene.mats, points, light(points, vis[:n_g]), blend=blend)
    r_rad = shade_performer(scene.mats, mirrored, light(mirrored, vis[n_g:]), blend="nearest")

    # the stage: its static light, each fire's light by its cells' mean radiance this frame,
    # past the performer's shadow
    cells = cell_radiance(emission)                                             # Q B G 3
    st = rig.stage
    s_rad = st.env + st.rho_d / jnp.pi * jnp.einsum("pqbg,pq,qbgc->pc", st.fire_unit, shade.T, cells)
    mi = rig.mirror
    m_rad = mi.env + mi.rho_d / jnp.pi * jnp.einsum("mqbg,qbgc->mc", mi.fire_unit, cells)

    # the reflection: the mirrored stage, sky, performer and flames, blurred by the roughness, times Fresnel
    reflected = rig.mirrored_sky.reshape(h * w, 3).at[mi.index].set(m_rad)
    reflected = reflected.at[r_scatter].set(r_rad, mode="drop")
    reflected = reflected.at[rig.mirrored_flames.index].add(_flames(rig.mirrored_flames, emission, r_distance))
    reflected = reflected.reshape(h, w, 3)
    beyond = jnp.where(_placed(reflects, mb, ph, False), r_distance - st.t, rig.mirror.beyond)
    cos = jnp.clip(-rig.rays[..., 1], 0.0, 1.0)
    to_floor = jnp.where(jnp.isfinite(st.t), st.t, 0.0)
    blur = glossy_blur_pixels(rig.roughness, beyond, to_floor, ph.fy)
    mirror_light = st.coat[..., None] * glossy_reflection(reflected, blur, cos, f0=STAGE_F0)
    fresnel = st.coat * fresnel_schlick(cos, STAGE_F0)

    # compose: sky, stage (diffuse x (1 - F) + reflection), performer, visible flames
    img = rig.background.reshape(h * w, 3)
    img = img.at[st.index].set(s_rad * (1 - fresnel.reshape(-1)[st.index])[:, None]
                               + mirror_light.reshape(-1, 3)[st.index])
    img = img.at[g_scatter].set(g_rad, mode="drop")
    surface_t = jnp.where(seen, g_distance, st.t)
    img = img.at[rig.flames.index].add(_flames(rig.flames, emission, surface_t)).reshape(h, w, 3)
    counts = FrameCounts(seen, g_count, r_count, jnp.maximum(g_extent, r_extent), jnp.maximum(g_large, r_large),
                         shadow_extent, shadow_large,
                         jnp.concatenate([projected_bounds(ph, x), projected_bounds(ph, mv)]))
    return img, counts


noh_frame_jit = eqx.filter_jit(noh_frame)
advance_robe_jit = eqx.filter_jit(advance_robe)
frame_image_jit = eqx.filter_jit(frame_image)


def _inside(bounds, box: tuple[int, int, int, int], ph: Pinhole) -> bool:
    """Whether the projected `bounds` lie in `box` (or the box is clipped by the image there)."""
    x0, y0, w, h = box
    b = [float(v) for v in bounds]
    return ((b[0] >= x0 or x0 == 0) and (b[1] >= y0 or y0 == 0) and (b[2] <= x0 + w or x0 + w == ph.width)
            and (b[3] <= y0 + h or y0 + h == ph.height))


def grown(rig: NohRig, counts: FrameCounts) -> NohRig | None:
    """A rig with larger buffers if the frame's `counts` overflowed this one's (None if it fit)."""
    changes = {}
    if int(counts.performer) > rig.capacity:
        changes["capacity"] = round_up(1.25 * int(counts.performer))
    if int(counts.reflection) > rig.reflection_capacity:
        changes["reflection_capacity"] = round_up(1.25 * int(counts.reflection))
    if float(counts.view_extent) > rig.large_view_window:
        changes["large_view_window"] = pow2(float(counts.view_extent))
    if int(counts.view_large) > rig.large_view_capacity:
        changes["large_view_capacity"] = round_up(1.25 * int(counts.view_large), 64)
    shadow_window = large_shadow_window(float(counts.shadow_extent), rig.shadow_resolution)
    if shadow_window > rig.large_window:
        changes["large_window"] = shadow_window
    bounds = np.asarray(counts.bounds)
    for name, b in (("view_box", bounds[:4]), ("mirror_box", bounds[4:])):
        old = getattr(rig, name)
        if not _inside(b, old, rig.pinhole):   # the union of the old box and the new one
            new = pixel_box(b, rig.pinhole, 0.1)
            lo = (min(old[0], new[0]), min(old[1], new[1]))
            changes[name] = (*lo, max(old[0] + old[2], new[0] + new[2]) - lo[0],
                             max(old[1] + old[3], new[1] + new[3]) - lo[1])
    if int(counts.shadow_large) > rig.large_capacity:
        changes["large_capacity"] = round_up(1.25 * int(counts.shadow_large), 64)
    if not changes:
        return None
    return dataclasses.replace(rig, **changes)


def in_callers_config(fn):
    """`fn` to be run in another thread under this thread's JAX configuration: JAX's context
    managers (`jax.enable_x64`, the promotion rules) hold per thread, so a worker thread would
    otherwise trace under the global settings (float32 where the caller asked for float64)."""
    x64 = jax.config.jax_enable_x64
    rank, dtypes = jax.config.jax_numpy_rank_promotion, jax.config.jax_numpy_dtype_promotion

    def run(*args):
        with jax.enable_x64(x64), jax.numpy_rank_promotion(rank), jax.numpy_dtype_promotion(dtypes):
            return fn(*args)

    return run


class SequenceFrame(NamedTuple):
    """One frame of `sequence_frames`."""

    image: Float[Array, "H W 3"]
    state: ClothState          # the robe as rendered
    counts: FrameCounts
    rig: NohRig                # the rig it was rendered with (grown when a buffer overflowed)
    regrown: int               # how many times its buffers were grown (one compile each)


def sequence_frames(scene: NohScene, rig: NohRig, state: ClothState, count: int, frame_args, *, k_fire: int = 20
                    ) -> Iterator[SequenceFrame]:
    """`count` frames continuing the robe from `state`, each as `noh_frame` makes it (`frame_args(i)`:
    frame i's emission and key); a frame whose counts overflow the rig is rendered again with grown
    buffers, which later frames keep. The robe of the next frame is simulated in a worker thread
    while this one renders: its Verlet steps are small sequential kernels that keep about one core
    busy however many there are, so on two cores a frame's wall time comes nearer the larger of the
    two parts than their sum (docs/noh.md, "A frame")."""
    steps = rig.steps
    advance = in_callers_config(lambda st: jax.block_until_ready(advance_robe_jit(scene, st, steps)))

    with concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="robe") as pool:
        ahead = pool.submit(advance, state)
        for i in range(count):
            state = ahead.result()
            if i + 1 < count:
                ahead = pool.submit(advance, state)
            regrown = 0
            while True:
                image, counts = jax.block_until_ready(frame_image_jit(scene, rig, state, *frame_args(i), k_fire=k_fire))
                bigger = grown(rig, counts)
                if bigger is None:
                    break
                rig, regrown = bigger, regrown + 1
            yield SequenceFrame(image, state, counts, rig, regrown)


def render_sequence(scene: NohScene, *, frames: int, key: PRNGKeyArray, k_env: int = 20, k_fire: int = 20,
                    frame_dt: float = 0.1, shadow_resolution: int = 512, progress=None, time_repeats: int = 0,
                    info: dict | None = None, states: list | None = None) -> tuple[list[np.ndarray], NohRig]:
    """`frames` frames `frame_dt` s apart (the flames cycle through their frames), each
    continuing the robe from the previous one; then `time_repeats` more frames (continuing the
    dance, discarded) timed into `info["timed_s"]`. A frame that needs larger buffers than the
    rig has is rendered again with grown ones (one more compile). `info` also gets `prepare_s`,
    `compile_s` (the first frame), `frame_s`, `recompiles` and `performer_mask` (frame 0); `states`
    (a list) each frame's robe state as rendered (`performer.performer_mesh` of it is the frame's mesh)."""
    k_env_key, k_frames = jax.random.split(key)
    t0 = time.perf_counter()
    rig = jax.block_until_ready(prepare_rig(scene, key=k_env_key, k_env=k_env, shadow_resolution=shadow_resolution,
                                            frame_dt=frame_dt))
    prepare_s = time.perf_counter() - t0
    n_flames = scene.flames.shape[1]
    out, seconds, recompiles, mask0 = [], [], 0, None
    frame_args = lambda i: (scene.flames[:, i % n_flames], jax.random.fold_in(k_frames, i))  # noqa: E731
    total = frames + time_repeats
    ts = time.perf_counter()
    # timing: one frame more, so that the last frame timed has its successor's robe to simulate too
    for i, frame in enumerate(sequence_frames(scene, rig, scene.performer.costume.state,
                                              total + (time_repeats > 0), frame_args, k_fire=k_fire)):
        if i == total:
            break
        seconds.append(time.perf_counter() - ts)
        rig, recompiles = frame.rig, recompiles + frame.regrown
        if i == 0:
            mask0 = np.asarray(frame.counts.performer_mask)
        if i < frames:
            out.append(np.asarray(frame.image, np.float32))
            if states is not None:
                states.append(frame.state)
            if progress is not None:
                progress(1)
        ts = time.perf_counter()
    if info is not None:
        info.update(prepare_s=prepare_s, compile_s=seconds[0], frame_s=seconds[1:frames],
                    timed_s=seconds[frames:], recompiles=recompiles, performer_mask=mask0)
    return out, rig

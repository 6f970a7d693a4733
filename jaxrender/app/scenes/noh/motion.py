"""The Noh garment in motion, reflected in the polished stage floor (paper 004 sections 4.3 and
4.5), every frame computed from the geometry of that frame.

The garment (`sims.drape_garment`) is driven by a procedural dance (`sims.BodyMotion`: a slow
turn and sway, the hands lifting): each frame continues the Verlet simulation from the previous
frame's state (`sims.advance_cloth`, `steps` steps of the cloth's dt), then everything that
depends on the geometry follows it in the same jitted call (`moving_frame`): the rasterized
G-buffer and the garment's pixels (compacted into a fixed capacity), mip selection from their uv
derivatives, the garment's depth map from each fire and PCSS for every garment point and for the
floor, I_static of the garment (K_env environment samples) and the firelight (K_f samples of the
frame's flames), and the reflection in the floor.

What keeps that within about a second on two CPU cores, each exact or measured:
- the G-buffers are rasterized in boxes around the garment and its mirror image (`view_box`,
  `mirror_box`), not the whole image (the same pixels; `grown` widens a box the dance leaves);
- the fires' depth maps rasterize most triangles in a small window and the dance's few large
  ones in a large one, the two maps combined by their minimum (`_fire_depth_maps`: the same map);
- the floor's firelight is its irradiance (PCSS included) on a half-resolution grid of its pixels,
  read back bilinearly, times rho_d per pixel (`floor_firelight`; the floor is Lambertian here);
- the flames and their mirror images are looked up only at the pixels they can cover (found
  once: the camera and the fires stand still).

The polished stage floor: the garment and the flames are mirrored in the floor plane
(`jaxrender.fabric.mirror_mesh`) and rasterized/intersected with the camera's own rays; every
mirrored garment pixel is shaded as the real garment point it shows, seen from the floor point
(the mirrored view direction), with its own PCSS. The reflected image (sky mirrored, garment,
flames) is blurred by the floor's roughness and weighted by the Fresnel reflectance of its coat
(`jaxrender.fabric.glossy_reflection`); the stage's diffuse light is scaled by 1 - F, and its
specular lobe is dropped (the reflection is the specular part). The gravel does not reflect.

What stays over the sequence (`MotionRig`, from `prepare_motion`): the floor points and their
environment light (nothing moves between them and the sky), the background sky and the mirrored
sky, the environment samples, and the fires' shadow-map frames (aimed at the garment's starting
pose, with a field of view wide enough for the motion).
"""

from __future__ import annotations

import dataclasses
import math
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray

from jaxrender.fabric import (
    Pinhole,
    camera_pinhole,
    depth_map,
    fresnel_schlick,
    glossy_blur_pixels,
    glossy_reflection,
    mirror_mesh,
    raster_window,
    rasterize,
    reflect_directions,
    reflect_points,
    spot_pinhole,
    tangent_frames,
)
from jaxrender.lights import QuadLightSamples, env_radiance, sample_envmap, sample_quad_lights
from jaxrender.shadows import ShadowMap
from jaxrender.textures import bilinear
from sims import BodyMotion, ClothState, DrapedCloth, advance_cloth, cloth_mesh

from .frame import fire_light
from .prepare import fire_visibility, floor_texels, garment_points, quad_hits
from .scene import NohScene
from .shading import FloorPoints, GarmentPoints, SurfaceLight, shade_floor, shade_garment, shared_light

STAGE_F0 = 0.04          # reflectance at normal incidence of the waxed hinoki (a coat of index ~1.5)
STAGE_ROUGHNESS = 0.03   # radians: the spread of the polished floor's reflected rays
FAR_BEYOND = 100.0       # m: what the floor reflects of the sky lies this far beyond it (for the blur)


class MotionRig(eqx.Module):
    """Everything constant over a moving sequence (module docstring)."""

    cloth: DrapedCloth
    motion: BodyMotion
    pinhole: Pinhole                        # the camera's
    floor: FloorPoints                      # every pixel whose ray meets the floor plane
    floor_uv: Float[Array, "P 2"]           # where each floor pixel reads the half-resolution firelight
    shadow_points: Float[Array, "S 3"]      # the floor under the pixels of a half-resolution grid that see it
    shadow_index: Int[Array, " S"]          # ... their index in that grid (flattened)
    shadow_valid: Float[Array, "Hh Wh"]     # 1 where a pixel of that grid sees the floor
    floor_static: Float[Array, "P 3"]
    floor_coat: Float[Array, "H W"]         # 1 where the polished stage is, 0 on the gravel and off the floor
    background: Float[Array, "H W 3"]
    mirrored_sky: Float[Array, "H W 3"]
    rays: Float[Array, "H W 3"]
    t_floor: Float[Array, "H W"]
    env_direction: Float[Array, "K 3"]
    env_weight: Float[Array, "K 3"]
    flames: FlamePixels                     # the flames seen directly (in front of what is behind them)
    mirrored_flames: FlamePixels            # ... mirrored in the floor (beyond the floor plane)
    light_position: Float[Array, "Q 3"]
    light_rotation: Float[Array, "Q 3 3"]
    tan_cutoff: float = eqx.field(static=True)
    window: int = eqx.field(static=True)
    shadow_window: int = eqx.field(static=True)          # the depth maps' raster window for most triangles
    large_window: int = eqx.field(static=True)           # ... for the few larger ones (`_fire_depth_maps`)
    large_capacity: int = eqx.field(static=True)         # how many triangles the large window takes
    shadow_resolution: int = eqx.field(static=True)
    capacity: int = eqx.field(static=True)
    reflection_capacity: int = eqx.field(static=True)

    steps: int = eqx.field(static=True)
    near: float = eqx.field(static=True)
    roughness: float = eqx.field(static=True)
    view_box: tuple[int, int, int, int] = eqx.field(static=True)     # (x0, y0, w, h): where the garment and
    mirror_box: tuple[int, int, int, int] = eqx.field(static=True)   # its mirror image are rasterized


class FlamePixels(eqx.Module):
    """The pixels whose rays meet a flame quad (the camera and the fires stand still: found once),
    each quad's ray distance and uv there, and whether it is hit (1) inside the quad."""

    index: Int[Array, " n"]
    t: Float[Array, "Q n"]
    uv: Float[Array, "Q n 2"]
    inside: Float[Array, "Q n"]


class FrameCounts(eqx.Module):
    """What a frame needed, for the host to check against the rig's fixed sizes, and where the
    garment is in the image (for the sequence's exposure)."""

    garment_mask: Array
    garment: Array
    reflection: Array
    view_extent: Array
    shadow_extent: Array
    shadow_large: Array
    bounds: Array           # (x0, y0, x1, y1) in pixels of the garment's projected vertices, then of its mirror's


def _round_up(n: float, granule: int = 1024) -> int:
    return int(granule * math.ceil(max(n, 1) / granule))


def _pow2(n: float) -> int:
    return int(2 ** math.ceil(math.log2(max(2.0, n))))


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


def _extent(ph: Pinhole, vertices: Array, triangles: Array) -> Array:
    """The largest projected bounding box of a triangle, in pixels."""
    return jnp.max(_extents(ph, vertices, triangles))


def _box(bounds: np.ndarray, ph: Pinhole, margin: float) -> tuple[int, int, int, int]:
    """The pixel rectangle (x0, y0, w, h) around `bounds` (x0, y0, x1, y1), `margin` x its size
    wider on every side, clipped to the image (full width/height if it misses the image)."""
    x0, y0, x1, y1 = (float(b) for b in bounds)
    mx, my = margin * (x1 - x0), margin * (y1 - y0)
    lo = (max(0, int(math.floor(x0 - mx))), max(0, int(math.floor(y0 - my))))
    hi = (min(ph.width, int(math.ceil(x1 + mx))), min(ph.height, int(math.ceil(y1 + my))))
    if hi[0] <= lo[0] or hi[1] <= lo[1]:
        return 0, 0, ph.width, ph.height
    return lo[0], lo[1], hi[0] - lo[0], hi[1] - lo[1]


def _bounds(ph: Pinhole, vertices: Array) -> Array:
    px, _ = ph.project(vertices)
    return jnp.stack([jnp.min(px[:, 0]), jnp.min(px[:, 1]), jnp.max(px[:, 0]), jnp.max(px[:, 1])])


def _inside(bounds, box: tuple[int, int, int, int], ph: Pinhole) -> bool:
    """Whether the projected `bounds` lie in `box` (or the box is clipped by the image there)."""
    x0, y0, w, h = box
    b = [float(v) for v in bounds]
    return ((b[0] >= x0 or x0 == 0) and (b[1] >= y0 or y0 == 0) and (b[2] <= x0 + w or x0 + w == ph.width)
            and (b[3] <= y0 + h or y0 + h == ph.height))


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


def _fire_depth_maps(rig: MotionRig, x: Array, triangles: Array) -> tuple[list[ShadowMap], Array, Array]:
    """The garment's depth map from each fire, (maps, largest triangle extent, most large triangles).

    A raster window is sized by the largest projected triangle, and as the garment dances a few
    triangles (a stretched sleeve seen edge-on, a fold near a fire) grow to 4x the others' size in
    the fires' maps: one window for all would cost 16x. So the triangles are split by their
    extent: all but the large ones are rasterized with `rig.shadow_window`, the large ones
    (at most `rig.large_capacity`, compacted) with `rig.large_window`, and the two depth maps
    are combined by their minimum (a z-buffer of the union: the same map as one pass).
    Degenerate triangles (0, 0, 0) pad both sets and cover nothing."""
    n_tri = triangles.shape[0]
    padded = jnp.concatenate([triangles, jnp.zeros((1, 3), triangles.dtype)])
    maps, largest, most = [], [], []
    for q in range(rig.light_position.shape[0]):  # four fires: unrolled
        sp = spot_pinhole(rig.light_position[q], rig.light_rotation[q], rig.tan_cutoff, rig.shadow_resolution)
        ext = _extents(sp, x, triangles)
        large = ext > rig.shadow_window
        small = jnp.where(large[:, None], 0, triangles)
        big = padded[jnp.nonzero(large, size=rig.large_capacity, fill_value=n_tri)[0]]
        depth = jnp.minimum(depth_map(sp, x, small, window=rig.shadow_window),
                            depth_map(sp, x, big, window=rig.large_window))
        maps.append(ShadowMap(depth=depth, position=rig.light_position[q], rotation=rig.light_rotation[q],
                              tan_cutoff=jnp.asarray(rig.tan_cutoff, x.dtype)))
        largest.append(jnp.max(ext))
        most.append(jnp.sum(large.astype(jnp.int32)))
    return maps, jnp.max(jnp.stack(largest)), jnp.max(jnp.stack(most))


def _shadow_frames(scene: NohScene, vertices: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Each fire's shadow camera aimed at the garment's bounding box centre, one field of view for
    all (the largest needed, times `margin` for the motion)."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    target = 0.5 * (lo + hi)
    corners = np.asarray([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
    positions, rotations, tan_c = [], [], 0.0
    for pos in np.asarray(scene.fires.center, np.float64):
        z = target - pos
        z /= np.linalg.norm(z)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        rot = np.stack([x, np.cross(z, x), z])
        local = (corners - pos) @ rot.T
        tan_c = max(tan_c, float(np.max(np.abs(local[:, :2]) / local[:, 2:3])))
        positions.append(pos)
        rotations.append(rot)
    return np.asarray(positions), np.asarray(rotations), tan_c * margin


def prepare_motion(scene: NohScene, cloth: DrapedCloth, motion: BodyMotion, *, key: PRNGKeyArray, k_env: int = 20,
                   shadow_resolution: int = 512, near: float = 0.5, frame_dt: float = 0.1,
                   roughness: float = STAGE_ROUGHNESS) -> MotionRig:
    """The sequence's constant part and the fixed sizes of the per-frame buffers (from the
    settled garment, with margins for the motion; `moving_noh` grows them if a frame needs more)."""
    dtype = scene.vertices.dtype
    ph = camera_pinhole(scene.camera)
    h, w = ph.height, ph.width
    gy, gx = jnp.meshgrid(jnp.arange(h, dtype=dtype) + 0.5, jnp.arange(w, dtype=dtype) + 0.5, indexing="ij")
    rays = ph.ray(jnp.stack([gx, gy], -1))
    down = rays[..., 1] < -1e-6
    t_floor = jnp.where(down, -ph.origin[1] / jnp.where(down, rays[..., 1], -1.0), jnp.inf)
    f_index = jnp.asarray(np.flatnonzero(np.isfinite(np.asarray(t_floor))), jnp.int32)
    flat_rays = rays.reshape(-1, 3)[f_index]
    pos = ph.origin[None, :] + t_floor.reshape(-1)[f_index][:, None] * flat_rays
    texel = floor_texels(pos)
    stage = texel.lobe0.rho_s[:, 0] > 0
    # the polished stage: its specular part is the reflection, so the lobe is dropped
    lobe = eqx.tree_at(lambda lb: lb.rho_s, texel.lobe0, jnp.zeros_like(texel.lobe0.rho_s))
    texel = eqx.tree_at(lambda t: (t.lobe0, t.lobe1), texel, (lobe, lobe))
    floor = FloorPoints(f_index, pos, -flat_rays, texel)
    # the floor's soft shadows are computed on a half-resolution grid (2 x 2 pixel blocks) and read
    # back bilinearly at every floor pixel
    hh, hw = (h + 1) // 2, (w + 1) // 2
    sy, sx = jnp.meshgrid(2.0 * jnp.arange(hh, dtype=dtype) + 1.0, 2.0 * jnp.arange(hw, dtype=dtype) + 1.0,
                          indexing="ij")
    half_rays = ph.ray(jnp.stack([sx, sy], -1))
    half_down = half_rays[..., 1] < -1e-6
    half_t = jnp.where(half_down, -ph.origin[1] / jnp.where(half_down, half_rays[..., 1], -1.0), 0.0)
    shadow_index = jnp.asarray(np.flatnonzero(np.asarray(half_down)), jnp.int32)
    shadow_points = (ph.origin[None, None, :] + half_t[..., None] * half_rays).reshape(-1, 3)[shadow_index]
    fy, fx = jnp.divmod(f_index, w)
    floor_uv = jnp.stack([(fx.astype(dtype) + 0.5) / (2 * hw), (fy.astype(dtype) + 0.5) / (2 * hh)], -1)
    s = sample_envmap(scene.env, key, k_env)
    env_weight = s.radiance * ((s.direction[:, 1] > 0).astype(s.radiance.dtype) / (k_env * s.pdf))[:, None]
    floor_static = shade_floor(floor, shared_light(s.direction, env_weight, pos.shape[0]))
    coat = jnp.zeros((h * w,), dtype).at[f_index].set(stage.astype(dtype)).reshape(h, w)
    up = jnp.asarray([0.0, 1.0, 0.0], dtype)
    background = env_radiance(scene.env, rays, filter="mitsuba")
    mirrored_sky = env_radiance(scene.env, reflect_directions(rays, up), filter="mitsuba")
    # where the flames and their mirror images cover the image (hit beyond the floor plane)
    fl = scene.fires
    t, uv, inside = quad_hits(fl.center, fl.u, fl.v, ph.origin, rays)
    flames = _flame_pixels(t, uv, inside & (t > 0))
    origin = jnp.zeros(3, dtype)
    mirrored_centre = reflect_points(fl.center, origin, up)
    t, uv, inside = quad_hits(mirrored_centre, fl.u, reflect_directions(fl.v, up), ph.origin, rays)
    mirrored_flames = _flame_pixels(t, uv, inside & (t > t_floor[None]))
    # fixed sizes from the settled pose, with margins for the motion
    x0 = np.asarray(cloth.state.x)
    light_pos, light_rot, tan_c = _shadow_frames(scene, x0, margin=1.6)
    tris = cloth.triangles
    window = _pow2(1.1 * raster_window(ph, cloth.state.x, tris))
    # the depth maps' windows: most triangles fit 1/32 of the map's side (16 px at 512^2: the
    # settled garment's largest is ~17 px, all but ~2 below 16); the larger ones of the dance (up to
    # ~70 px at 512^2, at most ~25 of them) get their own window (`_fire_depth_maps`)
    spot = [spot_pinhole(p, r, tan_c, shadow_resolution) for p, r in zip(light_pos, light_rot)]
    rest = max(float(_extent(sp, cloth.state.x, tris)) for sp in spot)
    shadow_window = _pow2(shadow_resolution / 32)
    large_window = _pow2(max(shadow_resolution / 4, 2 * rest))

    gb = rasterize(ph, cloth.state.x, tris, cloth.uv.reshape(-1, 2), window=window)
    count = int(np.sum(np.asarray(gb.hit) > 0))
    # the G-buffers are rasterized in the rectangles around the garment and its mirror image only
    # (25% of their size wider on every side for the dance: it sways ~15% of that; `grown` widens
    # them if a frame leaves them)
    x0 = cloth.state.x
    view_box = _box(np.asarray(_bounds(ph, x0)), ph, 0.25)
    mirror_box = _box(np.asarray(_bounds(ph, x0 * jnp.asarray([1.0, -1.0, 1.0], dtype))), ph, 0.25)
    steps = max(1, int(round(frame_dt / cloth.dt)))
    return MotionRig(cloth, motion, ph, floor, floor_uv, shadow_points, shadow_index, half_down.astype(dtype),
                     floor_static, coat,
                     background, mirrored_sky, rays, t_floor, s.direction, env_weight, flames, mirrored_flames,
                     jnp.asarray(light_pos, dtype),
                     jnp.asarray(light_rot, dtype), float(tan_c), window, shadow_window, large_window, 64,
                     shadow_resolution,
                     _round_up(1.15 * count), _round_up(0.4 * count), steps, float(near), float(roughness),
                     view_box, mirror_box)


def _compact(mask: Array, capacity: int) -> tuple[Array, Array, Array]:
    """(scatter index with out-of-range padding, gather index clipped into range, count)."""
    flat = mask.reshape(-1)
    n = flat.shape[0]
    index = jnp.nonzero(flat, size=capacity, fill_value=n)[0].astype(jnp.int32)
    return index, jnp.minimum(index, n - 1), jnp.sum(flat.astype(jnp.int32))


def _with_light(a: SurfaceLight, b: SurfaceLight) -> SurfaceLight:
    """Two sets of samples at the same points as one (one shading pass)."""
    return SurfaceLight(jnp.concatenate([a.direction, b.direction], 1), jnp.concatenate([a.weight, b.weight], 1))


def _flame_pixels(t: Array, uv: Array, inside: Array) -> FlamePixels:
    """Host-side: the pixels where any quad is hit (`inside`, Q H W), with the quads' t and uv there."""
    index = np.flatnonzero(np.any(np.asarray(inside), axis=0))
    flat = lambda a: jnp.asarray(np.asarray(a).reshape(a.shape[0], -1, *a.shape[3:])[:, index])  # noqa: E731
    return FlamePixels(jnp.asarray(index, jnp.int32), flat(t), flat(uv), flat(inside.astype(t.dtype)))


def _flames(pixels: FlamePixels, emission: Float[Array, "Q Hf Wf 3"], t_stop: Float[Array, "H W"]) -> Array:
    """The flames' radiance at `pixels` where each quad lies before `t_stop` (the surface behind)."""
    stop = t_stop.reshape(-1)[pixels.index]
    out = jnp.zeros(pixels.index.shape + (3,), emission.dtype)
    for q in range(emission.shape[0]):  # four fires: unrolled
        hit = pixels.inside[q] * (pixels.t[q] < stop).astype(emission.dtype)
        out = out + hit[:, None] * bilinear(emission[q], pixels.uv[q], wrap="clamp")
    return out


def floor_firelight(rig: MotionRig, samples: QuadLightSamples, vis: Float[Array, "S Q"]) -> Float[Array, "P 3"]:
    """The firelight reflected by every floor pixel, from its irradiance on the half-resolution
    grid (`vis`: each fire's PCSS visibility at `rig.shadow_points`) read back bilinearly.

    The floor's BRDF is Lambertian here (the polished stage's specular lobe is its reflection,
    dropped from the lobe; the gravel has none), so its firelight is rho_d / pi times the
    irradiance E = sum_k max(wi_k . up, 0) L_k V_q(k) / (r_k^2 pdf_k K) (`fire_light`'s weights),
    which is smooth but for the shadows: the shadows are soft (PCSS, flames 0.4 m wide) and the
    flames >= 1 m from the floor, so E on 2 x 2 pixel blocks, read back bilinearly, keeps both,
    while rho_d (the planks' grain and seams) stays per pixel. Grid pixels that miss the floor
    (above the horizon) read E = 0: their floor neighbours lie at the horizon, where E ~ 1/r^2 -> 0."""
    light = fire_light(samples, rig.shadow_points, vis, rig.light_position.shape[0])
    irradiance = jnp.sum(jnp.maximum(light.direction[..., 1], 0.0)[..., None] * light.weight, axis=1)
    hh, hw = rig.shadow_valid.shape
    grid = jnp.zeros((hh * hw, 3), irradiance.dtype).at[rig.shadow_index].set(irradiance).reshape(hh, hw, 3)
    return rig.floor.texel.rho_d / jnp.pi * bilinear(grid, rig.floor_uv)


def _mirror_back(points: GarmentPoints, up: Array) -> GarmentPoints:
    """Garment points rasterized from the mirrored mesh, as the real points they show: position,
    view direction (toward the floor point) and shading frame reflected back."""
    origin = jnp.zeros(3, points.position.dtype)
    frame = tangent_frames(reflect_directions(points.frame[:, 2], up), reflect_directions(points.frame[:, 0], up))
    return eqx.tree_at(lambda p: (p.position, p.wo, p.frame), points,
                       (reflect_points(points.position, origin, up), reflect_directions(points.wo, up), frame))


def moving_frame(scene: NohScene, rig: MotionRig, state: ClothState, emission: Float[Array, "Q Hf Wf 3"],
                 key: PRNGKeyArray, *, k_fire: int = 20, blend: str = "shading"
                 ) -> tuple[Float[Array, "H W 3"], ClothState, FrameCounts]:
    """One frame of the moving garment (module docstring): the cloth advanced by a frame, then
    the view, shadows, lighting and reflection of its new pose."""
    cloth = rig.cloth
    state = advance_cloth(cloth, state, rig.motion, steps=rig.steps)
    x = state.x
    dtype = x.dtype
    normals = cloth_mesh(cloth, x).normals.reshape(-1, 3)
    geo = eqx.tree_at(lambda s: (s.vertices, s.vertex_normals), scene, (x, normals))
    ph = rig.pinhole
    h, w = ph.height, ph.width
    uv = cloth.uv.reshape(-1, 2)
    up = jnp.asarray([0.0, 1.0, 0.0], dtype)

    # what the camera sees: the garment in front of the floor plane (rasterized in its box)
    vb, mb = rig.view_box, rig.mirror_box
    gb = rasterize(_cropped(ph, vb), x, cloth.triangles, uv, window=rig.window)
    in_box = (gb.hit > 0) & (gb.distance < rig.t_floor[vb[1]:vb[1] + vb[3], vb[0]:vb[0] + vb[2]])
    g_scatter, g_gather, g_count = _compact(in_box, rig.capacity)
    points = garment_points(ph, geo, gb, g_gather)
    g_scatter = _full_index(g_scatter, vb, ph)
    garment = _placed(in_box, vb, ph, False)
    g_distance = _placed(gb.distance, vb, ph, jnp.inf)

    # shadow maps of this pose from every fire, PCSS at every garment, floor and reflected point
    maps, shadow_extent, shadow_large = _fire_depth_maps(rig, x, cloth.triangles)

    # the mirrored garment: what the floor reflects, as real garment points seen from the floor
    mv, mn, mt = mirror_mesh(x, normals, cloth.triangles, jnp.zeros(3, dtype), up)
    gbr = rasterize(_cropped(ph, mb), mv, mt, uv, window=rig.window)
    in_mirror = (slice(mb[1], mb[1] + mb[3]), slice(mb[0], mb[0] + mb[2]))
    reflects = (gbr.hit > 0) & (rig.floor_coat[in_mirror] > 0) & ~garment[in_mirror]
    r_scatter, r_gather, r_count = _compact(reflects, rig.reflection_capacity)
    mirror = eqx.tree_at(lambda s: (s.vertices, s.vertex_normals, s.triangles), scene, (mv, mn, mt))
    mirrored = _mirror_back(garment_points(ph, mirror, gbr, r_gather), up)
    r_scatter = _full_index(r_scatter, mb, ph)
    r_distance = _placed(gbr.distance, mb, ph, jnp.inf)      # inf where it reflects no garment

    n_g = points.position.shape[0]
    vis = fire_visibility(maps, jnp.concatenate([points.position, mirrored.position]), rig.near)

    # light: the same environment samples, the frame's flames
    fires = eqx.tree_at(lambda f: f.emission, scene.fires, emission)
    samples = sample_quad_lights(fires, key, k_fire)
    n_fires = fires.center.shape[0]

    def garment_light(p, v):
        return _with_light(shared_light(rig.env_direction, rig.env_weight, p.position.shape[0]),
                           fire_light(samples, p.position, v, n_fires))

    g_rad = shade_garment(scene.mats, points, garment_light(points, vis[:n_g]), blend=blend)
    # the reflected garment at its nearest mip level (half the shading): blurred by the floor's
    # roughness and weighted by F = 0.04-0.3, the blend between two levels is not seen there
    r_rad = shade_garment(scene.mats, mirrored, garment_light(mirrored, vis[n_g:]), blend="nearest")
    f_rad = floor_firelight(rig, samples, fire_visibility(maps, rig.shadow_points, rig.near)) + rig.floor_static

    # the reflection: mirrored sky, garment and flames, blurred by the roughness, times Fresnel
    beyond = jnp.where(jnp.isfinite(r_distance), r_distance - rig.t_floor, FAR_BEYOND)
    reflected = rig.mirrored_sky.reshape(h * w, 3).at[r_scatter].set(r_rad, mode="drop").reshape(h, w, 3)
    m_index = rig.mirrored_flames.index
    reflected = reflected.reshape(h * w, 3).at[m_index].add(_flames(rig.mirrored_flames, emission, r_distance))
    reflected = reflected.reshape(h, w, 3)
    cos = jnp.clip(-rig.rays[..., 1], 0.0, 1.0)
    focal = ph.fy
    blur = glossy_blur_pixels(rig.roughness, beyond, jnp.where(jnp.isfinite(rig.t_floor), rig.t_floor, 0.0), focal)
    mirror_light = rig.floor_coat[..., None] * glossy_reflection(reflected, blur, cos, f0=STAGE_F0)
    fresnel = rig.floor_coat * fresnel_schlick(cos, STAGE_F0)

    # compose: sky, floor (diffuse x (1 - F) + reflection), garment, visible flames
    img = rig.background.reshape(h * w, 3)
    f_idx = rig.floor.index
    img = img.at[f_idx].set(f_rad * (1 - fresnel.reshape(-1)[f_idx])[:, None] + mirror_light.reshape(-1, 3)[f_idx])
    img = img.at[g_scatter].set(g_rad, mode="drop")
    surface_t = jnp.where(garment, g_distance, rig.t_floor)
    img = img.at[rig.flames.index].add(_flames(rig.flames, emission, surface_t)).reshape(h, w, 3)
    view_extent = jnp.maximum(_extent(ph, x, cloth.triangles), _extent(ph, mv, mt))
    counts = FrameCounts(garment, g_count, r_count, view_extent, shadow_extent, shadow_large,
                         jnp.concatenate([_bounds(ph, x), _bounds(ph, mv)]))
    return img, state, counts


moving_frame_jit = eqx.filter_jit(moving_frame)


def grown(rig: MotionRig, counts: FrameCounts) -> MotionRig | None:
    """A rig with larger buffers if the frame's `counts` overflowed this one's (None if it fit)."""
    changes = {}
    if int(counts.garment) > rig.capacity:
        changes["capacity"] = _round_up(1.25 * int(counts.garment))
    if int(counts.reflection) > rig.reflection_capacity:
        changes["reflection_capacity"] = _round_up(1.25 * int(counts.reflection))
    if float(counts.view_extent) > rig.window:
        changes["window"] = _pow2(float(counts.view_extent))
    if float(counts.shadow_extent) > rig.large_window:
        changes["large_window"] = _pow2(float(counts.shadow_extent))
    bounds = np.asarray(counts.bounds)
    for name, b in (("view_box", bounds[:4]), ("mirror_box", bounds[4:])):
        old = getattr(rig, name)
        if not _inside(b, old, rig.pinhole):   # the union of the old box and the new one
            new = _box(b, rig.pinhole, 0.25)
            lo = (min(old[0], new[0]), min(old[1], new[1]))
            changes[name] = (*lo, max(old[0] + old[2], new[0] + new[2]) - lo[0],
                             max(old[1] + old[3], new[1] + new[3]) - lo[1])
    if int(counts.shadow_large) > rig.large_capacity:
        changes["large_capacity"] = _round_up(1.25 * int(counts.shadow_large), 64)
    if not changes:
        return None
    return dataclasses.replace(rig, **changes)


def render_moving_noh(scene: NohScene, cloth: DrapedCloth, *, frames: int, key: PRNGKeyArray,
                      motion: BodyMotion | None = None, k_env: int = 20, k_fire: int = 20, frame_dt: float = 0.1,
                      shadow_resolution: int = 512, progress=None, time_repeats: int = 0,
                      info: dict | None = None) -> tuple[list[np.ndarray], MotionRig]:
    """`frames` frames of the moving garment, `frame_dt` s apart (the flames cycle through
    their frames), each continuing the cloth from the previous one; then `time_repeats` more
    frames (continuing the dance, discarded) timed into `info["timed_s"]`. A frame that needs
    larger buffers than the rig has is rendered again with grown ones (one more compile).
    `info` also gets `prepare_s`, `compile_s` (the first frame), `frame_s`, `recompiles` and
    `garment_mask` (where the garment is in the first frame)."""
    motion = BodyMotion(axis_z=float(cloth.capsule[1])) if motion is None else motion
    k_env_key, k_frames = jax.random.split(key)
    t0 = time.perf_counter()
    rig = jax.block_until_ready(prepare_motion(scene, cloth, motion, key=k_env_key, k_env=k_env,
                                               shadow_resolution=shadow_resolution, frame_dt=frame_dt))
    prepare_s = time.perf_counter() - t0
    n_flames = scene.flames.shape[1]
    state = cloth.state
    out, seconds, recompiles, mask0 = [], [], 0, None
    for i in range(frames + time_repeats):
        ts = time.perf_counter()
        while True:
            image, new_state, counts = jax.block_until_ready(
                moving_frame_jit(scene, rig, state, scene.flames[:, i % n_flames], jax.random.fold_in(k_frames, i),
                                 k_fire=k_fire))
            bigger = grown(rig, counts)
            if bigger is None:
                break
            rig, recompiles = bigger, recompiles + 1
        seconds.append(time.perf_counter() - ts)
        state = new_state
        if i == 0:
            mask0 = np.asarray(counts.garment_mask)
        if i < frames:
            out.append(np.asarray(image, np.float32))
            if progress is not None:
                progress(1)
    if info is not None:
        info.update(prepare_s=prepare_s, compile_s=seconds[0], frame_s=seconds[1:frames],
                    timed_s=seconds[frames:], recompiles=recompiles, garment_mask=mask0)
    return out, rig

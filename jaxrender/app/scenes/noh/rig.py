"""Everything of a Noh sequence that stays constant (`prepare_rig`): the camera's view of the
stage (ray cast once), the stage's environment light and each fire's unit-power irradiance with
the stage's own shadows, what the polished floors reflect of the stage, the half-resolution
stage points inside each fire's shadow frustum, the flames' pixels, the fires' shadow cameras
aimed at the performer's whole path, and the fixed sizes of the per-frame buffers.

What is precomputed and why that is exact or where it approximates: docs/noh.md, "A frame".
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray

from jaxrender.fabric import Pinhole, camera_pinhole, reflect_directions, reflect_points
from jaxrender.lights import env_radiance, sample_envmap

from .performer import performer_mesh
from .scene import NohScene
from .shading import quad_hits
from .stage import FLAME_SIZE, StageHits, _chunked, basket_hides, cast_stage, hidden_length, stage_occluded

STAGE_ROUGHNESS = 0.03   # radians: the spread of the polished floor's reflected rays
FAR_BEYOND = 100.0       # m: what the floor reflects of the sky lies this far beyond it (for the blur)
FLAME_CELLS = (8, 4)     # bands x column groups over each flame: a frame lights the stage by their mean radiance
_COLUMNS = 4             # columns of points in each group (one point per column and band)


class StagePixels(eqx.Module):
    """The pixels that see the stage (`index`; `t` per pixel, inf for the sky) and their light
    that does not move: the environment's (with the stage's shadows) and, per fire, the
    irradiance of a flame of unit radiance (with the stage's shadows); `shadow_uv`: where each
    reads the half-resolution grid of the performer's shadows."""

    index: Int[Array, " P"]
    rho_d: Float[Array, "P 3"]
    env: Float[Array, "P 3"]
    fire_unit: Float[Array, "P Q B G"]
    shadow_uv: Float[Array, "P 2"]
    coat: Float[Array, "H W"]
    t: Float[Array, "H W"]


class MirrorPixels(eqx.Module):
    """For the polished pixels: the stage (or the sky) that their mirrored rays meet, as
    radiance from the environment and unit fire irradiance, and how far beyond the floor it is."""

    index: Int[Array, " M"]
    rho_d: Float[Array, "M 3"]
    env: Float[Array, "M 3"]
    fire_unit: Float[Array, "M Q B G"]
    stop: Float[Array, "H W"]          # the unfolded distance to what is mirrored (0 off the polish)
    beyond: Float[Array, "H W"]


class ShadowGrid(eqx.Module):
    """Per fire, the half-resolution stage points inside its shadow frustum (padded, `cell` =
    their grid index, hh * hw for padding)."""

    points: Float[Array, "Q C 3"]
    cell: Int[Array, "Q C"]
    shape: tuple[int, int] = eqx.field(static=True)


class FlamePixels(eqx.Module):
    """The pixels whose rays meet a flame quad (found once), each quad's ray distance and uv there,
    and whether it is hit (1) inside the quad."""

    index: Int[Array, " n"]
    t: Float[Array, "Q n"]
    uv: Float[Array, "Q n 2"]
    inside: Float[Array, "Q n"]


class NohRig(eqx.Module):
    """The sequence's constant part (module docstring) and the per-frame buffers' fixed sizes."""

    pinhole: Pinhole
    rays: Float[Array, "H W 3"]
    background: Float[Array, "H W 3"]
    mirrored_sky: Float[Array, "H W 3"]
    stage: StagePixels
    mirror: MirrorPixels
    shadow_grid: ShadowGrid
    env_direction: Float[Array, "K 3"]
    env_weight: Float[Array, "K 3"]            # the performer's: zero where the roof hides the sky
    flames: FlamePixels
    mirrored_flames: FlamePixels
    light_position: Float[Array, "Q 3"]
    light_rotation: Float[Array, "Q 3 3"]
    tan_cutoff: float = eqx.field(static=True)
    window: int = eqx.field(static=True)                 # the G-buffers' raster window for most triangles
    large_view_window: int = eqx.field(static=True)      # ... for the few larger ones
    large_view_capacity: int = eqx.field(static=True)
    shadow_window: int = eqx.field(static=True)          # the depth maps' raster window for most triangles
    large_window: int = eqx.field(static=True)           # ... for the few larger ones
    large_capacity: int = eqx.field(static=True)
    shadow_resolution: int = eqx.field(static=True)
    capacity: int = eqx.field(static=True)
    reflection_capacity: int = eqx.field(static=True)
    steps: int = eqx.field(static=True)
    near: float = eqx.field(static=True)
    roughness: float = eqx.field(static=True)
    view_box: tuple[int, int, int, int] = eqx.field(static=True)
    mirror_box: tuple[int, int, int, int] = eqx.field(static=True)


def round_up(n: float, granule: int = 1024) -> int:
    return int(granule * math.ceil(max(n, 1) / granule))


def pow2(n: float) -> int:
    return int(2 ** math.ceil(math.log2(max(2.0, n))))


def large_shadow_window(extent: float, resolution: int) -> int:
    """The depth maps' window for large triangles: `extent` pixels rounded up to a power of two,
    never more than the map's own (a window's origin is clipped to the map, so one of the map's
    size covers any triangle)."""
    return pow2(min(extent, resolution))


def pixel_box(bounds, ph: Pinhole, margin: float) -> tuple[int, int, int, int]:
    """The pixel rectangle (x0, y0, w, h) around `bounds` (x0, y0, x1, y1), `margin` x its size
    wider on every side, clipped to the image (the full image if it misses it)."""
    # far beyond the image (a vertex near the camera's plane) or undefined: clipped, never an overflow
    x0, y0, x1, y1 = np.clip(np.nan_to_num(np.asarray(bounds, np.float64), nan=0.0), -4.0 * ph.width, 4.0 * ph.width)
    mx, my = margin * (x1 - x0), margin * (y1 - y0)
    lo = (max(0, int(math.floor(x0 - mx))), max(0, int(math.floor(y0 - my))))
    hi = (min(ph.width, int(math.ceil(x1 + mx))), min(ph.height, int(math.ceil(y1 + my))))
    if hi[0] <= lo[0] or hi[1] <= lo[1]:
        return 0, 0, ph.width, ph.height
    return lo[0], lo[1], hi[0] - lo[0], hi[1] - lo[1]


def projected_bounds(ph: Pinhole, points: Array) -> Array:
    px, _ = ph.project(points)
    return jnp.stack([jnp.min(px[:, 0]), jnp.min(px[:, 1]), jnp.max(px[:, 0]), jnp.max(px[:, 1])])


def _flame_pixels(t: Array, uv: Array, inside: Array) -> FlamePixels:
    """Host-side: the pixels where any quad is hit (`inside`, Q H W), with the quads' t and uv there."""
    index = np.flatnonzero(np.any(np.asarray(inside), axis=0))
    flat = lambda a: jnp.asarray(np.asarray(a).reshape(a.shape[0], -1, *a.shape[3:])[:, index])  # noqa: E731
    return FlamePixels(jnp.asarray(index, jnp.int32), flat(t), flat(uv), flat(inside.astype(t.dtype)))


def _shadow_frames(centers: np.ndarray, lo: np.ndarray, hi: np.ndarray, margin: float
                   ) -> tuple[np.ndarray, np.ndarray, float]:
    """Each fire's shadow camera aimed at the centre of the box (lo, hi) the performer moves in,
    one field of view for all (the largest needed, times `margin`)."""
    target = 0.5 * (lo + hi)
    corners = np.asarray([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
    rotations, tan_c = [], 0.0
    for pos in centers:
        z = target - pos
        z /= np.linalg.norm(z)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        rot = np.stack([x, np.cross(z, x), z])
        local = (corners - pos) @ rot.T
        tan_c = max(tan_c, float(np.max(np.abs(local[:, :2]) / local[:, 2:3])))
        rotations.append(rot)
    return np.asarray(centers), np.asarray(rotations), tan_c * margin


def flame_grid(scene: NohScene) -> tuple[Array, Array, float]:
    """Each flame's points, one per band and column (Q B G C 3: `FLAME_CELLS` bands from the top,
    as the emission's rows, x groups of `_COLUMNS` columns), its bands' bottom and top heights
    (Q B 2) and the area each point stands for."""
    fl = scene.fires
    dtype = fl.center.dtype
    bands, groups = FLAME_CELLS
    cols = groups * _COLUMNS
    s = ((jnp.arange(cols, dtype=dtype) + 0.5) / cols * 2 - 1).reshape(groups, _COLUMNS)   # -1..1 along u
    t = 1 - (jnp.arange(bands, dtype=dtype) + 0.5) / bands * 2                 # 1..-1 along v (top first)
    pts = (fl.center[:, None, None, None] + s[None, None, :, :, None] * fl.u[:, None, None, None]
           + t[None, :, None, None, None] * fl.v[:, None, None, None])
    edge = 1 - jnp.arange(bands + 1, dtype=dtype) / bands * 2
    heights = fl.center[:, 1:2] + edge[None] * fl.v[:, 1:2]                    # Q B+1, decreasing
    return pts, jnp.stack([heights[:, 1:], heights[:, :-1]], -1), FLAME_SIZE[0] * FLAME_SIZE[1] / (cols * bands)


def cell_radiance(emission: Float[Array, "Q Hf Wf 3"]) -> Float[Array, "Q B G 3"]:
    """Each flame's mean radiance in each of its `FLAME_CELLS` (bands of rows from the top x groups
    of columns)."""
    def shares(n: int, parts: int) -> np.ndarray:        # (parts, n): each texel's share of each part
        edge = np.arange(parts + 1) / parts
        lo, hi = np.arange(n) / n, (np.arange(n) + 1) / n
        return np.clip(np.minimum(hi[None], edge[1:, None]) - np.maximum(lo[None], edge[:-1, None]), 0, None) * parts

    bands, groups = FLAME_CELLS
    rows = jnp.asarray(shares(emission.shape[1], bands), emission.dtype)
    cols = jnp.asarray(shares(emission.shape[2], groups), emission.dtype)
    return jnp.einsum("bh,gw,qhwc->qbgc", rows, cols, emission)


def _fire_unit(scene: NohScene, position: Array, normal: Array) -> Float[Array, "N Q B G"]:
    """Per fire and cell, the irradiance of a flame of unit radiance at stage points: a point per
    band and column (cosine over r^2, the flame a billboard facing every point), the part of each
    band its basket hides from the point taken away exactly (`stage.basket_hides`)."""
    pts, heights, area = flame_grid(scene)
    q, b, g, c = pts.shape[:4]
    d = pts[None] - position[:, None, None, None, None]                         # N Q B G C 3
    r2 = jnp.maximum(jnp.sum(d * d, -1), 1e-6)
    cos_r2 = jnp.maximum(jnp.einsum("nqbgck,nk->nqbgc", d, normal), 0.0) / r2 ** 1.5
    columns = pts[:, 0].reshape(q * g * c, 3)
    centre = jnp.repeat(scene.fires.center[:, jnp.asarray([0, 2])], g * c, axis=0)
    lo, hi = basket_hides(position, columns, centre)                           # N QGC 4
    lo, hi = lo.reshape(-1, q, 1, g, c, 4), hi.reshape(-1, q, 1, g, c, 4)
    bottom, top = heights[None, :, :, None, None, 0], heights[None, :, :, None, None, 1]
    hidden = hidden_length(lo, hi, bottom, top) / (top - bottom)
    return jnp.sum(cos_r2 * (1 - hidden), axis=-1) * area


def static_light(scene: NohScene, position: Array, normal: Array, env_dir: Array, env_weight: Array
                 ) -> tuple[Float[Array, "N 3"], Float[Array, "N Q B G"]]:
    """(environment irradiance / pi, per-fire and cell unit irradiance) at stage points, the
    stage's own shadows included: the environment's K samples against the quads that shadow the
    sky, each fire against every quad toward its flame's centre (one batch of rays each) and its
    basket against each band of each column (`_fire_unit`)."""
    lifted = position + 1e-3 * normal
    n, k = position.shape[0], env_dir.shape[0]
    dtype = position.dtype
    origins = jnp.repeat(lifted, k, axis=0)                                   # point-major: N K rays
    dirs = jnp.tile(env_dir, (n, 1))
    lit = 1.0 - stage_occluded(scene.stage, origins, dirs, jnp.full((n * k,), jnp.inf, dtype), occluders_only=True)
    cos = jnp.maximum(normal @ env_dir.T, 0.0) * lit.reshape(n, k)            # N K
    env = cos @ env_weight
    q = scene.fires.center.shape[0]
    unit = _chunked(lambda p, nn: _fire_unit(scene, p, nn), position, normal, chunk=1024)
    to = scene.fires.center[None] - lifted[:, None]                           # N Q 3
    dist = jnp.linalg.norm(to, axis=-1)
    seen = 1.0 - stage_occluded(scene.stage, jnp.repeat(lifted, q, axis=0), (to / dist[..., None]).reshape(-1, 3),
                                (dist - 0.05).reshape(-1))
    return env / jnp.pi, unit * seen.reshape(n, q, 1, 1)


def _pixel_grid(ph: Pinhole, step: int, dtype) -> Array:
    """Rays through the centres of `step` x `step` pixel blocks (H/step x W/step x 3)."""
    hh, hw = -(-ph.height // step), -(-ph.width // step)
    sy, sx = jnp.meshgrid(step * jnp.arange(hh, dtype=dtype) + step / 2, step * jnp.arange(hw, dtype=dtype) + step / 2,
                          indexing="ij")
    return ph.ray(jnp.stack([sx, sy], -1))


def _performer_box(scene: NohScene, margin: float) -> tuple[np.ndarray, np.ndarray]:
    """The box the performer's joints move in over the motion, `margin` m wider (the robe)."""
    p = np.asarray(scene.performer.motion.positions, np.float64).reshape(-1, 3)
    return p.min(axis=0) - margin, p.max(axis=0) + margin


class _View(eqx.Module):
    rays: Array
    hits: StageHits
    env_direction: Array
    env_weight: Array
    background: Array
    mirrored_sky: Array
    flame_hits: tuple
    mirrored_flame_hits: tuple


@eqx.filter_jit
def _view(scene: NohScene, ph: Pinhole, key: PRNGKeyArray, k_env: int) -> _View:
    """The camera's rays, the stage they meet, the environment's samples, the sky behind and
    mirrored, and the flame quads (and their mirror images) along every ray."""
    dtype = scene.stage.center.dtype
    rays = _pixel_grid(ph, 1, dtype)
    flat = rays.reshape(-1, 3)
    hits = cast_stage(scene.stage, jnp.broadcast_to(ph.origin, flat.shape), flat)
    s = sample_envmap(scene.env, key, k_env)
    env_weight = s.radiance * ((s.direction[:, 1] > 0).astype(s.radiance.dtype) / (k_env * s.pdf))[:, None]
    up = jnp.asarray([0.0, 1.0, 0.0], dtype)
    fl = scene.fires
    mirrored_centre = reflect_points(fl.center, jnp.zeros(3, dtype), up)
    return _View(rays, hits, s.direction, env_weight, env_radiance(scene.env, rays, filter="mitsuba"),
                 env_radiance(scene.env, reflect_directions(rays, up), filter="mitsuba"),
                 quad_hits(fl.center, fl.u, fl.v, ph.origin, rays),
                 quad_hits(mirrored_centre, fl.u, reflect_directions(fl.v, up), ph.origin, rays))


@eqx.filter_jit
def _mirrored(scene: NohScene, position: Array, rays: Array) -> tuple[StageHits, Array]:
    """What the polished points' mirrored rays meet, and the sky along them."""
    up = jnp.asarray([0.0, 1.0, 0.0], position.dtype)
    d = reflect_directions(rays, up)
    return cast_stage(scene.stage, position + 1e-3 * up, d), env_radiance(scene.env, d, filter="mitsuba")


@eqx.filter_jit
def _performer_view(scene: NohScene, ph: Pinhole, env_direction: Array, middle: Array):
    """Frame 0's mesh, its projected vertices, and which environment samples the stage hides
    from the performer's middle."""
    mesh = performer_mesh(scene.performer, scene.performer.costume.state)
    px, _ = ph.project(mesh.vertices)
    hidden = stage_occluded(scene.stage, jnp.broadcast_to(middle, env_direction.shape), env_direction,
                            jnp.full(env_direction.shape[:1], jnp.inf, env_direction.dtype), occluders_only=True)
    return mesh, px, hidden


def prepare_rig(scene: NohScene, *, key: PRNGKeyArray, k_env: int = 20, shadow_resolution: int = 512,
                near: float = 0.5, frame_dt: float = 0.1, roughness: float = STAGE_ROUGHNESS) -> NohRig:
    """The sequence's constant part and the fixed sizes of the per-frame buffers (from frame 0
    and the performer's path, with margins; `grown` enlarges them if a frame needs more)."""
    dtype = scene.stage.center.dtype
    ph = camera_pinhole(scene.camera)
    h, w = ph.height, ph.width
    view = _view(scene, ph, key, k_env)
    hits = view.hits
    flat_rays = view.rays.reshape(-1, 3)
    index = jnp.asarray(np.flatnonzero(np.isfinite(np.asarray(hits.t))), jnp.int32)
    m_index = jnp.asarray(np.flatnonzero(np.asarray(hits.coat) > 0), jnp.int32)
    m_hits, sky = _mirrored(scene, hits.position[m_index], flat_rays[m_index])
    m_seen = jnp.isfinite(m_hits.t)
    # the static light of the stage points and of the mirrored ones, in one batch
    n_p = index.shape[0]
    env, unit = _static_light_jit(scene, jnp.concatenate([hits.position[index], m_hits.position]),
                                  jnp.concatenate([hits.normal[index], m_hits.normal]), view.env_direction,
                                  view.env_weight)
    rho = hits.rho_d[index]
    fy, fx = jnp.divmod(index, w)
    hh, hw = -(-h // 2), -(-w // 2)
    shadow_uv = jnp.stack([(fx.astype(dtype) + 0.5) / (2 * hw), (fy.astype(dtype) + 0.5) / (2 * hh)], -1)
    coat = hits.coat.reshape(h, w)
    t_stage = hits.t.reshape(h, w)
    stage = StagePixels(index, rho, env[:n_p] * rho, unit[:n_p], shadow_uv, coat, t_stage)
    m_env = jnp.where(m_seen[:, None], env[n_p:] * m_hits.rho_d, sky)
    m_unit = jnp.where(m_seen[:, None, None, None], unit[n_p:], 0.0)
    beyond = jnp.full((h * w,), FAR_BEYOND, dtype).at[m_index].set(jnp.where(m_seen, m_hits.t, FAR_BEYOND))
    stop = jnp.zeros((h * w,), dtype).at[m_index].set(hits.t[m_index] + jnp.where(m_seen, m_hits.t, jnp.inf))
    mirror = MirrorPixels(m_index, m_hits.rho_d, m_env, m_unit, stop.reshape(h, w), beyond.reshape(h, w))
    # the fires' shadow cameras over the performer's whole path; the stage points they see
    lo, hi = _performer_box(scene, 0.45)
    centers = np.asarray(scene.fires.center, np.float64)
    light_pos, light_rot, tan_c = _shadow_frames(centers, lo, hi, margin=1.1)
    half_rays = _pixel_grid(ph, 2, dtype).reshape(-1, 3)
    half = _cast_jit(scene.stage, jnp.broadcast_to(ph.origin, half_rays.shape), half_rays)
    half_pos = np.asarray(half.position, np.float64)
    half_ok = np.isfinite(np.asarray(half.t))
    cells = []
    for q in range(len(centers)):
        local = (half_pos - light_pos[q]) @ light_rot[q].T
        z = local[:, 2]
        uv = local[:, :2] / np.where(z > 0, z, 1.0)[:, None] / (2 * tan_c) + 0.5
        cells.append(np.flatnonzero(half_ok & (z > near) & np.all((uv >= 0) & (uv <= 1), axis=-1)))
    cap = max(1, max(len(c) for c in cells))
    cell = np.full((len(centers), cap), hh * hw, np.int64)
    pts = np.zeros((len(centers), cap, 3))
    for q, c in enumerate(cells):
        cell[q, :len(c)] = c
        pts[q, :len(c)] = half_pos[c]
        pts[q, len(c):] = light_pos[q] + 1e-3 * light_rot[q][2]     # padding: at the light, never shadowed
    grid = ShadowGrid(jnp.asarray(pts, dtype), jnp.asarray(cell, jnp.int32), (hh, hw))
    # the performer's environment: the samples the stage hides from its middle are dropped
    mesh, px, hidden = _performer_view(scene, ph, view.env_direction, jnp.asarray(0.5 * (lo + hi), dtype))
    performer_env = view.env_weight * (1.0 - hidden)[:, None]
    # where the flames and their mirror images cover the image
    t, uv, inside = view.flame_hits
    flames = _flame_pixels(t, uv, inside & (t > 0) & (t < t_stage[None]))
    t, uv, inside = view.mirrored_flame_hits
    mirrored_flames = _flame_pixels(t, uv, inside & (t > t_stage[None]) & (coat[None] > 0)
                                    & (t < stop.reshape(h, w)[None]))
    # fixed sizes from frame 0, with margins for the motion; boxes from the whole path
    # the G-buffers' windows: most triangles in 16 pixels (the robe's are ~6-17 at 720 x 480), the
    # others of frame 0 (with margins for the motion) in a larger one
    # every size below from projections clipped to the image (or map): a vertex near a camera's plane
    # projects arbitrarily far, but a buffer never needs more than the image's pixels
    image = np.asarray([w, h], np.float64)
    px = np.clip(np.nan_to_num(np.asarray(px, np.float64), nan=0.0), 0.0, image)
    view_ext = np.max(np.ptp(px[np.asarray(mesh.triangles)], axis=1), axis=-1) + 2
    window = 16
    large_view_window = pow2(max(2 * window, 1.5 * float(view_ext.max())))
    large_view_capacity = round_up(2 * int(np.sum(view_ext > window)) + 64, 64)
    corners = np.asarray([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])])
    view_box = pixel_box(_project_bounds(ph, corners), ph, 0.02)
    mirror_box = pixel_box(_project_bounds(ph, corners * np.asarray([1.0, -1.0, 1.0])), ph, 0.02)
    covered = float(np.ptp(px[:, 0]) * np.ptp(px[:, 1]))
    # the depth maps' windows: most triangles in 1/32 of the map's side, the larger ones of frame 0
    # (with margins for the motion) in their own window (`motion.fire_depth_maps`)
    shadow_window = pow2(shadow_resolution / 32)
    verts, tris = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.triangles)
    largest, most = 0.0, 0
    for q in range(len(centers)):
        local = (verts - light_pos[q]) @ light_rot[q].T
        sp = (local[:, :2] / np.maximum(local[:, 2:3], 1e-6) / (2 * tan_c) + 0.5) * shadow_resolution
        sp = np.clip(np.nan_to_num(sp, nan=0.0), 0.0, shadow_resolution)
        ext = np.max(np.ptp(sp[tris], axis=1), axis=-1) + 2
        largest, most = max(largest, float(ext.max())), max(most, int(np.sum(ext > shadow_window)))
    steps = max(1, int(round(frame_dt / scene.performer.costume.dt)))
    return NohRig(ph, view.rays, view.background, view.mirrored_sky, stage, mirror, grid, view.env_direction,
                  performer_env, flames, mirrored_flames, jnp.asarray(light_pos, dtype), jnp.asarray(light_rot, dtype),
                  float(tan_c), window, large_view_window, large_view_capacity, shadow_window,
                  large_shadow_window(max(2 * shadow_window, 1.5 * largest), shadow_resolution),
                  round_up(1.5 * most + 32, 64), shadow_resolution,
                  round_up(0.75 * covered),
                  round_up(0.35 * covered), steps, float(near), float(roughness), view_box, mirror_box)


def _project_bounds(ph: Pinhole, points: np.ndarray) -> np.ndarray:
    """(x0, y0, x1, y1) of points projected by the pinhole (host-side)."""
    local = (points - np.asarray(ph.origin)) @ np.asarray(ph.rotation).T
    z = np.where(np.abs(local[:, 2]) > 1e-9, local[:, 2], 1e-9)
    x, y = ph.cx + ph.fx * local[:, 0] / z, ph.cy + ph.fy * local[:, 1] / z
    return np.asarray([x.min(), y.min(), x.max(), y.max()])


_cast_jit = jax.jit(cast_stage)
_static_light_jit = eqx.filter_jit(static_light)

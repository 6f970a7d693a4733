"""Everything of a Noh sequence that does not change from frame to frame (`prepare_noh`): what the
camera sees, the garment's shadow maps from each fire and PCSS visibility of every visible point
(`jaxrender.shadows.pcss`, light size = the flame's width), the static environment light I_static
(K directions drawn once by luminance x sin(theta), blocked below the horizon by the ground), the
sky behind, and where the flame billboards cover the image.

Two jitted stages around a host-side compaction of the garment and floor pixels (their counts fix
the shapes of everything per point)."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from jaxrender.brdf import BTFTexel, Lobe
from jaxrender.fabric import (
    GBuffer,
    Pinhole,
    camera_pinhole,
    depth_map,
    raster_window,
    rasterize,
    spot_pinhole,
    tangent_frames,
)
from jaxrender.lights import env_radiance, sample_envmap
from jaxrender.maths import dot, normalize
from jaxrender.shadows import ShadowMap, pcss

from .mask import LABELS
from .scene import FIRE_SIZE, NohScene
from .shading import FloorPoints, GarmentPoints, shade_floor, shade_garment, shared_light


class ViewSurfaces(eqx.Module):
    """Per pixel: the garment's G-buffer, the view ray, the distance to the floor plane, and
    which of the two (or neither: sky) the pixel sees."""

    gbuffer: GBuffer
    rays: Float[Array, "H W 3"]
    t_floor: Float[Array, "H W"]
    garment: Bool[Array, "H W"]
    floor: Bool[Array, "H W"]


class FlameBillboards(eqx.Module):
    """Where each fire's flame quad (facing the camera) covers a pixel in front of the surfaces."""

    uv: Float[Array, "Q H W 2"]
    hit: Float[Array, "Q H W"]


class NohPrepared(eqx.Module):
    """Everything constant over a sequence (see the module docstring)."""

    garment: GarmentPoints
    floor: FloorPoints
    garment_vis: Float[Array, "G Q"]      # PCSS visibility of each fire
    floor_vis: Float[Array, "P Q"]
    garment_static: Float[Array, "G 3"]   # I_static: the environment's light
    floor_static: Float[Array, "P 3"]
    background: Float[Array, "H W 3"]
    flames: FlameBillboards
    env_direction: Float[Array, "K 3"]


def floor_texels(pos: Array) -> BTFTexel:
    """Hinoki planks on the stage (|x| < 3, -3 < z < 2.5), white gravel around it."""
    x, z = pos[:, 0], pos[:, 2]
    plank = jnp.floor(x / 0.3)
    grain = 0.85 + 0.15 * jnp.sin(z * 7.0 + plank * 1.7 + 2.0 * jnp.sin(z * 1.3 + plank))
    seam = jnp.clip(jnp.abs(x / 0.3 - jnp.round(x / 0.3)) * 40, 0.3, 1.0)
    tone = 0.8 + 0.2 * jnp.sin(plank * 12.9898) ** 2
    wood = jnp.stack([0.32 * jnp.ones_like(x), 0.2 * jnp.ones_like(x), 0.11 * jnp.ones_like(x)], -1)
    wood = wood * (grain * seam * tone)[:, None]
    stage = (jnp.abs(x) < 3.0) & (z > -3.0) & (z < 2.5)
    gravel = jnp.stack([0.22 * jnp.ones_like(x), 0.22 * jnp.ones_like(x), 0.21 * jnp.ones_like(x)], -1)
    rho_d = jnp.where(stage[:, None], wood, gravel)
    rho_s = jnp.where(stage[:, None], 0.08, 0.0) * jnp.ones_like(rho_d)
    n = jnp.zeros_like(rho_d).at[:, 2].set(1.0)
    s = jnp.where(stage, 0.15, 0.5)
    lobe = Lobe(rho_s, n, s, s)
    return BTFTexel(rho_d, lobe, lobe, jnp.zeros_like(s))


def fire_shadow_maps(scene: NohScene, resolution: int) -> list[ShadowMap]:
    """One depth map of the garment per fire, all with the same field of view (one compile)."""
    verts = scene.vertices
    lo, hi = np.asarray(jnp.min(verts, axis=0)), np.asarray(jnp.max(verts, axis=0))
    target = jnp.asarray(0.5 * (lo + hi), dtype=verts.dtype)
    corners = jnp.asarray([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1]) for c in (lo[2], hi[2])],
                          dtype=verts.dtype)
    frames, tan_c = [], 0.0
    for q in range(scene.fires.center.shape[0]):
        pos = scene.fires.center[q]
        zaxis = normalize(target - pos)
        xaxis = normalize(jnp.cross(jnp.asarray([0.0, 1.0, 0.0], dtype=pos.dtype), zaxis))
        rot = jnp.stack([xaxis, jnp.cross(zaxis, xaxis), zaxis])
        local = (corners - pos[None, :]) @ rot.T
        tan_c = max(tan_c, float(jnp.max(jnp.abs(local[:, :2]) / local[:, 2:3])) * 1.1)
        frames.append((pos, rot))
    phs = [spot_pinhole(pos, rot, tan_c, resolution) for pos, rot in frames]
    window = max(raster_window(ph, verts, scene.triangles) for ph in phs)
    render = eqx.filter_jit(lambda ph, v: depth_map(ph, v, scene.triangles, window=window))
    return [ShadowMap(depth=render(ph, verts), position=pos, rotation=rot,
                      tan_cutoff=jnp.asarray(tan_c, dtype=pos.dtype))
            for ph, (pos, rot) in zip(phs, frames)]


def view_surfaces(ph: Pinhole, scene: NohScene, window: int) -> ViewSurfaces:
    """Rasterize the garment and intersect the floor plane y = 0 for every pixel."""
    gb = rasterize(ph, scene.vertices, scene.triangles, scene.uv, window=window)
    dtype = scene.vertices.dtype
    gy, gx = jnp.meshgrid(jnp.arange(ph.height, dtype=dtype) + 0.5, jnp.arange(ph.width, dtype=dtype) + 0.5,
                          indexing="ij")
    rays = ph.ray(jnp.stack([gx, gy], -1))                          # H W 3
    down = rays[..., 1] < -1e-6
    t_floor = jnp.where(down, -ph.origin[1] / jnp.where(down, rays[..., 1], -1.0), jnp.inf)
    garment = (gb.hit > 0) & (gb.distance < t_floor)
    floor = ~garment & jnp.isfinite(t_floor)
    return ViewSurfaces(gb, rays, t_floor, garment, floor)


def _flat(a: Array) -> Array:
    return a.reshape((a.shape[0] * a.shape[1],) + a.shape[2:])


def garment_points(ph: Pinhole, scene: NohScene, gb: GBuffer, index: Array) -> GarmentPoints:
    """Position, shading frame (tangent along the uv's u), BTF uv footprint and material of the
    garment pixels `index`."""
    tri = _flat(gb.triangle)[index]
    bary = _flat(gb.barycentric)[index]
    vid = scene.triangles[tri]
    n = sum(bary[:, i:i + 1] * scene.vertex_normals[vid[:, i]] for i in range(3))
    p0, p1, p2 = (scene.vertices[vid[:, i]] for i in range(3))
    t0, t1, t2 = (scene.uv[vid[:, i]] for i in range(3))
    e1, e2, d1, d2 = p1 - p0, p2 - p0, t1 - t0, t2 - t0
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    det = jnp.where(jnp.abs(det) > 1e-12, det, 1e-12)
    dpdu = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / det[:, None]
    pos = _flat(gb.position)[index]
    wo = normalize(ph.origin[None, :] - pos)
    n = normalize(n)
    n = jnp.where((jnp.sum(n * wo, -1) < 0)[:, None], -n, n)   # two-sided: face the viewer
    uv = _flat(gb.uv)[index]
    hm, wm = scene.labels.shape
    col = jnp.clip(jnp.floor(uv[:, 0] * wm).astype(jnp.int32), 0, wm - 1)
    row = jnp.clip(jnp.floor(uv[:, 1] * hm).astype(jnp.int32), 0, hm - 1)
    material = scene.labels[row, col]
    use_colour = (material == LABELS.index("pattern")).astype(pos.dtype)
    return GarmentPoints(index, pos, tangent_frames(n, dpdu), wo, uv * scene.tiles,
                         _flat(gb.duv_dx)[index] * scene.tiles, _flat(gb.duv_dy)[index] * scene.tiles,
                         material, scene.colours[row, col], use_colour)


def floor_points(ph: Pinhole, view: ViewSurfaces, index: Array) -> FloorPoints:
    rays = _flat(view.rays)[index]
    pos = ph.origin[None, :] + _flat(view.t_floor)[index][:, None] * rays
    return FloorPoints(index, pos, -rays, floor_texels(pos))


def fire_visibility(maps: list[ShadowMap], points: Array, near: float) -> Float[Array, "N Q"]:
    """PCSS per fire, light size = the flame's width, blockers no nearer than `near`."""
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *maps)     # one traced PCSS, vmapped over fires
    return jax.vmap(lambda sm: pcss(sm, points, light_size=float(FIRE_SIZE[0]), near=near, bias=0.02))(stacked).T


def quad_hits(center: Float[Array, "Q 3"], u: Float[Array, "Q 3"], v: Float[Array, "Q 3"], eye: Float[Array, "3"],
              rays: Float[Array, "H W 3"]
              ) -> tuple[Float[Array, "Q H W"], Float[Array, "Q H W 2"], Bool[Array, "Q H W"]]:
    """Each quad (centre, half-edge vectors u, v) against the rays from `eye`: the ray distance
    to its plane, the quad's uv there (u right, v up -> rows down) and whether it lies inside."""
    ts, uvs, ins = [], [], []
    for q in range(center.shape[0]):  # four fires: unrolled
        nrm = normalize(jnp.cross(u[q], v[q]))
        safe = jnp.where(jnp.abs(dot(rays, nrm)) > 1e-9, dot(rays, nrm), 1e-9)
        t = dot(center[q] - eye, nrm) / safe
        p = t[..., None] * rays + jnp.reshape(eye - center[q], (1, 1, 3))   # hit point relative to the centre
        a = dot(p, u[q]) / dot(u[q], u[q])
        b = dot(p, v[q]) / dot(v[q], v[q])
        ts.append(t)
        uvs.append(jnp.stack([(a + 1) / 2, (1 - b) / 2], -1))
        ins.append((jnp.abs(a) <= 1) & (jnp.abs(b) <= 1))
    return jnp.stack(ts), jnp.stack(uvs), jnp.stack(ins)


def flame_billboards(scene: NohScene, ph: Pinhole, view: ViewSurfaces) -> FlameBillboards:
    """Each flame quad hit by each view ray in front of the garment or floor, with its uv."""
    fl = scene.fires
    surface_t = jnp.where(view.garment, view.gbuffer.distance, view.t_floor)
    t, uv, inside = quad_hits(fl.center, fl.u, fl.v, ph.origin, view.rays)
    return FlameBillboards(uv, (inside & (t > 0) & (t < surface_t[None])).astype(view.rays.dtype))


def prepare_points(ph: Pinhole, scene: NohScene, view: ViewSurfaces, g_index: Array, f_index: Array,
                   maps: list[ShadowMap], key: PRNGKeyArray, k_env: int, near: float) -> NohPrepared:
    """The second stage of `prepare_noh`, for the compacted garment and floor pixels."""
    garment = garment_points(ph, scene, view.gbuffer, g_index)
    floor = floor_points(ph, view, f_index)
    vis = fire_visibility(maps, jnp.concatenate([garment.position, floor.position], axis=0), near)
    n_garment = garment.position.shape[0]
    s = sample_envmap(scene.env, key, k_env)
    env_weight = s.radiance * ((s.direction[:, 1] > 0).astype(s.radiance.dtype) / (k_env * s.pdf))[:, None]
    garment_static = shade_garment(scene.mats, garment, shared_light(s.direction, env_weight, n_garment))
    floor_static = shade_floor(floor, shared_light(s.direction, env_weight, floor.position.shape[0]))
    background = env_radiance(scene.env, view.rays, filter="mitsuba")
    return NohPrepared(garment, floor, vis[:n_garment], vis[n_garment:], garment_static, floor_static, background,
                       flame_billboards(scene, ph, view), s.direction)


_view_surfaces_jit = eqx.filter_jit(view_surfaces)
_prepare_points_jit = eqx.filter_jit(prepare_points)


def prepare_noh(scene: NohScene, *, key: PRNGKeyArray | None = None, k_env: int = 20, shadow_resolution: int = 512,
                near: float = 0.5) -> NohPrepared:
    """Rasterize, intersect the floor, sample the environment, PCSS per fire, I_static."""
    key = jax.random.key(7) if key is None else key
    ph = camera_pinhole(scene.camera)
    view = _view_surfaces_jit(ph, scene, raster_window(ph, scene.vertices, scene.triangles))
    g_index = jnp.asarray(np.flatnonzero(np.asarray(view.garment)), dtype=jnp.int32)
    f_index = jnp.asarray(np.flatnonzero(np.asarray(view.floor)), dtype=jnp.int32)
    maps = fire_shadow_maps(scene, shadow_resolution)
    return _prepare_points_jit(ph, scene, view, g_index, f_index, maps, key, k_env, near)

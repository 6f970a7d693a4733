"""Takigi Noh (paper 004, section 4): a draped Noh costume by firelight under a dusk sky.

Scene (metres, y up, the stage floor at y = 0): a garment hung from two shoulder points
(`sims.cloth.drape_cloth`, Verlet mass-spring) in front of the camera; a hinoki stage floor
(|x| < 3, -3 < z < 2.5) inside white gravel; four bonfires around the stage, each a flame quad whose
emission texture is the current frame of `sims.fire.fire_frames`; the environment: a procedural
dusk sky (`jaxrender.sky.sky_envmap`, sun 2 degrees above the horizon) or any user EXR (lat-long,
Mitsuba `envmap` orientation).

Materials (paper Fig. 7): a mask over the garment's uv assigns each region a BTF: by the mask's
8-bit colour, gold (255, 255, 0) = `brocade` (kinran), green (0, 255, 0) = `hexagon`
(tortoise-shell kikko weave), cyan (0, 255, 255) = `satin` (the underlayer); any other colour is
the plain `pattern` weave whose rho_d is that colour (sRGB-decoded). BTFs are pyramids of 1- or
2-lobe levels (`jaxrender.fabric`), repeated `tiles` times across the garment.

Lighting per frame (eqs. 2-4): I = I_static + I_dynamic. I_static: K environment directions
drawn once per sequence by luminance x sin(theta) (`jaxrender.lights.sample_envmap`), blocked
below the horizon by the ground. I_dynamic: K_f points drawn over all four flame quads by emitted
power for the frame (`jaxrender.lights.sample_quad_lights`), shared by all shading points;
flames are volumes, so each flame quad is treated as facing the shading point (|cos_y| = 1)
while its texture gives the radiance; each fire's visibility at a point is PCSS
(`jaxrender.shadows.pcss`) over a 512^2 depth map of the garment rendered from the fire
(`jaxrender.fabric.depth_map`, SHAFTS's ShadowMap format), light size = the flame's width.
The geometry, the environment samples, the shadows and I_static are computed once per sequence
(`prepare_noh`); a frame (`noh_frame`) is the firelight, the visible flames and compositing.
Visible flames are added to the image (additive, in front of whatever lies behind them).
"""

from __future__ import annotations

import functools
import math
import os
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, PRNGKeyArray

from ..maths import normalize
from ..brdf import BTFTexel, Lobe
from ..camera import Camera
from ..fabric import (MaterialSet, camera_pinhole, depth_map, raster_window, rasterize, shade_fabric, shade_single_lobe,
                      spot_pinhole, stack_materials, tangent_frames)
from ..lights import (EnvMap, QuadLights, env_radiance, sample_envmap,
                      sample_quad_lights)
from ..shadows import ShadowMap, pcss
from ..textures import bilinear

__all__ = ["LABELS", "PALETTE", "default_mask", "mask_from_rgb", "procedural_btf", "default_btfs",
           "default_environment", "NohScene", "NohPrepared", "noh_scene", "prepare_noh", "noh_frame",
           "render_noh", "gallery_section"]

LABELS = ("brocade", "hexagon", "satin", "pattern")
PALETTE = {"brocade": (255, 255, 0), "hexagon": (0, 255, 0), "satin": (0, 255, 255)}
_PATTERN_COLOURS = ((190, 30, 40), (235, 230, 215), (40, 60, 140), (230, 120, 40))   # sRGB 8-bit


def _dtype():
    return jnp.float64 if jax.config.jax_enable_x64 else jnp.float32


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


# ---------------------------------------------------------------------------------------------
# Mask


def mask_from_rgb(rgb8: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(labels H W int32 indices into LABELS, pattern colour H W 3 linear) from an 8-bit RGB mask."""
    rgb8 = np.asarray(rgb8)
    labels = np.full(rgb8.shape[:2], LABELS.index("pattern"), np.int32)
    for name, colour in PALETTE.items():
        hit = np.all(np.abs(rgb8[..., :3].astype(np.int32) - np.asarray(colour)) <= 2, axis=-1)
        labels[hit] = LABELS.index(name)
    colour = _srgb_to_linear(rgb8[..., :3].astype(np.float64) / 255.0).astype(np.float32)
    return labels, colour


def default_mask(size: int = 256) -> np.ndarray:
    """The built-in 8-bit RGB mask over the garment's uv (row 0 = the shoulders): dan-gawari
    blocks alternating gold brocade and hexagon weave, flower roundels in the plain weave's
    colours, and a satin underlayer showing at the hem."""
    v, u = np.meshgrid((np.arange(size) + 0.5) / size, (np.arange(size) + 0.5) / size, indexing="ij")
    out = np.zeros((size, size, 3), np.uint8)
    block = (np.floor(u * 2).astype(int) + np.floor(v * 3).astype(int)) % 2
    out[block == 0] = PALETTE["brocade"]
    out[block == 1] = PALETTE["hexagon"]
    # flower roundels on a staggered lattice: five petals around a centre
    cells = 5
    cu, cv = u * cells, v * cells * 1.5
    row = np.floor(cv)
    cu = cu + 0.5 * (row % 2)
    fu, fv = cu - np.floor(cu) - 0.5, cv - row - 0.5
    r = np.hypot(fu, fv)
    ang = np.arctan2(fv, fu)
    petal = r < 0.22 + 0.12 * np.cos(5 * ang)
    idx = (np.floor(cu).astype(int) * 7 + row.astype(int) * 3) % len(_PATTERN_COLOURS)
    colours = np.asarray(_PATTERN_COLOURS, np.uint8)[idx]
    out[petal] = colours[petal]
    centre = r < 0.07
    out[centre] = (235, 200, 60)  # a golden-yellow centre painted in the plain weave
    out[v > 0.9] = PALETTE["satin"]
    return out


# ---------------------------------------------------------------------------------------------
# Procedural BTFs (level 0, one lobe); the pyramid is built by EM (`fitting.pyramid`)


def procedural_btf(kind: str, size: int = 32, *, key: PRNGKeyArray | None = None) -> BTFTexel:
    """A one-lobe level-0 BTF `size x size` of a woven structure.

    `brocade`: `fitting.synth.synth_maps` (silk ground with gold weft floats); `hexagon`: a
    tortoise-shell hexagon weave (threads circling each cell: normals tilt away from the cell
    centre, anisotropy along the rim); `satin`: long warp floats (narrow highlights across them);
    `pattern`: a plain weave of white silk (rho_d replaced by the mask colour when rendering).
    """
    dtype = _dtype()
    key = jax.random.key(0) if key is None else key
    if kind == "brocade":
        from fitting.synth import synth_maps

        t = synth_maps(key, (size, size))
        # a warmer, gold-dominated brocade: make the silk ground a deep red
        gold = t.lobe0.rho_s[..., 0] > 1.0
        red = jnp.asarray([0.35, 0.03, 0.03], dtype=dtype)
        rho_d = jnp.where(gold[..., None], t.rho_d, red * (t.rho_d[..., :1] / jnp.maximum(jnp.mean(t.rho_d[..., :1]), 1e-6)))
        return BTFTexel.single(rho_d.astype(dtype), t.lobe0.rho_s.astype(dtype), t.lobe0.normal.astype(dtype),
                               t.lobe0.sigma_x.astype(dtype), t.lobe0.sigma_y.astype(dtype))
    y, x = np.meshgrid((np.arange(size) + 0.5) / size, (np.arange(size) + 0.5) / size, indexing="ij")
    if kind == "hexagon":
        cells = 2.0
        # hexagonal lattice: nearest centre among two offset rectangular lattices
        sx, sy = x * cells, y * cells * math.sqrt(3) / 1.0
        a = np.stack([np.round(sx), np.round(sy / math.sqrt(3)) * math.sqrt(3)], -1)
        b = np.stack([np.floor(sx) + 0.5, (np.floor(sy / math.sqrt(3)) + 0.5) * math.sqrt(3)], -1)
        p = np.stack([sx, sy], -1)
        c = np.where((np.sum((p - a) ** 2, -1) < np.sum((p - b) ** 2, -1))[..., None], a, b)
        d = p - c
        r = np.hypot(d[..., 0], d[..., 1])
        rim = np.clip((r - 0.25) / 0.3, 0, 1)
        tilt = 0.6 * rim
        nx, ny = tilt * d[..., 0] / np.maximum(r, 1e-6), -tilt * d[..., 1] / np.maximum(r, 1e-6)
        normal = np.stack([nx, ny, np.ones_like(nx)], -1)
        rho_d = np.where((rim > 0.5)[..., None], [0.05, 0.22, 0.12], [0.02, 0.10, 0.08])
        rho_s = np.where((rim > 0.5)[..., None], [0.5, 0.55, 0.45], [0.25, 0.3, 0.25])
        sigma_x = np.where(rim > 0.5, 0.12, 0.3)
        sigma_y = np.where(rim > 0.5, 0.3, 0.12)
    elif kind == "satin":
        floats = 8
        a = (x * floats) % 1.0 * 2 - 1
        normal = np.stack([0.5 * a, 0.05 * np.sin(2 * np.pi * (y * 4 + np.floor(x * floats) * 0.37)), np.ones_like(a)], -1)
        rho_d = np.broadcast_to(np.asarray([0.18, 0.35, 0.5]), x.shape + (3,)) * (1 - 0.3 * a[..., None] ** 4)
        rho_s = np.broadcast_to(np.asarray([0.7, 0.75, 0.8]), x.shape + (3,))
        sigma_x, sigma_y = np.full(x.shape, 0.25), np.full(x.shape, 0.06)
    elif kind == "pattern":
        p = max(2, size // 8)
        i, j = np.floor(y * size).astype(int) // p, np.floor(x * size).astype(int) // p
        warp_up = (i + j) % 2 == 0
        a = ((x * size) % p + 0.5 - 0.5) / p * 2 - 1
        b = ((y * size) % p + 0.5 - 0.5) / p * 2 - 1
        normal = np.stack([np.where(warp_up, 0.5 * a, 0.2 * a), np.where(warp_up, -0.2 * b, -0.5 * b), np.ones_like(a)], -1)
        rho_d = np.broadcast_to(np.asarray([0.7, 0.7, 0.7]), x.shape + (3,)).copy()
        rho_s = np.broadcast_to(np.asarray([0.3, 0.3, 0.3]), x.shape + (3,))
        sigma_x = np.where(warp_up, 0.3, 0.12)
        sigma_y = np.where(warp_up, 0.12, 0.3)
    else:
        raise ValueError(f"unknown BTF kind {kind!r}: use one of {LABELS}")
    normal = normal / np.linalg.norm(normal, axis=-1, keepdims=True)
    arr = lambda z: jnp.asarray(np.ascontiguousarray(z), dtype=dtype)  # noqa: E731
    return BTFTexel.single(arr(rho_d), arr(rho_s), arr(normal), arr(sigma_x), arr(sigma_y))


def btf_levels_from_channels(levels: list[dict]) -> list[BTFTexel]:
    """BTFTexel levels from `jaxrender.io.read_btf`'s channel dicts."""
    dtype = _dtype()
    return [jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=dtype), BTFTexel.from_channels(c)) for c in levels]


def default_btfs(*, size: int = 32, pyramid: str = "em", key: PRNGKeyArray | None = None) -> dict[str, list[BTFTexel]]:
    """Level pyramids for every label from `procedural_btf`; `pyramid`: `em` (2-lobe EM levels,
    `fitting.pyramid.pyramid_levels`) or `none` (level 0 only)."""
    key = jax.random.key(0) if key is None else key
    out = {}
    for i, name in enumerate(LABELS):
        level0 = procedural_btf(name, size, key=jax.random.fold_in(key, i))
        levels = [level0]
        if pyramid == "em":
            from fitting.pyramid import pyramid_levels

            levels += list(pyramid_levels(level0)[0])
        elif pyramid != "none":
            raise ValueError(f"unknown pyramid {pyramid!r}: use 'em' or 'none'")
        out[name] = levels
    return out


@functools.lru_cache(maxsize=4)
def _sky(width: int, height: int, elevation: float, azimuth: float) -> np.ndarray:
    from ..sky import sky_envmap, sun_direction

    return np.asarray(sky_envmap(sun_direction(elevation, azimuth), width=width, height=height, sun_disk=True))


def default_environment(*, width: int = 128, height: int = 64, sun_elevation_deg: float = -2.0,
                        sun_azimuth_deg: float = 235.0, irradiance: float = 0.08) -> EnvMap:
    """Twilight from `jaxrender.sky.sky_envmap` (the sun just below the horizon, behind-left of
    the stage), scaled so that the sky's irradiance on the horizontal stage is `irradiance`
    (the bonfires then dominate, as at a takigi Noh after sunset)."""
    sky = _sky(width, height, float(sun_elevation_deg), float(sun_azimuth_deg))
    rows = np.arange(height)
    omega = 2 * np.pi / width * (np.cos(np.pi * rows / height) - np.cos(np.pi * (rows + 1) / height))
    cos_t = np.cos(np.pi * (rows + 0.5) / height)
    lum = 0.2126 * sky[..., 0] + 0.7152 * sky[..., 1] + 0.0722 * sky[..., 2]
    e = float(np.sum(lum * (np.maximum(cos_t, 0) * omega)[:, None]))
    return EnvMap.from_array(jnp.asarray(sky, dtype=_dtype()), scale=irradiance / max(e, 1e-12))


# ---------------------------------------------------------------------------------------------
# Scene


@functools.lru_cache(maxsize=2)
def _cloth(rows: int, cols: int):
    from sims.cloth import drape_cloth

    return drape_cloth(rows=rows, cols=cols, top=1.6, height=1.5, shoulder_span=1.0, shoulder_u=0.08, body_radius=0.12,
                       body_z=-0.16, folds=5, fold_depth=0.05)


class NohScene(eqx.Module):
    camera: Camera
    vertices: Float[Array, "V 3"]
    vertex_normals: Float[Array, "V 3"]
    uv: Float[Array, "V 2"]
    triangles: Int[Array, "T 3"]
    fires: QuadLights                       # emission: the flame sequences, F_fires x frames x H x W x 3
    flames: Float[Array, "Q N H W 3"]
    labels: Int[Array, "Hm Wm"]
    colours: Float[Array, "Hm Wm 3"]
    mats: MaterialSet
    env: EnvMap
    tiles: float = eqx.field(static=True)


FIRE_POSITIONS = ((-1.25, 0.9), (1.25, 0.9), (-1.6, -1.3), (1.6, -1.3))   # (x, z) of the four bonfires
FIRE_SIZE = (0.55, 0.8)                                                    # width, height (m)
FIRE_BASE = 0.95                                                           # flames burn in baskets on stands (m)


def noh_scene(*, width: int = 720, height: int = 480, frames: int = 20, key: PRNGKeyArray | None = None,
              mask_rgb: np.ndarray | None = None, btfs: dict[str, list[BTFTexel]] | None = None,
              env: EnvMap | None = None, cloth_rows: int = 40, cloth_cols: int = 32, tiles: float = 6.0,
              flame_size: tuple[int, int] = (128, 64), fire_intensity: float = 12.0, btf_size: int = 32,
              pyramid: str = "em") -> NohScene:
    """Assemble the scene; every input not given is the built-in one (module docstring)."""
    from sims.fire import fire_frames

    key = jax.random.key(2024) if key is None else key
    dtype = _dtype()
    cam = Camera((0.9, 1.2, 3.4), (0.0, 0.82, 0.0), (0.0, 1.0, 0.0), 40.0, width=width, height=height)
    cloth = _cloth(cloth_rows, cloth_cols)
    verts = cloth.vertices.reshape(-1, 3).astype(dtype)
    normals = cloth.normals.reshape(-1, 3).astype(dtype)
    uv = cloth.uv.reshape(-1, 2).astype(dtype)
    centers, us, vs = [], [], []
    w, h = FIRE_SIZE
    for x, z in FIRE_POSITIONS:
        to_cam = np.asarray([float(cam.eye[0]) - x, 0.0, float(cam.eye[2]) - z])
        to_cam /= np.linalg.norm(to_cam)
        right = np.cross([0.0, 1.0, 0.0], to_cam)
        centers.append([x, FIRE_BASE + h / 2, z])
        us.append(right * w / 2)
        vs.append([0.0, h / 2, 0.0])
    keys = jax.random.split(key, len(FIRE_POSITIONS))
    flames = jnp.stack([fire_frames(k, frames=frames, height=flame_size[0], width=flame_size[1],
                                    intensity=fire_intensity) for k in keys]).astype(dtype)
    fires = QuadLights(jnp.asarray(centers, dtype=dtype), jnp.asarray(np.asarray(us), dtype=dtype),
                       jnp.asarray(vs, dtype=dtype), flames[:, 0])
    labels, colours = mask_from_rgb(default_mask() if mask_rgb is None else mask_rgb)
    btfs = default_btfs(size=btf_size, pyramid=pyramid) if btfs is None else btfs
    missing = [name for name in LABELS if name not in btfs]
    if missing:
        fallback = default_btfs(size=btf_size, pyramid=pyramid)
        btfs = {**{n: fallback[n] for n in missing}, **btfs}
    mats = stack_materials([btfs[name] for name in LABELS])
    env = default_environment() if env is None else env
    return NohScene(cam, verts, normals, uv, jnp.asarray(cloth.triangles), fires, flames,
                    jnp.asarray(labels), jnp.asarray(colours, dtype=dtype), mats, env, float(tiles))


class NohPrepared(eqx.Module):
    """Everything constant over a sequence (see `prepare_noh`)."""

    g_index: Int[Array, "G"]
    g_pos: Float[Array, "G 3"]
    g_frame: Float[Array, "G 3 3"]
    g_wo: Float[Array, "G 3"]
    g_uv: Float[Array, "G 2"]
    g_dx: Float[Array, "G 2"]
    g_dy: Float[Array, "G 2"]
    g_material: Int[Array, "G"]
    g_colour: Float[Array, "G 3"]
    g_use_colour: Float[Array, "G"]
    g_vis: Float[Array, "G Q"]
    g_static: Float[Array, "G 3"]
    f_index: Int[Array, "P"]
    f_pos: Float[Array, "P 3"]
    f_wo: Float[Array, "P 3"]
    f_texel: BTFTexel
    f_vis: Float[Array, "P Q"]
    f_static: Float[Array, "P 3"]
    background: Float[Array, "H W 3"]
    fire_uv: Float[Array, "Q H W 2"]
    fire_hit: Float[Array, "Q H W"]
    env_direction: Float[Array, "K 3"]


def _floor_texels(pos: Array) -> BTFTexel:
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


def _fire_shadow_maps(scene: NohScene, resolution: int) -> list[ShadowMap]:
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
        local = (corners - pos) @ rot.T
        tan_c = max(tan_c, float(jnp.max(jnp.abs(local[:, :2]) / local[:, 2:3])) * 1.1)
        frames.append((pos, rot))
    phs = [spot_pinhole(pos, rot, tan_c, resolution) for pos, rot in frames]
    window = max(raster_window(ph, verts, scene.triangles) for ph in phs)
    render = eqx.filter_jit(lambda ph, v: depth_map(ph, v, scene.triangles, window=window))
    return [ShadowMap(depth=render(ph, verts), position=pos, rotation=rot, tan_cutoff=jnp.asarray(tan_c, dtype=pos.dtype))
            for ph, (pos, rot) in zip(phs, frames)]


def _stage1(ph, scene: NohScene, window: int):
    gb = rasterize(ph, scene.vertices, scene.triangles, scene.uv, window=window)
    h, w = ph.height, ph.width
    dtype = scene.vertices.dtype
    gy, gx = jnp.meshgrid(jnp.arange(h, dtype=dtype) + 0.5, jnp.arange(w, dtype=dtype) + 0.5, indexing="ij")
    rays = ph.ray(jnp.stack([gx, gy], -1))                          # H W 3
    eye = ph.origin
    down = rays[..., 1] < -1e-6
    t_floor = jnp.where(down, -eye[1] / jnp.where(down, rays[..., 1], -1.0), jnp.inf)
    garment = (gb.hit > 0) & (gb.distance < t_floor)
    floor = ~garment & jnp.isfinite(t_floor)
    return gb, rays, t_floor, garment, floor


def _stage2(ph, scene: NohScene, gb, rays, t_floor, garment, g_index, f_index, maps, key, k_env: int, near: float):
    h, w = ph.height, ph.width
    dtype = scene.vertices.dtype
    eye = ph.origin
    flat = lambda a: a.reshape((h * w,) + a.shape[2:])  # noqa: E731
    # garment surface data
    tri = flat(gb.triangle)[g_index]
    bary = flat(gb.barycentric)[g_index]
    vid = scene.triangles[tri]
    n = sum(bary[:, i:i + 1] * scene.vertex_normals[vid[:, i]] for i in range(3))
    p0, p1, p2 = (scene.vertices[vid[:, i]] for i in range(3))
    t0, t1, t2 = (scene.uv[vid[:, i]] for i in range(3))
    e1, e2, d1, d2 = p1 - p0, p2 - p0, t1 - t0, t2 - t0
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    det = jnp.where(jnp.abs(det) > 1e-12, det, 1e-12)
    dpdu = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / det[:, None]
    g_pos = flat(gb.position)[g_index]
    g_wo = normalize(eye[None, :] - g_pos)
    n = normalize(n)
    n = jnp.where((jnp.sum(n * g_wo, -1) < 0)[:, None], -n, n)   # two-sided: face the viewer
    g_frame = tangent_frames(n, dpdu)
    g_uv_mask = flat(gb.uv)[g_index]
    hm, wm = scene.labels.shape
    mcol = jnp.clip(jnp.floor(g_uv_mask[:, 0] * wm).astype(jnp.int32), 0, wm - 1)
    mrow = jnp.clip(jnp.floor(g_uv_mask[:, 1] * hm).astype(jnp.int32), 0, hm - 1)
    g_material = scene.labels[mrow, mcol]
    g_colour = scene.colours[mrow, mcol]
    g_use = (g_material == LABELS.index("pattern")).astype(dtype)

    # floor
    f_pos = eye[None, :] + flat(t_floor)[f_index][:, None] * flat(rays)[f_index]
    f_wo = -flat(rays)[f_index]
    f_texel = _floor_texels(f_pos)

    # shadows: PCSS per fire, light size = the flame's width, blockers no nearer than `near`
    light_size = float(FIRE_SIZE[0])
    stacked = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *maps)     # one traced PCSS, vmapped over fires
    points = jnp.concatenate([g_pos, f_pos], axis=0)
    vis = jax.vmap(lambda sm: pcss(sm, points, light_size=light_size, near=near, bias=0.02))(stacked).T
    g_vis, f_vis = vis[:g_pos.shape[0]], vis[g_pos.shape[0]:]

    # static environment light (same K directions for every point; the ground hides y < 0)
    s = sample_envmap(scene.env, key, k_env)
    env_w = s.radiance * ((s.direction[:, 1] > 0).astype(dtype) / (k_env * s.pdf))[:, None]
    prepared = NohPrepared(g_index, g_pos, g_frame, g_wo, g_uv_mask * scene.tiles, flat(gb.duv_dx)[g_index] * scene.tiles,
                           flat(gb.duv_dy)[g_index] * scene.tiles, g_material, g_colour, g_use, g_vis,
                           jnp.zeros_like(g_pos), f_index, f_pos, f_wo, f_texel, f_vis, jnp.zeros_like(f_pos),
                           jnp.zeros((h, w, 3), dtype), jnp.zeros((4, h, w, 2), dtype), jnp.zeros((4, h, w), dtype),
                           s.direction)
    g_static, f_static = _shade_all(scene.mats, prepared, s.direction, env_w)
    # background sky and the visible flames (billboards facing the camera)
    background = env_radiance(scene.env, rays, filter="mitsuba")
    fire_uv, fire_hit = [], []
    fl = scene.fires
    for q in range(fl.center.shape[0]):  # four fires: unrolled
        nrm = normalize(jnp.cross(fl.u[q], fl.v[q]))
        denom = jnp.sum(rays * nrm, -1)
        safe = jnp.where(jnp.abs(denom) > 1e-9, denom, 1e-9)
        t = jnp.sum((fl.center[q] - eye) * nrm) / safe
        p = eye + t[..., None] * rays - fl.center[q]
        a = jnp.sum(p * fl.u[q], -1) / jnp.sum(fl.u[q] ** 2)
        b = jnp.sum(p * fl.v[q], -1) / jnp.sum(fl.v[q] ** 2)
        inside = (jnp.abs(a) <= 1) & (jnp.abs(b) <= 1) & (t > 0)
        surf_t = jnp.where(garment, gb.distance, t_floor)
        fire_hit.append((inside & (t < surf_t)).astype(dtype))
        fire_uv.append(jnp.stack([(a + 1) / 2, (1 - b) / 2], -1))
    return eqx.tree_at(lambda p: (p.g_static, p.f_static, p.background, p.fire_uv, p.fire_hit), prepared,
                       (g_static, f_static, background, jnp.stack(fire_uv), jnp.stack(fire_hit)))


_stage1_jit = eqx.filter_jit(_stage1)
_stage2_jit = eqx.filter_jit(_stage2)


def prepare_noh(scene: NohScene, *, key: PRNGKeyArray | None = None, k_env: int = 20, shadow_resolution: int = 512,
                near: float = 0.5) -> NohPrepared:
    """Rasterize, intersect the floor, sample the environment, PCSS per fire, I_static.

    Two jitted stages around a host-side compaction of the garment and floor pixels (their
    counts fix the shapes of everything per pixel)."""
    key = jax.random.key(7) if key is None else key
    ph = camera_pinhole(scene.camera)
    window = raster_window(ph, scene.vertices, scene.triangles)
    gb, rays, t_floor, garment, floor = _stage1_jit(ph, scene, window)
    g_index = jnp.asarray(np.flatnonzero(np.asarray(garment)), dtype=jnp.int32)
    f_index = jnp.asarray(np.flatnonzero(np.asarray(floor)), dtype=jnp.int32)
    maps = _fire_shadow_maps(scene, shadow_resolution)
    return _stage2_jit(ph, scene, gb, rays, t_floor, garment, g_index, f_index, maps, key, k_env, near)


def _shade_all(mats: MaterialSet, prep: NohPrepared, directions: Array, weights: Array, *,
               g_weight: Array | None = None, f_weight: Array | None = None, g_dirs=None, f_dirs=None,
               blend: str = "shading") -> tuple[Array, Array]:
    """Garment and floor radiance for K samples (shared directions, or per-point ones)."""
    ng, nf, k = prep.g_pos.shape[0], prep.f_pos.shape[0], directions.shape[0]
    gd = jnp.broadcast_to(directions[None], (ng, k, 3)) if g_dirs is None else g_dirs
    fd = jnp.broadcast_to(directions[None], (nf, k, 3)) if f_dirs is None else f_dirs
    gw = jnp.broadcast_to(weights[None], (ng, k, 3)) if g_weight is None else g_weight
    fw = jnp.broadcast_to(weights[None], (nf, k, 3)) if f_weight is None else f_weight
    g = shade_fabric(mats, prep.g_material, prep.g_uv, prep.g_dx, prep.g_dy, prep.g_frame, prep.g_wo, gd, gw,
                     diffuse_override=prep.g_colour, use_override=prep.g_use_colour, blend=blend)
    dtype = prep.f_pos.dtype
    floor_frame = jnp.broadcast_to(jnp.asarray([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]], dtype=dtype),
                                   (nf, 3, 3))
    f = shade_single_lobe(prep.f_texel, floor_frame, prep.f_wo, fd, fw)
    return g, f


def noh_frame(scene: NohScene, prep: NohPrepared, emission: Float[Array, "Q H W 3"], key: PRNGKeyArray, *,
              k_fire: int = 20, blend: str = "shading") -> Float[Array, "H W 3"]:
    """One frame (linear radiance): I_static + firelight with PCSS + visible flames over the sky."""
    fires = eqx.tree_at(lambda f: f.emission, scene.fires, emission)
    s = sample_quad_lights(fires, key, k_fire)
    q = fires.center.shape[0]
    onehot = (s.light[:, None] == jnp.arange(q, dtype=jnp.int32)[None, :]).astype(emission.dtype)   # K Q

    def weights(points, vis):
        d = s.position[None, :, :] - points[:, None, :]
        r2 = jnp.maximum(jnp.sum(d * d, -1), 1e-8)
        wi = d / jnp.sqrt(r2)[..., None]
        g = (vis @ onehot.T) / (r2 * s.pdf_area[None, :] * k_fire)          # billboard flames: |cos_y| = 1
        return wi, s.radiance[None, :, :] * g[..., None]

    gd, gw = weights(prep.g_pos, prep.g_vis)
    fd, fw = weights(prep.f_pos, prep.f_vis)
    g, f = _shade_all(scene.mats, prep, s.position, s.radiance, g_weight=gw, f_weight=fw, g_dirs=gd, f_dirs=fd,
                      blend=blend)
    h, w = prep.background.shape[0], prep.background.shape[1]
    img = prep.background.reshape(h * w, 3)
    img = img.at[prep.g_index].set(g + prep.g_static)
    img = img.at[prep.f_index].set(f + prep.f_static)
    img = img.reshape(h, w, 3)
    for i in range(q):  # four fires: unrolled
        img = img + prep.fire_hit[i][..., None] * bilinear(emission[i], prep.fire_uv[i], wrap="clamp")
    return img


_noh_frame_jit = eqx.filter_jit(noh_frame)


def render_noh(*, frames: int = 20, width: int = 720, height: int = 480, key: PRNGKeyArray | None = None,
               mask_rgb: np.ndarray | None = None, btfs: dict[str, list[BTFTexel]] | None = None,
               env: EnvMap | None = None, k_env: int = 20, k_fire: int = 20, progress=None,
               info: dict | None = None, time_repeats: int = 0, shadow_resolution: int = 512,
               **scene_kwargs) -> Float[Array, "F H W 3"]:
    """The animation: `frames` linear-radiance frames H x W x 3 (float32).

    `progress(1)` is called after each frame; `info` (a dict) receives `prepare_s`, `compile_s`
    (the first frame, including compilation), `frame_s` (a list, later frames) and `exposure`
    (for `tonemap_frames`: the garment's 90th-percentile luminance in frame 0 -> 0.3).
    `time_repeats` = N: afterwards render N more frames (cycling through the sequence, discarded)
    and put their times into `info["timed_s"]` (compiled, `block_until_ready`).
    """
    key = jax.random.key(2024) if key is None else key
    k_scene, k_env_key, k_frames = jax.random.split(key, 3)
    t0 = time.perf_counter()
    scene = noh_scene(width=width, height=height, frames=frames, key=k_scene, mask_rgb=mask_rgb, btfs=btfs, env=env,
                      **scene_kwargs)
    prep = jax.block_until_ready(prepare_noh(scene, key=k_env_key, k_env=k_env, shadow_resolution=shadow_resolution))
    t1 = time.perf_counter()
    out, frame_s = [], []
    compile_s = None
    for f in range(frames):  # frames are sequential: one jitted call each
        ts = time.perf_counter()
        img = jax.block_until_ready(_noh_frame_jit(scene, prep, scene.flames[:, f], jax.random.fold_in(k_frames, f),
                                                   k_fire=k_fire))
        dt = time.perf_counter() - ts
        if compile_s is None:
            compile_s = dt
        else:
            frame_s.append(dt)
        out.append(np.asarray(img, dtype=np.float32))
        if progress is not None:
            progress(1)
    timed = []
    for i in range(time_repeats):
        ts = time.perf_counter()
        jax.block_until_ready(_noh_frame_jit(scene, prep, scene.flames[:, i % frames],
                                             jax.random.fold_in(k_frames, frames + i), k_fire=k_fire))
        timed.append(time.perf_counter() - ts)
    if info is not None:
        info["timed_s"] = timed
        lum = out[0].reshape(-1, 3)[np.asarray(prep.g_index)] @ np.asarray([0.2126, 0.7152, 0.0722], np.float32)
        info.update(prepare_s=t1 - t0, compile_s=compile_s, frame_s=frame_s,
                    exposure=0.3 / max(float(np.percentile(lum, 90)) if lum.size else 1.0, 1e-6))
    return np.stack(out)


def tonemap_frames(frames: np.ndarray, *, exposure: float | None = None, key_value: float = 0.6) -> np.ndarray:
    """Display-referred (linear, for `write_png`'s sRGB encoding) frames: one exposure for the
    sequence (given, or the 90th percentile luminance of frame 0 -> `key_value`), then the
    `jaxrender.io.tonemap` curve."""
    from ..io import tonemap

    if exposure is None:
        lum = 0.2126 * frames[0, ..., 0] + 0.7152 * frames[0, ..., 1] + 0.0722 * frames[0, ..., 2]
        exposure = key_value / max(float(np.percentile(lum, 90)), 1e-6)
    return np.stack([np.asarray(tonemap(f, exposure=exposure)) for f in frames])


def write_animation(out_dir: str | os.PathLike, frames: np.ndarray, *, gif_name: str = "noh.gif",
                    fps: float = 10.0, exposure: float | None = None) -> list[Path]:
    """frame_NNN.png (tone mapped) + frame_NNN.exr (linear) + an animated GIF; atomic per file."""
    import imageio.v3 as iio

    from ..io import atomic_path, linear_to_srgb, write_exr, write_png

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    shown = tonemap_frames(frames, exposure=exposure)
    paths = []
    for i, (lin, disp) in enumerate(zip(frames, shown)):
        paths.append(write_png(out_dir / f"frame_{i:03d}.png", disp))
        paths.append(write_exr(out_dir / f"frame_{i:03d}.exr", lin))
    rgb8 = (np.clip(np.asarray(linear_to_srgb(shown)), 0, 1) * 255 + 0.5).astype(np.uint8)
    with atomic_path(out_dir / gif_name) as tmp:
        iio.imwrite(tmp, rgb8, extension=".gif", duration=1000.0 / fps, loop=0)
    paths.append(out_dir / gif_name)
    return paths


def gallery_section(out_dir: Path, *, quick: bool = False) -> list[dict]:
    """Noh garment by firelight under a dusk sky: frames + GIF (+ EXR)."""
    out_dir = Path(out_dir)
    sub = out_dir / "noh"
    frames_n, w, h = (3, 160, 120) if quick else (20, 720, 480)
    extra = dict(cloth_rows=16, cloth_cols=13, shadow_resolution=128) if quick else {}
    timings: dict = {}
    t0 = time.perf_counter()
    btfs, source = _gallery_btfs(quick)
    frames = render_noh(frames=frames_n, width=w, height=h, btfs=btfs, info=timings, **extra)
    paths = write_animation(sub, frames, exposure=timings["exposure"])
    total = time.perf_counter() - t0
    rel = [str(p.relative_to(out_dir)) for p in paths if p.suffix in (".png", ".gif")]
    frame_s = timings.get("frame_s") or [float("nan")]
    return [{"title": "Takigi Noh: woven fabric under firelight and a dusk sky (paper 004)",
             "images": [rel[-1], rel[0]],
             "caption": ("A Noh costume (Verlet-draped cloth) with gold brocade, hexagon (kikko) weave, satin "
                         f"underlayer and coloured plain-weave roundels chosen by a mask; BTFs: {source}. "
                         "Lit by 20 environment samples of a physically based "
                         "dusk sky and 20 samples per frame over four Perlin-noise bonfires, with PCSS shadows."),
             "params": {"frames": frames_n, "width": w, "height": h, "k_env": 20, "k_fire": 20, "btfs": source},
             "timings": {"total_s": total, "prepare_s": timings.get("prepare_s"),
                         "first_frame_s": timings.get("compile_s"), "median_frame_s": float(np.median(frame_s))}}]


def _gallery_btfs(quick: bool):
    """BTFs for the gallery: the gold brocade fitted from a synthetic capture (`fitting.synth_capture`
    -> `fitting.fit_capture` with its EM pyramid), the other weaves procedural truth; quick mode
    uses truth maps only (no fit)."""
    if quick:
        return default_btfs(size=8, pyramid="none"), "procedural truth BTFs, level 0 only (quick mode: no fit, no EM)"
    import tempfile

    from ..io import read_btf

    try:
        from fitting import fit_capture, synth_capture

        with tempfile.TemporaryDirectory() as tmp:
            cap = synth_capture(Path(tmp) / "capture", key=jax.random.key(3), size=(32, 32), lights=300, progress=False)
            btf = fit_capture(cap, Path(tmp) / "btf", pyramid=True, progress=False)
            _, levels = read_btf(btf)
        btfs = default_btfs(size=32)
        btfs["brocade"] = btf_levels_from_channels(levels)
        return btfs, ("gold brocade BTF fitted (LM + EM pyramid) from a synthetic 300-light capture; "
                      "hexagon, satin and plain weaves from procedural truth maps")
    except Exception as error:  # the gallery must render even if the fitting package fails
        return default_btfs(size=32), f"procedural truth BTFs (the fit failed: {type(error).__name__}: {error})"

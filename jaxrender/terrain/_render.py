"""Dunes with bump-mapped wind ripples, shaded in texture space per visible quad at its level of
detail (paper 001 sections 3.1-3.6), then ray-cast to the screen.

Pipeline of a frame:
1. `plan_quads`: back-face and frustum culling per dune quad, ripple level from projected area.
2. On the host, the number of quads at each level gives the fixed capacities of the per-level
   buffers (rounded up, so a camera path re-uses one compilation): shapes stay static, and only
   visible quads at their level are shaded -- culling and LOD really save work.
3. `shade_quads`: for every buffered quad, every texel of its level: the ripple normal (mip
   pyramid level, Fig. 6) tilted into the dune's local slope frame (Fig. 5), the sand-grain
   albedo, Lambert under the sun with the dune shadow (incremental ray march, section 3.4) and
   the ripple shadow (horizon map, section 3.5), plus sky ambient light.
4. Each pixel's camera ray is cast against the dune heightfield (`ray_cast_coherent`: a full
   march for every 4th pixel, a short bracketed one for the others); the hit's quad and position
   in the quad select the shaded texels (bilinear, within the quad's tile of its level's atlas).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ..camera import Camera
from ..lights import Sun
from ..maths import normalize
from ..shadows import heightfield_light, horizon_band, horizon_light, horizon_map, triangle_height
from ..textures import bilinear, downsample2
from ._detail import DetailMaps
from ._dune import close_periodic, ray_cast_coherent, vertex_normals
from ._grain import sand_grain_texture
from ._lod import quad_levels, quad_screen_area, quad_visibility
from ._normals import normal_pyramid, ripple_normal_map

__all__ = ["TerrainMaps", "build_terrain_maps", "plan_quads", "quad_capacities", "shade_quads", "render_terrain",
           "shadow_steps", "with_detail"]


class TerrainMaps(eqx.Module):
    """Everything precomputed per scene: dune vertices and normals, and per ripple level the
    normal map, grain albedo, horizon map and its per-texel slope band (level l has R / 2^l
    texels across); optionally a window of quads with its own micro relief (`detail`, the
    footprints: `with_detail`)."""

    z: Float[Array, "Ny Nx"]
    normals: Float[Array, "Ny Nx 3"]
    ripple_normals: tuple[Float[Array, "r r 3"], ...]
    grain: tuple[Float[Array, "r r 1"], ...]
    horizon: tuple[Float[Array, "r r D"], ...]
    horizon_band: tuple[Float[Array, "r r D"], ...]
    spacing: float = eqx.field(static=True)
    texels: int = eqx.field(static=True)
    detail: DetailMaps | None = None

    @property
    def levels(self) -> int:
        return len(self.ripple_normals)

    @property
    def quads(self) -> tuple[int, int]:
        return self.z.shape[0] - 1, self.z.shape[1] - 1


def build_terrain_maps(dune_z: Float[ArrayLike, "N M"], ripple_z: Float[ArrayLike, "R R"], *, key: Array,
                       spacing: float = 1.0, texels: int = 64, levels: int = 4, directions: int = 8,
                       grain_contrast: float = 0.35) -> TerrainMaps:
    """Precompute the maps from a periodic dune field and a periodic ripple field, both already
    in world units (heights). Ripple texels are `spacing / texels` wide: each dune quad shows a
    `texels` x `texels` window of the (tiled) ripple field at level 0. The grain texture is made
    from `key` at the ripple map's size."""
    dune_z = jnp.asarray(dune_z)
    ripple_z = jnp.asarray(ripple_z, dtype=dune_z.dtype)
    r = ripple_z.shape[0]
    if ripple_z.shape != (r, r) or r % 2 ** (levels - 1) or texels % 2 ** (levels - 1):
        raise ValueError(f"ripple map {ripple_z.shape} and texels {texels} must be square multiples of 2^(levels-1)")
    z = close_periodic(dune_z)
    texel = spacing / texels
    normals = normal_pyramid(ripple_normal_map(ripple_z, texel_size=texel), levels=levels)
    grain0 = sand_grain_texture(key, r, contrast=grain_contrast).astype(dune_z.dtype)[..., None]
    grain = [grain0]
    hor = [jnp.moveaxis(horizon_map(ripple_z, directions=directions, texel_size=texel), 0, -1)]
    for _ in range(levels - 1):
        grain.append(downsample2(grain[-1]))
        hor.append(downsample2(hor[-1]))
    band = tuple(jnp.moveaxis(horizon_band(jnp.moveaxis(h, -1, 0)), 0, -1) for h in hor)
    return TerrainMaps(z, vertex_normals(z, spacing=spacing), normals, tuple(grain), tuple(hor), band, spacing, texels)


def with_detail(maps: TerrainMaps, detail: DetailMaps | None) -> TerrainMaps:
    """The maps with the quads of `detail`'s window shaded from its relief (None: ripples only)."""
    if detail is not None:
        (qi0, qj0), (nx, ny) = detail.origin, detail.quads
        nqy, nqx = maps.quads
        if qi0 < 0 or qj0 < 0 or qi0 + nx > nqx or qj0 + ny > nqy or len(detail.normals) != maps.levels:
            raise ValueError(f"detail window {detail.quads} at quad {detail.origin} with {len(detail.normals)} levels "
                             f"does not fit {maps.quads} quads with {maps.levels} levels")
    return eqx.tree_at(lambda m: m.detail, maps, detail, is_leaf=lambda x: x is None)


def shadow_steps(maps: TerrainMaps, sun_elevation_deg: float) -> int:
    """Grid-line crossings per family a shadow ray needs to clear the highest vertex (static)."""
    z = np.asarray(maps.z)
    relief = float(z.max() - z.min())
    tan_el = math.tan(math.radians(max(sun_elevation_deg, 0.5)))
    return int(min(max(maps.quads), math.ceil(relief / (tan_el * maps.spacing)) + 2))


def plan_quads(maps: TerrainMaps, camera: Camera, *, lod: bool = True, culling: bool = True,
               lod_bias: float = 0.0) -> tuple[Array, Array]:
    """(visible, level) per quad, both (Ny-1, Nx-1). Without `lod` every quad is at level 0;
    without `culling` every quad is visible."""
    if culling:
        visible = quad_visibility(maps.z, camera, spacing=maps.spacing)
    else:
        visible = jnp.ones(maps.quads, bool)
    if lod:
        level = quad_levels(quad_screen_area(maps.z, camera, spacing=maps.spacing), texels=maps.texels,
                            levels=maps.levels, bias=lod_bias)
    else:
        level = jnp.zeros(maps.quads, jnp.int32)
    return visible, level


def quad_capacities(visible: ArrayLike, level: ArrayLike, levels: int, *, granule: int = 32) -> tuple[int, ...]:
    """Host side: buffer capacity per level = number of visible quads at that level, rounded up
    to a multiple of `granule` (0 stays 0)."""
    visible = np.asarray(visible)
    level = np.asarray(level)
    counts = [int(np.sum(visible & (level == l))) for l in range(levels)]
    return tuple(0 if c == 0 else granule * math.ceil(c / granule) for c in counts)


class _Flags(eqx.Module):
    ripples: bool = eqx.field(static=True)
    dune_shadows: bool = eqx.field(static=True)
    ripple_shadows: bool = eqx.field(static=True)
    shadow_steps: int = eqx.field(static=True)


def _shade_points(maps: TerrainMaps, xy: Array, ripple_n: Array, grain: Array, hor: Array, band: Array, sun: Sun,
                  albedo: Array, sky: Array, flags: _Flags, texel: float) -> Array:
    """Radiance of dune points at world `xy` (... x 2) given their ripple normal, grain,
    horizon slopes and slope bands (looked up at the point's level); `texel` is the shading
    texel's world size. Both shadow edges are antialiased over the shading texel."""
    dtype = xy.dtype
    ny, nx = maps.z.shape
    zd = triangle_height(maps.z, xy, spacing=maps.spacing)
    uv = jnp.stack([(xy[..., 0] / maps.spacing + 0.5) / nx, (xy[..., 1] / maps.spacing + 0.5) / ny], axis=-1)
    nd = normalize(bilinear(maps.normals, uv))
    light = sun.direction.astype(dtype)
    lb = jnp.broadcast_to(light, nd.shape)
    ex = jnp.broadcast_to(jnp.asarray([1.0, 0.0, 0.0], dtype), nd.shape)
    t = normalize(ex - nd * jnp.sum(ex * nd, -1, keepdims=True))
    b = jnp.cross(nd, t)
    if flags.ripples:
        n = normalize(ripple_n[..., 0:1] * t + ripple_n[..., 1:2] * b + ripple_n[..., 2:3] * nd)
        g = grain[..., 0]
    else:
        n, g = nd, jnp.ones(xy.shape[:-1], dtype)
    cos = jnp.maximum(jnp.sum(n * lb, -1), 0.0)
    lit = jnp.ones(xy.shape[:-1], dtype)
    if flags.dune_shadows:
        p = jnp.concatenate([xy, zd[..., None]], axis=-1)
        lit = heightfield_light(maps.z, p, light, spacing=maps.spacing, n_steps=flags.shadow_steps,
                                bias=1e-3 * maps.spacing, footprint=texel)
    if flags.ripple_shadows and flags.ripples:
        local = jnp.stack([jnp.sum(lb * t, -1), jnp.sum(lb * b, -1), jnp.sum(lb * nd, -1)], axis=-1)
        lit = lit * horizon_light(jnp.moveaxis(hor, -1, 0), jnp.moveaxis(band, -1, 0), local)
    rgb = (1,) * (xy.ndim - 1) + (3,)
    direct = (cos * lit)[..., None] * jnp.reshape(sun.irradiance.astype(dtype), rgb)
    ambient = (0.5 + 0.5 * n[..., 2])[..., None] * jnp.reshape(sky.astype(dtype), rgb)
    return (jnp.reshape(albedo.astype(dtype), rgb) * g[..., None] / jnp.pi) * (direct + ambient)


def _shade_level(maps: TerrainMaps, ids: Array, l: int, sun: Sun, albedo: Array, sky: Array, flags: _Flags,
                 batch: int) -> Array:
    """Shaded tiles (cap, n, n, 3) of the quads `ids` at level l."""
    n = maps.texels // 2**l
    r = maps.ripple_normals[l].shape[0]
    nqx = maps.quads[1]
    dtype = maps.z.dtype
    a, bb = jnp.meshgrid(jnp.arange(n, dtype=jnp.int32), jnp.arange(n, dtype=jnp.int32), indexing="ij")
    frac_y = (a.astype(dtype) + 0.5) / n
    frac_x = (bb.astype(dtype) + 0.5) / n

    def one(q):
        qj, qi = q // nqx, q % nqx
        xy = jnp.stack([(qi.astype(dtype) + frac_x) * maps.spacing, (qj.astype(dtype) + frac_y) * maps.spacing],
                       axis=-1)
        row = jnp.mod(qj * n + a, r)
        col = jnp.mod(qi * n + bb, r)
        normal, hor = maps.ripple_normals[l][row, col], maps.horizon[l][row, col]
        band = maps.horizon_band[l][row, col]
        if maps.detail is not None:  # a quad inside the detail window reads the window's own relief
            d = maps.detail
            di, dj = qi - d.origin[0], qj - d.origin[1]
            inside = (di >= 0) & (di < d.quads[0]) & (dj >= 0) & (dj < d.quads[1])
            drow = jnp.clip(dj, 0, d.quads[1] - 1) * n + a
            dcol = jnp.clip(di, 0, d.quads[0] - 1) * n + bb
            normal = jnp.where(inside, d.normals[l][drow, dcol], normal)
            hor = jnp.where(inside, d.horizon[l][drow, dcol], hor)
            band = jnp.where(inside, d.horizon_band[l][drow, dcol], band)
        return _shade_points(maps, xy, normal, maps.grain[l][row, col], hor, band, sun, albedo, sky, flags,
                             maps.spacing / n)

    return jax.lax.map(one, ids, batch_size=max(1, min(batch, ids.shape[0])))


def shade_quads(maps: TerrainMaps, visible: Array, level: Array, sun: Sun, albedo: Array, sky: Array, *,
                capacities: tuple[int, ...], ripples: bool = True, dune_shadows: bool = True,
                ripple_shadows: bool = True, shadow_steps: int = 16, texel_batch: int = 1 << 18
                ) -> tuple[tuple[Array | None, ...], Array]:
    """Texture-space shading of the visible quads: per level, tiles (capacity, n, n, 3), and the
    slot of every quad in its level's buffer (-1 where not buffered)."""
    flags = _Flags(ripples, dune_shadows, ripple_shadows, shadow_steps)
    vis = visible.ravel()
    lev = level.ravel()
    slot = jnp.full(vis.shape, -1, jnp.int32)
    tiles = []
    for l, cap in enumerate(capacities):
        if cap == 0:
            tiles.append(None)
            continue
        mask = vis & (lev == l)
        ids = jnp.nonzero(mask, size=cap, fill_value=0)[0].astype(jnp.int32)
        slot = jnp.where(mask, jnp.cumsum(mask.astype(jnp.int32)) - 1, slot)
        n = maps.texels // 2**l
        tiles.append(_shade_level(maps, ids, l, sun, albedo, sky, flags, max(1, texel_batch // (n * n))))
    return tuple(tiles), slot.reshape(visible.shape)


def _atlas(tiles: Array) -> tuple[Array, int]:
    cap, n = tiles.shape[0], tiles.shape[1]
    cols = int(math.ceil(math.sqrt(cap)))
    rows = int(math.ceil(cap / cols))
    pad = rows * cols - cap
    t = jnp.concatenate([tiles, jnp.zeros((pad,) + tiles.shape[1:], tiles.dtype)], axis=0) if pad else tiles
    t = t.reshape(rows, cols, n, n, 3).transpose(0, 2, 1, 3, 4).reshape(rows * n, cols * n, 3)
    return t, cols


def render_terrain(maps: TerrainMaps, camera: Camera, sun: Sun, *, albedo: Float[ArrayLike, "3"],
                   sky_irradiance: Float[ArrayLike, "3"], visible: Array, level: Array, capacities: tuple[int, ...],
                   ripples: bool = True, dune_shadows: bool = True, ripple_shadows: bool = True,
                   shadow_steps: int = 16, ray_steps: int = 96) -> tuple[Array, Array, Array]:
    """(radiance H x W x 3, distance H x W (inf where the ray misses), hit mask) of the dunes.

    `visible`, `level` from `plan_quads` and `capacities` from `quad_capacities` (static)."""
    dtype = maps.z.dtype
    albedo = jnp.asarray(albedo, dtype)
    sky = jnp.asarray(sky_irradiance, dtype)
    tiles, slot = shade_quads(maps, visible, level, sun, albedo, sky, capacities=capacities, ripples=ripples,
                              dune_shadows=dune_shadows, ripple_shadows=ripple_shadows, shadow_steps=shadow_steps)
    dirs = camera.primary_rays().astype(dtype)
    eye = camera.eye.astype(dtype)
    stride = max(1, min(4, camera.height // 100))  # 4 at 480 rows; small images need the full march
    t, hit = ray_cast_coherent(maps.z, eye, dirs, spacing=maps.spacing, n_steps=ray_steps, stride=stride)
    t_safe = jnp.where(hit, t, 0.0)
    p = jnp.reshape(eye, (1, 1, 3)) + dirs * t_safe[..., None]
    nqy, nqx = maps.quads
    gx = p[..., 0] / maps.spacing
    gy = p[..., 1] / maps.spacing
    qi = jnp.clip(jnp.floor(gx).astype(jnp.int32), 0, nqx - 1)
    qj = jnp.clip(jnp.floor(gy).astype(jnp.int32), 0, nqy - 1)
    fx = jnp.clip(gx - qi.astype(dtype), 0.0, 1.0)
    fy = jnp.clip(gy - qj.astype(dtype), 0.0, 1.0)
    q_level = level[qj, qi]
    q_slot = slot[qj, qi]
    color = jnp.zeros(p.shape, dtype)
    for l, tl in enumerate(tiles):
        if tl is None:
            continue
        atlas, cols = _atlas(tl)
        n = tl.shape[1]
        rows = atlas.shape[0] // n
        s = jnp.maximum(q_slot, 0)
        u = (s % cols).astype(dtype) + jnp.clip(fx, 0.5 / n, 1 - 0.5 / n)
        v = (s // cols).astype(dtype) + jnp.clip(fy, 0.5 / n, 1 - 0.5 / n)
        c = bilinear(atlas, jnp.stack([u / cols, v / rows], axis=-1))
        color = jnp.where((q_level == l)[..., None], c, color)
    # a first hit from above cannot land on a culled quad; should rounding put one there, the
    # pixel gets the sky-lit sand colour rather than a hole
    fallback = jnp.reshape(albedo * sky / jnp.pi, (1, 1, 3))
    color = jnp.where((q_slot >= 0)[..., None], color, fallback)
    color = jnp.where(hit[..., None], color, 0.0)
    return color, t, hit

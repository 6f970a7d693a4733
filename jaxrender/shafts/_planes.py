"""The sample-plane method of paper 000 (eqs. 5-9), emulating the graphics-hardware pipeline.

Per spot light:
- n sample planes parallel to the screen, equally spaced (midpoints of n intervals of width dr)
  between the nearest and farthest view depths the lit volume reaches (the cone cut at the
  light's reach, see `light_reach` / `cone_depth_range`). On a pixel whose ray makes the angle psi
  with the view axis, plane depth r lies at distance t = r / cos(psi) and dt = dr / cos(psi).
- m sub-sample planes per interval [r_i - dr/2, r_i + dr/2] (midpoints) average H * I_l into
  J_i (eqs. 8-9): H from the light's shadow map (nearest texel + bias), I_l from the spot light
  (falloff and projected light map); samples behind the visible surface contribute nothing.
- g = F(alpha) h(s, t) (eq. 6) from a 1-D table of F over alpha in [0, pi] and a 2-D table of h
  over s in [s_min, s_max], t in [0, t_max] (`render.table_size` entries each, linear
  interpolation, clamped at the ends like a texture), with alpha and (s, t) computed at the
  vertices of a coarse mesh on each plane (`mesh` = cells across x down) and interpolated
  bilinearly to the pixels, as texture coordinates are. `g_per_pixel=True` computes alpha, s, t
  per pixel; `tables=False` evaluates F and h in closed form (both only in float mode).
- I_s = sum_i J_i g_i dt (eq. 7), added plane by plane to the frame buffer.

8-bit emulation (`quantize_bits` = B > 0; design.md): the F and h tables are scaled by their
maxima and rounded to 2^B - 1 levels, the light maps likewise (by their maximum), J (rendered
into a B-bit buffer) too, and the frame buffer accumulates in steps of display_white / (2^B - 1),
saturating at display_white. Shadow-map depths are not quantized. Rounding has a straight-through
gradient (`jaxrender.textures.quantize`).

Gradients: with tables, values come from the tables and the derivative w.r.t. rho, kappa and K
from the closed-form F and h at the looked-up coordinates (they differ by the tables'
interpolation error); without tables (`tables=False`) the gradient is exactly that of the image.

Fog with a density grid: g becomes F(alpha) h(s, t) D with the density factor
D = d(P) exp(rho kappa ((s + t) - (tau_l + tau_v))) evaluated per pixel at every plane (a 3-D
texture lookup the 2001 hardware lacked; float also in B-bit mode): d from the grid, the optical
depths tau_l toward the light and tau_v toward the eye from the volumes of `fog_volumes`. So the
paper's tables stay as they are and D = 1 to rounding for a grid of ones.

Pruning: the image is cut into tiles; a tile is processed (`lax.cond` inside `lax.map`) only when
some pixel's ray passes through the light's cone in front of the visible surface (the per-pixel
ray/cone interval), so pixels outside every cone's screen footprint cost (almost) nothing, and the
planes only span each cone's own depth range. Static shapes throughout; jittable and
differentiable end to end.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name
from jaxtyping import Array, Bool, Float, Int

from ..geometry import cast_rays, hit_point
from ..lights import SpotLight
from ..maths import atan_nonneg, outer, safe_norm, sum_short
from ..shadows import ShadowMap
from ..textures import bilinear, quantize
from ._fog import RayFog, fog_volumes
from ._model import (
    FAR,
    S_FLOOR,
    attenuation_h,
    cone_depth_range,
    cone_intervals,
    light_reach,
    phase_cos,
    surface_term,
)
from ._raymarch import surface_visibility
from ._scene import RenderSettings, ShaftsScene, shadow_maps

__all__ = ["render_planes"]


def _interp_weights(n_pixels: int, cells: int) -> np.ndarray:
    """(n_pixels, cells + 1) linear-interpolation weights from mesh vertices to pixel centres."""
    x = (np.arange(n_pixels) + 0.5) / n_pixels * cells
    i0 = np.clip(np.floor(x).astype(int), 0, cells - 1)
    f = x - i0
    w = np.zeros((n_pixels, cells + 1))
    w[np.arange(n_pixels), i0] = 1.0 - f
    w[np.arange(n_pixels), i0 + 1] = f
    return w


def _dot(a: Array, b: Array) -> Array:
    """a . b over the last axis, b one 3-vector (XLA's CPU matmul is slow for K = 3)."""
    return a[..., 0] * b[0] + a[..., 1] * b[1] + a[..., 2] * b[2]


def _scatter_geometry(points: Array, dirs: Array, light_pos: Array) -> tuple[Array, Array]:
    """(alpha, s) at points seen along unit view `dirs`: alpha between the light's propagation
    direction and the direction toward the eye (-dirs), gradient-safe (atan2, safe norms)."""
    rel = points - jnp.broadcast_to(light_pos, points.shape)
    s = safe_norm(rel)
    w = rel / jnp.maximum(s, S_FLOOR)[..., None]
    to_eye = -dirs
    cos_a = jnp.sum(w * to_eye, axis=-1)
    sin_a = safe_norm(jnp.cross(w, to_eye))
    return jnp.arctan2(sin_a, cos_a), s


class PhaseTables(eqx.Module):
    """g = F(alpha) h(s, t) (eq. 6) as the hardware's textures hold it: a 1-D table of F over alpha
    in [0, pi] and a 2-D table of h over s in [s_min, s_max] (columns), t in [0, t_max] (rows),
    quantized in B-bit mode; or in closed form (`tables=False`)."""

    F: Float[Array, " N"]
    h: Float[Array, "N N"]
    s_min: Float[Array, ""]
    s_max: Float[Array, ""]
    t_max: Float[Array, ""]
    rho: Float[Array, ""]
    kappa: Float[Array, ""]
    K: Float[Array, ""]
    tables: bool = eqx.field(static=True)

    def g(self, alpha: Array, s: Array, t: Array) -> Array:
        if not self.tables:
            return phase_cos(jnp.cos(alpha), self.K) * attenuation_h(s, t, self.rho, self.kappa)
        n = self.F.shape[0]
        ua = (jnp.clip(alpha / jnp.pi, 0.0, 1.0) * (n - 1) + 0.5) / n
        F = bilinear(self.F[None, :, None], jnp.stack([ua, jnp.full_like(ua, 0.5)], axis=-1))[..., 0]
        us = ((s - self.s_min) / (self.s_max - self.s_min) * (n - 1) + 0.5) / n
        vt = (t / self.t_max * (n - 1) + 0.5) / n
        h = bilinear(self.h[..., None], jnp.stack([us, vt], axis=-1))[..., 0]
        # Values come from the (constant) tables; the derivative w.r.t. rho, kappa, K is the closed
        # form's at the looked-up (clamped) coordinates. Differentiating through the table entries
        # instead would scatter a full table cotangent per tile and chunk (a 17x slower gradient);
        # the two differ only by the tables' interpolation error.
        a_c, s_c, t_c = (jax.lax.stop_gradient(x)
                         for x in (alpha, jnp.clip(s, self.s_min, self.s_max), jnp.clip(t, 0.0, self.t_max)))
        exact = phase_cos(jnp.cos(a_c), self.K) * attenuation_h(s_c, t_c, self.rho, self.kappa)
        return F * h + (exact - jax.lax.stop_gradient(exact))


def phase_tables(scene: ShaftsScene, quantize_bits: int, dtype, *, tables: bool) -> PhaseTables:
    settings: RenderSettings = scene.render
    rho, kappa, K = scene.medium.rho, scene.medium.kappa, scene.medium.K
    n = settings.table_size
    s_min = jnp.asarray(settings.s_min, dtype=dtype)
    s_max = jnp.asarray(settings.s_max, dtype=dtype)
    t_max = jnp.asarray(settings.t_max, dtype=dtype)
    nodes = jnp.arange(n, dtype=dtype) / (n - 1)
    F_tab = phase_cos(jnp.cos(nodes * jnp.pi), K)
    h_tab = attenuation_h((s_min + nodes * (s_max - s_min))[None, :], (nodes * t_max)[:, None], rho, kappa)
    if quantize_bits:
        F_max, h_max = jnp.max(F_tab), jnp.max(h_tab)
        F_tab = quantize(F_tab / F_max, quantize_bits) * F_max
        h_tab = quantize(h_tab / h_max, quantize_bits) * h_max
    return PhaseTables(jax.lax.stop_gradient(F_tab), jax.lax.stop_gradient(h_tab), s_min, s_max, t_max,
                       jnp.asarray(rho), jnp.asarray(kappa), jnp.asarray(K), tables)


class Tiling(eqx.Module):
    """The image cut into tiles of `rows x cols` pixels (padded at the bottom and right)."""

    height: int = eqx.field(static=True)
    width: int = eqx.field(static=True)
    rows: int = eqx.field(static=True)
    cols: int = eqx.field(static=True)

    @property
    def shape(self) -> tuple[int, int]:
        """Tiles down and across."""
        return -(-self.height // self.rows), -(-self.width // self.cols)

    @property
    def padded(self) -> tuple[int, int]:
        n_ty, n_tx = self.shape
        return n_ty * self.rows, n_tx * self.cols

    def pad(self, x: Array, value: float | None) -> Array:
        hp, wp = self.padded
        widths = ((0, hp - self.height), (0, wp - self.width)) + ((0, 0),) * (x.ndim - 2)
        return jnp.pad(x, widths, mode="edge") if value is None else jnp.pad(x, widths, constant_values=value)

    def untile(self, x: Array) -> Array:
        """(n_tiles, rows, cols, C) -> (H, W, C)."""
        n_ty, n_tx = self.shape
        x = x.reshape((n_ty, n_tx, self.rows, self.cols) + x.shape[3:])
        x = jnp.moveaxis(x, 1, 2).reshape(self.padded + x.shape[4:])
        return x[:self.height, :self.width]

    def origins(self) -> tuple[Int[Array, " T"], Int[Array, " T"]]:
        """Top-left pixel (row, column) of every tile, row-major."""
        n_ty, n_tx = self.shape
        return jnp.repeat(jnp.arange(n_ty), n_tx) * self.rows, jnp.tile(jnp.arange(n_tx), n_ty) * self.cols


class ViewRays(eqx.Module):
    """Everything per pixel that does not depend on the light (padded to whole tiles)."""

    eye: Float[Array, " 3"]
    forward: Float[Array, " 3"]
    dirs: Float[Array, "Hp Wp 3"]
    mesh_rows: Float[Array, "Hp my1"]     # interpolation weights from the mesh's vertices to pixels
    mesh_cols: Float[Array, "Wp mx1"]
    vertex_dirs: Float[Array, "my1 mx1 3"]
    vertex_cos: Float[Array, "my1 mx1"]


class LightPlanes(eqx.Module):
    """One spot light's sample planes and what the sub-plane samples need of the light."""

    position: Float[Array, " 3"]
    frame: Float[Array, "3 3"]            # the light's x, y, z axes (rows)
    local_eye: Float[Array, " 3"]         # the eye in the light's frame
    r: Float[Array, " n"]                 # plane depths (padded to whole chunks; `on` marks real ones)
    on: Bool[Array, " n"]
    r_near: Float[Array, ""]
    dr: Float[Array, ""]
    depths: Float[Array, "n m"]           # sub-plane depths
    grids: Float[Array, "3 n my1 mx1"] | None   # (alpha, s, t) at the mesh vertices of every plane
    tan_cutoff: Float[Array, ""]
    cutoff: Float[Array, ""]
    beam: Float[Array, ""]
    inv_ramp: Float[Array, ""]
    light_map: Float[Array, "h w 3"]      # divided by its maximum
    scale_rgb: Float[Array, " 3"]         # intensity x the map's maximum
    depth: Float[Array, " R2"]            # the shadow map's depths, flattened
    shadow_bias: Float[Array, ""]
    resolution: int = eqx.field(static=True)
    uniform_map: bool = eqx.field(static=True)
    fog: RayFog | None = None             # a density grid's lookups (None: uniform fog)
    sub_count: Int[Array, ""] | None = None  # sub-planes in use when counts are traced (None: cfg.subplanes)


class TileRays(eqx.Module):
    """One tile's rays: directions (world and light frame), cos(psi), the visible surface's
    distance and the view-depth interval inside the cone."""

    dirs: Float[Array, "ty tx 3"]
    light_dirs: Float[Array, "ty tx 3"]
    cos_psi: Float[Array, "ty tx"]
    surface_t: Float[Array, "ty tx"]
    cone_near: Float[Array, "ty tx"]
    cone_far: Float[Array, "ty tx"]
    row0: Int[Array, ""]
    col0: Int[Array, ""]


class PlaneConfig(eqx.Module):
    """What stays fixed over a render: method settings and the tables."""

    tables: PhaseTables
    white: Float[Array, ""]
    tiling: Tiling
    subplanes: int = eqx.field(static=True)
    chunk: int = eqx.field(static=True)       # planes evaluated together
    n_chunks: int = eqx.field(static=True)
    quantize_bits: int = eqx.field(static=True)
    g_per_pixel: bool = eqx.field(static=True)


def light_planes(scene: ShaftsScene, view: ViewRays, light: SpotLight, sm: ShadowMap, cfg: PlaneConfig, *,
                 planes: int, fog: RayFog | None = None, counts=None) -> LightPlanes:
    """Planes spanning the view depths the light's cone reaches, and the light's parameters.
    `counts`: traced (planes, sub-planes) in use, at most `planes` and cfg.subplanes (the slots)."""
    dtype = view.dirs.dtype
    reach = light_reach(scene, light)
    r_near, r_far = cone_depth_range(light, reach, view.eye, view.forward)
    n_used, m_used = (planes, cfg.subplanes) if counts is None else counts
    dr = (r_far - r_near) / n_used
    plane_ids = jnp.arange(cfg.n_chunks * cfg.chunk)
    r = r_near + (plane_ids.astype(dtype) + 0.5) * dr  # planes past `planes` are masked
    sub = ((jnp.arange(cfg.subplanes, dtype=dtype) + 0.5) / m_used - 0.5)
    depths = r[:, None] + sub[None, :] * dr
    lx, ly, lz = light.frame()
    rel_eye = view.eye - light.position
    cut = light.cutoff
    beam = jnp.minimum(light.beam_width, cut)
    ramp_w = cut - beam
    lmap = light.quantized_map(cfg.quantize_bits)
    map_max = jnp.max(lmap)
    if cfg.g_per_pixel:
        grids = None
    else:
        t_vert = r[:, None, None] / view.vertex_cos[None, :, :]  # (n, my+1, mx+1)
        p_vert = view.eye[None, None, None, :] + t_vert[..., None] * view.vertex_dirs[None, :, :, :]
        a_vert, s_vert = _scatter_geometry(p_vert, jnp.broadcast_to(view.vertex_dirs, p_vert.shape), light.position)
        grids = jnp.stack([a_vert, s_vert, t_vert], axis=0)
    return LightPlanes(
        position=light.position, frame=jnp.stack([lx, ly, lz]),
        local_eye=jnp.stack([_dot(rel_eye, lx), _dot(rel_eye, ly), _dot(rel_eye, lz)]),
        r=r, on=plane_ids < n_used, r_near=r_near, dr=dr, depths=depths, grids=grids,
        tan_cutoff=jnp.tan(cut), cutoff=cut, beam=beam,
        inv_ramp=jnp.where(ramp_w > 1e-9, 1.0 / jnp.where(ramp_w > 1e-9, ramp_w, 1.0), 0.0),
        light_map=lmap / map_max, scale_rgb=light.intensity * map_max,
        depth=jax.lax.stop_gradient(sm.depth).reshape((-1,)), shadow_bias=scene.render.shadow_bias,
        resolution=sm.resolution, uniform_map=lmap.shape[0] * lmap.shape[1] == 1, fog=fog,
        sub_count=None if counts is None else jnp.asarray(m_used))


def tile_rays(view: ViewRays, lp: LightPlanes, per_pixel: Array, cfg: PlaneConfig, row0, col0) -> TileRays:
    """Slice one tile out of the padded per-pixel arrays (in place, no copy into tile order)."""
    ty, tx = cfg.tiling.rows, cfg.tiling.cols
    d = jax.lax.dynamic_slice(view.dirs, (row0, col0, 0), (ty, tx, 3))
    p = jax.lax.dynamic_slice(per_pixel, (row0, col0, 0), (ty, tx, 3))
    ld = jnp.stack([_dot(d, lp.frame[0]), _dot(d, lp.frame[1]), _dot(d, lp.frame[2])], axis=-1)
    return TileRays(d, ld, _dot(d, view.forward), p[..., 0], p[..., 1], p[..., 2], row0, col0)


def _plane_g(view: ViewRays, lp: LightPlanes, cfg: PlaneConfig, rays: TileRays, c, r_c: Array,
             tau_unit: Array) -> Array:
    """g of the chunk's planes at the tile's pixels (pc, ty, tx): exact per pixel, or interpolated
    from the mesh's vertices as the hardware interpolates texture coordinates."""
    if lp.grids is None:
        t_pl = r_c[:, None, None] * tau_unit[None]
        p_pl = view.eye[None, None, None, :] + t_pl[..., None] * rays.dirs[None]
        a_pl, s_pl = _scatter_geometry(p_pl, jnp.broadcast_to(rays.dirs, p_pl.shape), lp.position)
    else:
        wy = jax.lax.dynamic_slice_in_dim(view.mesh_rows, rays.row0, cfg.tiling.rows, axis=0)
        wx = jax.lax.dynamic_slice_in_dim(view.mesh_cols, rays.col0, cfg.tiling.cols, axis=0)
        grid_c = jax.lax.dynamic_slice_in_dim(lp.grids, c * cfg.chunk, cfg.chunk, axis=1)
        interp = jnp.einsum("ya,knab,xb->knyx", wy, grid_c, wx)
        a_pl, s_pl, t_pl = interp[0], interp[1], interp[2]
    return cfg.tables.g(a_pl, s_pl, t_pl)


def _density_factor(view: ViewRays, lp: LightPlanes, rays: TileRays, t_pl: Array, sigma) -> Array:
    """D = d(P) exp(sigma ((s + t) - (tau_l + tau_v))) at the planes' points P = eye + t_pl dirs
    (pc, ty, tx): the grid's correction of the uniform fog's g (module docstring)."""
    fog = lp.fog
    ld = rays.light_dirs
    x, y, z = (lp.local_eye[i] + t_pl * ld[None, :, :, i] for i in range(3))
    s = jnp.sqrt(jnp.maximum(x * x + y * y + z * z, S_FLOOR * S_FLOOR))
    front = z > 1e-9
    inv = 1.0 / (jnp.where(front, z, 1.0) * lp.tan_cutoff)
    tau_l = fog.light.lookup(jnp.where(front, x * inv, 0.0), jnp.where(front, y * inv, 0.0), s)
    p = [view.eye[i] + t_pl * rays.dirs[None, :, :, i] for i in range(3)]
    tau_v = fog.view.lookup_points(jnp.stack(p, axis=-1))
    exponent = jnp.minimum(sigma * ((s + t_pl) - (tau_l + tau_v)), 60.0)  # h carries exp(-sigma (s + t))
    return fog.grid.at_xyz(*p) * jnp.exp(exponent)


def chunk_scattering(view: ViewRays, lp: LightPlanes, cfg: PlaneConfig, rays: TileRays, c) -> Float[Array, "ty tx 3"]:
    """In-scattered light of planes [c*pc, (c+1)*pc) on one tile (eqs. 7-9)."""
    pc, B = cfg.chunk, cfg.quantize_bits
    tau_unit = 1.0 / rays.cos_psi  # distance along the ray per unit depth
    r_c = jax.lax.dynamic_slice_in_dim(lp.r, c * pc, pc)
    on_c = jax.lax.dynamic_slice_in_dim(lp.on, c * pc, pc)
    depths_c = jax.lax.dynamic_slice_in_dim(lp.depths, c * pc, pc, axis=0)
    g = _plane_g(view, lp, cfg, rays, c, r_c, tau_unit)  # (pc, ty, tx)
    if lp.fog is not None:
        g = g * _density_factor(view, lp, rays, r_c[:, None, None] * tau_unit[None], cfg.tables.rho * cfg.tables.kappa)
    # sub-sample planes: H * I_l averaged into J (component arithmetic, fused by XLA)
    ld = rays.light_dirs
    tau = depths_c[:, :, None, None] * tau_unit[None, None]  # (pc, m, ty, tx)
    x = lp.local_eye[0] + tau * ld[None, None, :, :, 0]
    y = lp.local_eye[1] + tau * ld[None, None, :, :, 1]
    z = lp.local_eye[2] + tau * ld[None, None, :, :, 2]
    rxy2 = x * x + y * y
    s = jnp.sqrt(jnp.maximum(rxy2 + z * z, S_FLOOR * S_FLOOR))
    front = z > 1e-9
    safe_z = jnp.where(front, z, 1.0)
    rxy_ok = rxy2 > 1e-30
    rxy = jnp.where(rxy_ok, jnp.sqrt(jnp.where(rxy_ok, rxy2, 1.0)), 0.0)
    theta = atan_nonneg(rxy / safe_z)
    fall = jnp.where(theta <= lp.beam, 1.0, (lp.cutoff - theta) * lp.inv_ramp)
    inv = 0.5 / (safe_z * lp.tan_cutoff)
    u = 0.5 + x * inv
    v = 0.5 + y * inv
    res = lp.resolution
    col = jnp.clip(jnp.floor(u * res).astype(jnp.int32), 0, res - 1)
    row = jnp.clip(jnp.floor(v * res).astype(jnp.int32), 0, res - 1)
    occ = lp.depth[row * res + col]
    ok = (front & (theta < lp.cutoff) & (s <= occ + lp.shadow_bias) & (tau < rays.surface_t[None, None])
          & on_c[:, None, None, None])
    if lp.sub_count is not None:  # traced counts: the sub-plane slots in use
        ok = ok & (jnp.arange(cfg.subplanes) < lp.sub_count)[None, :, None, None]
    ok = checkpoint_name(ok, "shaft_visible")  # saved for reverse mode (see `light_scattering`)
    weight = jnp.where(ok, fall, 0.0)
    dt = lp.dr * tau_unit  # (ty, tx)
    if lp.sub_count is not None:
        weight = weight * (cfg.subplanes / lp.sub_count)  # the means below divide by the slots
    if lp.uniform_map and not B:
        # one colour for the whole cone: sum the planes in one channel, colour at the end
        return outer(sum_short(sum_short(weight, 1) * g, 0) * (dt / cfg.subplanes), lp.scale_rgb)
    if lp.uniform_map:
        J = jnp.broadcast_to(jnp.mean(weight, axis=1)[..., None], weight.shape[:1] + weight.shape[2:] + (3,))
    else:
        J = jnp.mean(bilinear(lp.light_map, jnp.stack([u, v], axis=-1)) * weight[..., None], axis=1)  # (pc, ty, tx, 3)
    if B:
        J = quantize(J, B)
    contrib = J * (g * dt[None])[..., None] * lp.scale_rgb[None, None, None, :]
    if B:
        contrib = quantize(contrib, B, scale=cfg.white)
    return jnp.sum(contrib, axis=0)


def _chunk_step(view: ViewRays, lp: LightPlanes, cfg: PlaneConfig, rays: TileRays, depth_lo, depth_hi, acc, c):
    """Add chunk c to the tile's sum when its planes meet the tile's depth range inside the cone."""
    dtype = view.dirs.dtype
    lo = lp.r_near + (c * cfg.chunk).astype(dtype) * lp.dr
    hi = lo + cfg.chunk * lp.dr
    zeros = jnp.zeros_like(acc)
    part = jax.lax.cond((hi >= depth_lo) & (lo <= depth_hi),
                        lambda cc: chunk_scattering(view, lp, cfg, rays, cc), lambda cc: zeros, c)
    return acc + part, None


def tile_scattering(view: ViewRays, lp: LightPlanes, cfg: PlaneConfig, rays: TileRays) -> Float[Array, "ty tx 3"]:
    """The tile's in-scattered light: the chunks of planes that meet its rays inside the cone."""
    active = rays.cone_far > rays.cone_near
    depth_lo = jnp.min(jnp.where(active, rays.cone_near, jnp.inf))
    depth_hi = jnp.max(jnp.where(active, rays.cone_far, -jnp.inf))
    body = functools.partial(_chunk_step, view, lp, cfg, rays, depth_lo, depth_hi)
    body = jax.checkpoint(body, policy=jax.checkpoint_policies.save_only_these_names("shaft_visible"))
    zeros = jnp.zeros((cfg.tiling.rows, cfg.tiling.cols, 3), dtype=view.dirs.dtype)
    acc, _ = jax.lax.scan(body, zeros, jnp.arange(cfg.n_chunks))
    return acc


def _maybe_tile(view: ViewRays, lp: LightPlanes, cfg: PlaneConfig, per_pixel: Array, origin) -> Array:
    rays = tile_rays(view, lp, per_pixel, cfg, *origin)
    zeros = jnp.zeros((cfg.tiling.rows, cfg.tiling.cols, 3), dtype=view.dirs.dtype)
    return jax.lax.cond(jnp.any(rays.cone_far > rays.cone_near),
                        lambda r: tile_scattering(view, lp, cfg, r), lambda r: zeros, rays)


def light_scattering(scene: ShaftsScene, view: ViewRays, lp: LightPlanes, light: SpotLight, cfg: PlaneConfig,
                     surface_t: Array, *, prune: bool) -> Float[Array, "H W 3"]:
    """The in-scattered light of one spot (eq. 7) over the image."""
    if prune:
        t0, t1 = cone_intervals(scene, light, view.dirs[:cfg.tiling.height, :cfg.tiling.width], surface_t,
                                light_reach(scene, light))
    else:  # every pixel, every plane
        t0, t1 = jnp.zeros_like(surface_t), jnp.full_like(surface_t, FAR)
    cos_psi = _dot(view.dirs[:cfg.tiling.height, :cfg.tiling.width], view.forward)
    # per pixel: visible-surface distance and the view-depth interval inside the cone
    per_pixel = jax.lax.stop_gradient(cfg.tiling.pad(jnp.stack([surface_t, t0 * cos_psi, t1 * cos_psi], axis=-1), 0.0))
    if not prune:
        return cfg.tiling.untile(chunk_scattering(view, lp, cfg, tile_rays(view, lp, per_pixel, cfg, 0, 0), 0)[None])
    # Reverse mode (17x -> 4.3x the forward time on the 720x480 benchmark scene; 3.55x with the
    # custom JVP of `atan_nonneg`): each tile is rematerialized in the backward pass (the
    # checkpoint around the whole `_maybe_tile`, cond included: around `tile_scattering` alone,
    # the tile's closed-over inputs, the shadow map among them, came out of the cond as residuals
    # and were stacked per tile), and inside it each chunk of planes (`_chunk_step`), saving only
    # the visibility mask (1 byte per sample): otherwise ~30 per-chunk residuals are stacked over
    # the chunks, or the chunk's recomputation needs the whole shadow map, which `lax.cond`'s
    # partial evaluation copies out of every active tile and zero-fills for every skipped one.
    maybe_tile = jax.checkpoint(functools.partial(_maybe_tile, view, lp, cfg, per_pixel),
                                policy=jax.checkpoint_policies.nothing_saveable)
    return cfg.tiling.untile(jax.lax.map(maybe_tile, cfg.tiling.origins()))


def view_rays(scene: ShaftsScene, tiling: Tiling, mesh: tuple[int, int]) -> ViewRays:
    cam = scene.camera
    _, _, forward = cam.frame()
    dirs = cam.primary_rays()
    dtype = dirs.dtype
    hp, wp = tiling.padded
    mx, my = mesh
    vert_xy = jnp.stack(jnp.meshgrid(jnp.arange(mx + 1, dtype=dtype) * (cam.width / mx),
                                     jnp.arange(my + 1, dtype=dtype) * (cam.height / my), indexing="xy"), axis=-1)
    vert_dirs = cam.ray_direction(vert_xy)  # (my+1, mx+1, 3)
    return ViewRays(
        eye=cam.eye, forward=forward, dirs=tiling.pad(dirs, None),
        mesh_rows=jnp.asarray(np.pad(_interp_weights(cam.height, my), ((0, hp - cam.height), (0, 0)), mode="edge"),
                              dtype=dtype),
        mesh_cols=jnp.asarray(np.pad(_interp_weights(cam.width, mx), ((0, wp - cam.width), (0, 0)), mode="edge"),
                              dtype=dtype),
        vertex_dirs=vert_dirs, vertex_cos=_dot(vert_dirs, forward))


def render_planes(scene: ShaftsScene, *, planes: int = 30, subplanes: int = 6, quantize_bits: int = 0,
                  mesh: tuple[int, int] = (15, 10), g_per_pixel: bool = False, tables: bool = True,
                  tile: tuple[int, int] = (16, 32), plane_chunk: int = 6, prune: bool = True,
                  surface_shadows: str = "map", fog_nodes: int | tuple[int, int] | None = None,
                  return_parts: bool = False,
                  maps: tuple[ShadowMap, ...] | None = None, counts=None) -> Float[Array, "H W 3"]:
    """Render `scene` (H, W, 3 linear RGB) with the sample-plane method (see module docstring).

    planes, subplanes: n and m of the paper (default 30 x 6). quantize_bits: 0 = float, 8 = the
    paper's hardware. mesh: (cells across, cells down) of the texture-coordinate mesh (default 15 x 10).
    g_per_pixel / tables: skip the mesh interpolation / the tables (float mode only).
    tile: (rows, cols) of the pruning tiles; plane_chunk: planes evaluated together (a chunk is
    skipped on a tile when it misses the depth range of the tile's rays inside the cone).
    prune: skip tiles and chunks outside the cone (the result is the same either way); False
    evaluates every pixel and plane in one vectorized pass: a much smaller graph (faster
    compilation, e.g. for small images and gradients) at the cost of the pruned work.
    surface_shadows: "map" (shadow maps with a slope-scaled bias, as the hardware does) or "rays"
    (exact shadow rays, as the ray march). fog_nodes: (directions across, distances) of a density
    grid's optical-depth volumes, or one number for both (default `volume_nodes`). return_parts:
    also return (surface, per-light in-scattering list).
    maps: the lights' shadow maps when several renders share them (default: rendered here at the
    scene's `render.shadow_map`). counts: traced (planes, sub-planes) in use, at most `planes` and
    `subplanes`, which then only size the slots (one compiled function for many counts, as
    `choose_counts` needs).
    """
    if quantize_bits and (not tables or g_per_pixel):
        raise ValueError("quantize_bits > 0 emulates the hardware: it needs tables=True and g_per_pixel=False")
    B = int(quantize_bits)
    cam = scene.camera
    maps = shadow_maps(scene, scene.render.shadow_map) if maps is None else maps
    visibility = surface_visibility(scene, maps, surface_shadows)
    dirs = cam.primary_rays()
    dtype = dirs.dtype
    t_hit, normals, albedo = cast_rays(cam.eye, dirs, scene.prims)
    points = hit_point(cam.eye, dirs, t_hit, far=FAR)
    surface_t = jnp.where(jnp.isfinite(t_hit), t_hit, FAR)
    white = jnp.asarray(scene.render.display_white, dtype=dtype)
    fog = fog_volumes(scene, nodes=fog_nodes)
    if fog is None:
        surface = surface_term(scene, points, normals, albedo, t_hit, visibility, quantize_bits=B)
    else:
        surface = surface_term(scene, points, normals, albedo, t_hit, visibility, quantize_bits=B,
                               light_depth=fog.light_depth,
                               view_depth=fog.view_depth(scene, dirs, jnp.where(jnp.isfinite(t_hit), t_hit, 0.0)))
    frame = quantize(surface, B, scale=white) if B else surface

    ty, tx = tile if prune else (cam.height, cam.width)  # without pruning: one tile, all planes at once
    tiling = Tiling(cam.height, cam.width, ty, tx)
    chunk = max(1, min(plane_chunk, planes)) if prune else planes
    cfg = PlaneConfig(phase_tables(scene, B, dtype, tables=tables), white, tiling, subplanes, chunk,
                      -(-planes // chunk), B, g_per_pixel)
    view = view_rays(scene, tiling, mesh)
    per_light = [light_scattering(scene, view, light_planes(scene, view, light, sm, cfg, planes=planes,
                                                            fog=None if fog is None else fog.for_light(index),
                                                            counts=counts),
                                  light, cfg, surface_t, prune=prune)
                 for index, (light, sm) in enumerate(zip(scene.lights, maps))]
    image = frame + sum(per_light)
    if B:
        image = jnp.minimum(image, white)
    if return_parts:
        return image, (surface, per_light)
    return image

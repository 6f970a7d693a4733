"""The scattering model of paper 000 (eqs. 1-4) and the geometry both evaluations share.

    I_v = I_o exp(-rho kappa T) + I_s                                   (1)
    I_s = int_0^T H(t) I_l(t) g(alpha, s, t) dt                          (2)
    g   = rho F(alpha) exp(-rho kappa (s + t)) / s^2  = F(alpha) h(s, t)  (3), (6)
    F   = K (1 + 9 cos^16(alpha / 2))                                    (4)

alpha is the scattering angle: 0 when the light's propagation direction at P points straight at
the eye. Surfaces are two-sided Lambertian lit by every spot light with shadows and extinction
along the light path. All functions are gradient-safe (guarded divisions and square roots).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from ..geometry import bounding_points, nearest_distance
from ..lights import SpotLight
from ..maths import dot, safe_norm
from ..shadows import ShadowMap, shadow_test
from ._density import box_interval
from ._scene import ShaftsScene

S_FLOOR = 1e-6  # smallest light distance used in 1/s^2 (a sample exactly at the light)
FAR = 1e6  # stand-in for "no surface" distances (finite so gradients stay finite)


def phase_cos(cos_a: Float[ArrayLike, "..."], K: Float[ArrayLike, ""]) -> Float[Array, "..."]:
    """F from cos(alpha): K (1 + 9 ((1 + cos a) / 2)^8)  (cos^2(a/2) = (1 + cos a) / 2)."""
    c2 = 0.5 * (1.0 + jnp.asarray(cos_a))
    c4 = c2 * c2
    c8 = c4 * c4
    return K * (1.0 + 9.0 * c8 * c8)


def phase(alpha: Float[ArrayLike, "..."], K: Float[ArrayLike, ""]) -> Float[Array, "..."]:
    """F(alpha) = K (1 + 9 cos^16(alpha / 2)), alpha in radians."""
    return phase_cos(jnp.cos(jnp.asarray(alpha)), K)


def attenuation_h(s: Float[ArrayLike, "..."], t: Float[ArrayLike, "..."], rho, kappa) -> Float[Array, "..."]:
    """h(s, t) = rho exp(-rho kappa (s + t)) / s^2 (eq. 6), s floored at S_FLOOR."""
    s = jnp.maximum(jnp.asarray(s), S_FLOOR)
    return rho * jnp.exp(-rho * kappa * (s + jnp.asarray(t))) / (s * s)


def light_reach(scene: ShaftsScene, light: SpotLight, *, rim: int = 48, grid: int = 7) -> Float[Array, ""]:
    """How far from the light its lit volume reaches: the largest distance at which a ray of the
    cone (rim and interior sample directions) meets a surface, plus 2 %; if any of those rays
    escapes, the distance to the farthest corner of the scene's bounding points (or s_max when
    the scene is empty). Differentiable in the light's pose."""
    x, y, z = light.frame()
    tan_c = jnp.tan(light.cutoff)
    phi = jnp.arange(rim, dtype=tan_c.dtype) * (2.0 * jnp.pi / rim)
    rim_local = jnp.stack([jnp.cos(phi) * tan_c, jnp.sin(phi) * tan_c, jnp.ones_like(phi)], axis=-1)
    g = (np.arange(grid) + 0.5) / grid * 2.0 - 1.0
    gy, gx = np.meshgrid(g, g, indexing="ij")
    keep = (gx**2 + gy**2) <= 1.0
    gx, gy = jnp.asarray(gx[keep], dtype=tan_c.dtype), jnp.asarray(gy[keep], dtype=tan_c.dtype)
    inner = jnp.stack([gx * tan_c, gy * tan_c, jnp.ones_like(gx)], axis=-1)
    local = jnp.concatenate([rim_local, inner], axis=0)
    local = local / safe_norm(local)[:, None]
    dirs = local @ jnp.stack([x, y, z], axis=0)
    t = nearest_distance(light.position, dirs, scene.prims)
    finite = jnp.isfinite(t)
    hit_reach = 1.02 * jnp.max(jnp.where(finite, t, 0.0))
    if scene.spheres.count + scene.quads.count == 0:
        box_reach = jnp.asarray(scene.render.s_max, dtype=tan_c.dtype)
    else:
        pts = bounding_points(scene.prims)
        box_reach = jnp.max(safe_norm(pts - light.position[None, :]))
    return jnp.where(jnp.all(finite), hit_reach, box_reach)


def cone_depth_range(light: SpotLight, reach: Float[ArrayLike, ""], eye: Float[ArrayLike, "3"],
                     forward: Float[ArrayLike, "3"], *, near: float = 1e-3
                     ) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """View-depth range [r_near, r_far] of the cone cut at `reach` (the convex hull of the apex and
    the disk of radius reach*tan(cutoff) at axial distance reach); r_near >= `near`."""
    apex, centre, radius = light.cone_bound(reach)
    forward = jnp.asarray(forward)
    _, _, axis = light.frame()
    perp = safe_norm(forward - jnp.sum(forward * axis) * axis)
    d_apex = jnp.sum((apex - eye) * forward)
    d_centre = jnp.sum((centre - eye) * forward)
    lo = jnp.minimum(d_apex, d_centre - radius * perp)
    hi = jnp.maximum(d_apex, d_centre + radius * perp)
    lo = jnp.maximum(lo, near)
    hi = jnp.maximum(hi, lo + near)
    return lo, hi


def _dot3(a, b):
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def cone_interval(origin: Float[ArrayLike, "3"], direction: Float[ArrayLike, "*B 3"], apex: Float[ArrayLike, "3"],
                  axis: Float[ArrayLike, "3"], cos_c: Float[ArrayLike, ""], reach: Float[ArrayLike, ""]
                  ) -> tuple[Float[Array, "*B"], Float[Array, "*B"]]:
    """[t0, t1] of rays origin + t direction inside the cone (apex, unit axis, half-angle
    acos(cos_c) < 90 deg) cut by the ball of radius `reach` around the apex; t0 == t1 = 0 when a
    ray misses it. Branch-free and batched over `direction`: the set is convex, so its ends are
    among the roots of the cone and ball quadratics; the segments between the sorted candidates
    whose midpoints lie inside form the interval."""
    d = jnp.asarray(direction)
    w0 = jnp.broadcast_to(jnp.asarray(origin) - jnp.asarray(apex), d.shape)
    a = jnp.broadcast_to(jnp.asarray(axis), d.shape)
    # ball |w0 + t d|^2 <= R^2
    bb = _dot3(w0, d)
    ww = _dot3(w0, w0)
    cb = ww - reach * reach
    disc_b = bb * bb - cb
    ball_hit = disc_b > 0
    rb = jnp.sqrt(jnp.where(ball_hit, disc_b, 1.0))
    b1, b2 = -bb - rb, -bb + rb
    # cone (w.a)^2 - c^2 |w|^2 = A t^2 + 2 B t + C
    e, k = _dot3(d, a), _dot3(w0, a)
    c2 = cos_c * cos_c
    A = e * e - c2
    B = e * k - c2 * bb
    C = k * k - c2 * ww
    disc_c = B * B - A * C
    cone_real = disc_c > 0
    rc = jnp.sqrt(jnp.where(cone_real, disc_c, 1.0))
    safe_A = jnp.where(jnp.abs(A) > 1e-12, A, 1e-12)
    r1 = jnp.where(cone_real, (-B - rc) / safe_A, b1)
    r2 = jnp.where(cone_real, (-B + rc) / safe_A, b1)
    c0, c1, c2_, c3 = (jnp.clip(x, b1, b2) for x in (b1, r1, r2, b2))
    # sorting network for 4 values
    c0, c1 = jnp.minimum(c0, c1), jnp.maximum(c0, c1)
    c2_, c3 = jnp.minimum(c2_, c3), jnp.maximum(c2_, c3)
    c0, c2_ = jnp.minimum(c0, c2_), jnp.maximum(c0, c2_)
    c1, c3 = jnp.minimum(c1, c3), jnp.maximum(c1, c3)
    c1, c2_ = jnp.minimum(c1, c2_), jnp.maximum(c1, c2_)
    t0 = jnp.full_like(b1, jnp.inf)
    t1 = jnp.full_like(b1, -jnp.inf)
    for lo_c, hi_c in ((c0, c1), (c1, c2_), (c2_, c3)):
        mid = 0.5 * (lo_c + hi_c)
        axial = k + mid * e
        wsq = ww + 2.0 * mid * bb + mid * mid  # |w0 + mid d|^2, d unit
        inside = (axial >= 0) & (axial * axial >= c2 * wsq) & (hi_c > lo_c) & ball_hit
        t0 = jnp.where(inside, jnp.minimum(t0, lo_c), t0)
        t1 = jnp.where(inside, jnp.maximum(t1, hi_c), t1)
    empty = t1 < t0
    return jnp.where(empty, 0.0, t0), jnp.where(empty, 0.0, t1)


def cone_intervals(scene: ShaftsScene, light: SpotLight, dirs: Float[Array, "*B 3"], surface_t: Float[Array, "*B"],
                   reach: Float[Array, ""], *, margin: float = 1e-3) -> tuple[Float[Array, "*B"], Float[Array, "*B"]]:
    """Per-pixel [t0, t1] of the view ray inside `light`'s cone (widened by `margin` radians, a
    conservative bound: the integrand itself applies the exact cone), cut at the visible surface
    and, in fog with a density grid, to the grid's box (there is no fog outside it)."""
    _, _, axis = light.frame()
    cos_c = jnp.cos(jnp.minimum(light.cutoff + margin, 0.5 * jnp.pi - 1e-3))
    t0, t1 = cone_interval(scene.camera.eye, dirs, light.position, axis, cos_c, reach)
    t0 = jnp.maximum(t0, 0.0)
    t1 = jnp.minimum(t1, surface_t)
    grid = scene.medium.density
    if grid is not None:
        t_in, t_out = box_interval(grid.box_min, grid.box_max, scene.camera.eye, dirs)
        t0, t1 = jnp.maximum(t0, t_in), jnp.minimum(t1, t_out)
    return t0, jnp.maximum(t1, t0)


def surface_term(scene: ShaftsScene, points: Float[Array, "*B 3"], normals: Float[Array, "*B 3"],
                 albedo: Float[Array, "*B 3"], surface_t: Float[Array, "*B"], visibility, *, quantize_bits: int = 0,
                 light_depth=None, view_depth: Float[Array, "*B"] | None = None,
                 footprint: Float[Array, "*B"] | None = None) -> Float[Array, "*B 3"]:
    """I_o exp(-rho kappa T): two-sided Lambert albedo/pi * sum_lights I |cos| / s^2 exp(-rho kappa s) H,
    attenuated toward the eye; 0 where the ray hits nothing. `visibility(light_index, points,
    normals, s)` gives H at the surface points (shadow rays or a shadow map).

    With a density grid the path lengths s and T become optical depths (integrals of d):
    `light_depth(light_index, points)` along the path from each light, `view_depth` along the
    view ray to the surface (both required then). `footprint`: the pixel's width at each point,
    for light-map lookups at the mip level it needs (None: bilinear). The sum of `surface_light`
    over the lights, through `surface_radiance`."""
    total = sum(surface_light(scene, index, points, normals, visibility, quantize_bits=quantize_bits,
                              light_depth=light_depth, footprint=footprint) for index in range(len(scene.lights)))
    return surface_radiance(scene, albedo, surface_t, jnp.zeros_like(points) + total, view_depth=view_depth)


def surface_light(scene: ShaftsScene, index: int, points: Float[Array, "*B 3"], normals: Float[Array, "*B 3"],
                  visibility, *, quantize_bits: int = 0, light_depth=None,
                  footprint: Float[Array, "*B"] | None = None) -> Float[Array, "*B 3"]:
    """Light `index`'s term of `surface_term` at the points: I |cos| / s^2 exp(-rho kappa s) H (its
    optical depth for s with `light_depth`); zero outside the light's cone (its falloff)."""
    light = scene.lights[index]
    I, s, w = light.radiant_intensity(points, quantize_bits=quantize_bits, footprint=footprint)
    cos_i = jnp.abs(dot(w, normals))
    s_safe = jnp.maximum(s, S_FLOOR)
    H = visibility(index, points, normals, s)
    tau = s if light_depth is None else light_depth(index, points)
    scale = cos_i * H * jnp.exp(-scene.medium.sigma_t * tau) / (s_safe * s_safe)
    return I * scale[..., None]


def surface_radiance(scene: ShaftsScene, albedo: Float[Array, "*B 3"], surface_t: Float[Array, "*B"],
                     lit: Float[Array, "*B 3"], *, view_depth: Float[Array, "*B"] | None = None
                     ) -> Float[Array, "*B 3"]:
    """The radiance toward the eye of surfaces lit by `lit` (the lights' `surface_light` summed):
    albedo / pi * lit, attenuated along the view ray (its optical depth `view_depth` in a density
    grid); 0 where the ray hits nothing (surface_t infinite)."""
    sigma = scene.medium.sigma_t
    hit = jnp.isfinite(surface_t)
    T = jnp.where(hit, surface_t, 0.0) if view_depth is None else jnp.where(hit, view_depth, 0.0)
    radiance = albedo / jnp.pi * lit * jnp.exp(-sigma * T)[..., None]
    return jnp.where(hit[..., None], radiance, 0.0)


_SLOPE_BIAS = 1.5  # surface shadow lookups: extra bias in texel footprints x tan(incidence)
_MAX_SLOPE = 8.0  # cap on tan(incidence) in that slope-scaled bias
_NORMAL_OFFSET = 2.0  # surface shadow lookups move this many texel footprints along the normal


def shadow_map_visibility(scene: ShaftsScene, maps: tuple[ShadowMap, ...]):
    """visibility(light_index, points, normals, s) -> H at surface points from the lights' shadow
    maps (the hardware's way, for `surface_term`): the lookup point moves `_NORMAL_OFFSET` texel
    footprints off the surface toward the light and the bias grows with tan(incidence), against
    shadow acne on surfaces seen at grazing angles. No gradient (shadow maps carry none)."""
    bias0 = scene.render.shadow_bias

    def visibility(index, pts, nrm, s):
        sm, light = maps[index], scene.lights[index]
        w = (pts - jnp.broadcast_to(light.position, pts.shape)) / jnp.maximum(s, S_FLOOR)[..., None]
        cos_signed = dot(w, nrm)
        cos_i = jnp.clip(jnp.abs(cos_signed), 1e-3, 1.0)
        tan_i = jnp.minimum(jnp.sqrt(jnp.maximum(1.0 - cos_i * cos_i, 0.0)) / cos_i, _MAX_SLOPE)
        footprint = sm.texel_angle * s
        facing = jnp.where(cos_signed < 0, 1.0, -1.0).astype(pts.dtype)  # normal side toward the light
        lookup = pts + nrm * (_NORMAL_OFFSET * footprint * facing)[..., None]
        bias = bias0 + _SLOPE_BIAS * footprint * tan_i
        return shadow_test(sm, jax.lax.stop_gradient(lookup), bias=jax.lax.stop_gradient(bias))

    return visibility

"""Ray-marched reference (the paper's "conventional method"): samples along each view ray with
a shadow RAY per sample, exact spot-light evaluation, no tables, no quantization.

For each light and pixel the view ray is cut to the part inside the light's cone (and in front of
the visible surface, and within the light's reach; with a density grid, inside its box);
`samples` midpoint samples cover that interval, so the result converges to the exact integral of
eq. 2 as `samples` grows. With a density grid each sample's transmittance toward the
eye and toward the light is exact: `segment_optical_depth` integrates the trilinear density
piece by piece between voxel-centre planes (and the surfaces' light and view paths likewise).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..geometry import cast_rays, hit_point, occluded
from ..maths import outer
from ._density import DensityGrid, segment_optical_depth
from ._model import (
    FAR,
    S_FLOOR,
    attenuation_h,
    cone_intervals,
    light_reach,
    phase_cos,
    shadow_map_visibility,
    surface_term,
)
from ._scene import ShaftsScene

__all__ = ["render_raymarch", "raymarch_scattering"]

_SURFACE_OFFSET = 1e-4  # shadow rays leave surfaces this far along the normal


def shadow_ray_visibility(scene: ShaftsScene):
    """visibility(light_index, points, normals, s) -> H at surface points by shadow rays."""
    def visibility(index, points, normals, s):
        light = scene.lights[index]
        to_light = jnp.broadcast_to(light.position, points.shape) - points
        s_safe = jnp.maximum(s, S_FLOOR)
        w = to_light / s_safe[..., None]
        side = jnp.where(jnp.sum(w * normals, axis=-1) >= 0, 1.0, -1.0).astype(points.dtype)
        origin = points + normals * (_SURFACE_OFFSET * side)[..., None]
        return 1.0 - occluded(origin, w, s - 2 * _SURFACE_OFFSET, scene.prims)
    return visibility


def surface_visibility(scene: ShaftsScene, maps, surface_shadows: str):
    """The surfaces' shadows for `surface_term`: "map" (the lights' shadow maps, slope-scaled, as
    the hardware does) or "rays" (exact shadow rays, as the ray march)."""
    if surface_shadows == "map":
        return shadow_map_visibility(scene, maps)
    if surface_shadows == "rays":
        return shadow_ray_visibility(scene)
    raise ValueError(f"surface_shadows must be 'map' or 'rays', not {surface_shadows!r}")


def _pieces(grid: DensityGrid) -> int:
    return sum(grid.shape) + 7


def segment_depths(grid: DensityGrid, p0: Float[Array, "3"], points: Float[Array, "*B 3"], *, batch_size: int = 4096
                   ) -> Float[Array, "*B"]:
    """`segment_optical_depth` from one point to many, in batches (each segment holds ~2 x
    (nx + ny + nz) lookups)."""
    flat = points.reshape((-1, 3))
    out = jax.lax.map(lambda p: segment_optical_depth(grid, p0, p), flat, batch_size=batch_size)
    return out.reshape(points.shape[:-1])


def raymarch_scattering(scene: ShaftsScene, dirs: Float[Array, "N 3"], surface_t: Float[Array, " N"], *,
                        samples: int = 180, batch_size: int = 256) -> Float[Array, "N 3"]:
    """I_s of eq. 2 for N view rays (unit `dirs` from the camera eye), summed over the lights."""
    eye = scene.camera.eye
    rho, kappa, K = scene.medium.rho, scene.medium.kappa, scene.medium.K
    grid = scene.medium.density
    if grid is not None:  # every sample holds two exact segment integrals: smaller batches
        batch_size = max(1, batch_size * 8 // _pieces(grid))
    total = jnp.zeros(dirs.shape, dtype=dirs.dtype)
    frac = (jnp.arange(samples, dtype=dirs.dtype) + 0.5) / samples
    for light in scene.lights:
        reach = light_reach(scene, light)
        t0, t1 = cone_intervals(scene, light, dirs, surface_t, reach)

        def one_ray(args, light=light):
            d, a, b = args
            dt = (b - a) / samples
            t = a + frac * (b - a)
            pts = jnp.broadcast_to(eye, (samples, 3)) + outer(t, d)
            I, s, w = light.radiant_intensity(pts)
            cos_a = -(w @ d)
            if grid is None:
                g = phase_cos(cos_a, K) * attenuation_h(s, t, rho, kappa)
            else:  # rho d(P) F exp(-rho kappa (tau_view + tau_light)) / s^2, both optical depths exact
                tau = segment_optical_depth(grid, eye, pts) + segment_optical_depth(grid, light.position, pts)
                s_safe = jnp.maximum(s, S_FLOOR)
                g = phase_cos(cos_a, K) * rho * grid.at(pts) * jnp.exp(-rho * kappa * tau) / (s_safe * s_safe)
            H = 1.0 - occluded(pts, -w, s - 1e-4, scene.prims)
            return jnp.sum(I * (H * g)[:, None], axis=0) * dt

        total = total + jax.lax.map(one_ray, (dirs, t0, t1), batch_size=batch_size)
    return total


def render_raymarch(scene: ShaftsScene, *, samples: int = 180, batch_size: int = 256, return_parts: bool = False
                    ) -> Float[Array, "H W 3"]:
    """Exact-reference image (H, W, 3): surfaces (shadow rays, two-sided Lambert, extinction) plus
    the ray-marched in-scattering of every light (`samples` per light and pixel, inside the
    light's cone). Jittable and differentiable. return_parts: also return (surface, scattering)."""
    cam = scene.camera
    dirs = cam.primary_rays()
    t, normals, albedo = cast_rays(cam.eye, dirs, scene.prims)
    points = hit_point(cam.eye, dirs, t, far=FAR)
    grid = scene.medium.density
    if grid is None:
        surface = surface_term(scene, points, normals, albedo, t, shadow_ray_visibility(scene))
    else:
        surface = surface_term(scene, points, normals, albedo, t, shadow_ray_visibility(scene),
                               light_depth=lambda i, p: segment_depths(grid, scene.lights[i].position, p),
                               view_depth=segment_depths(grid, cam.eye, points))
    surface_t = jnp.where(jnp.isfinite(t), t, FAR)
    flat = raymarch_scattering(scene, dirs.reshape((-1, 3)), surface_t.reshape((-1,)), samples=samples,
                               batch_size=batch_size)
    scattering = flat.reshape(surface.shape)
    if return_parts:
        return surface + scattering, (surface, scattering)
    return surface + scattering

"""Sand dust (paper 001 section 3.7): particles advected over the dunes by eq. 7, drawn as
camera-facing billboards of a spherical cloud of grains, alpha-blended back to front."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..camera import Camera
from ..lights import Sun
from ..shadows import triangle_height

__all__ = ["DustParticles", "dust_particles", "composite_billboards", "billboard_alpha"]

DUST_ALBEDO = (0.75, 0.58, 0.40)


class DustParticles(eqx.Module):
    """Centres (P x 3, world) and radii (P, world units) of the dust clouds; `opacity` is the
    optical depth through a cloud's centre."""

    position: Float[Array, "P 3"]
    radius: Float[Array, " P"]
    opacity: Float[Array, " P"]


def dust_particles(key: Array, maps, ripple_height: Float[Array, "R R"], *, count: int = 600, steps: int = 20,
                   drift: float = 0.35, lift: float = 0.02, jitter: float = 0.08, size: float = 0.5,
                   region: tuple[float, float, float, float] | None = None) -> DustParticles:
    """Emit `count` clouds at random ripple-grid points of the dunes and advect them `steps`
    steps of eq. 7: x += dx + a_x, y += a_y, z = H_dune(x, y) + dz + a_z (wind along +x,
    a_* uniform in [-jitter, jitter]). A cloud's radius is proportional to the local ripple
    height at its emission point (shifted to be positive), scaled so the highest gets `size`.
    `region` (x0, x1, y0, y1) limits the emission area (default: the whole field)."""
    ny, nx = maps.z.shape
    dtype = maps.z.dtype
    x0, x1, y0, y1 = region or (0.0, (nx - 1) * maps.spacing, 0.0, (ny - 1) * maps.spacing)
    k_pos, k_walk = jax.random.split(key)
    r = ripple_height.shape[0]
    texel = maps.spacing / maps.texels
    # emission points on the ripple grid (texel centres)
    u = jax.random.uniform(k_pos, (count, 2), dtype)
    ix = jnp.floor((x0 + u[:, 0] * (x1 - x0)) / texel).astype(jnp.int32)
    iy = jnp.floor((y0 + u[:, 1] * (y1 - y0)) / texel).astype(jnp.int32)
    xy = jnp.stack([(ix.astype(dtype) + 0.5) * texel, (iy.astype(dtype) + 0.5) * texel], axis=-1)
    rh = ripple_height[jnp.mod(iy, r), jnp.mod(ix, r)]
    lo, hi = jnp.min(ripple_height), jnp.max(ripple_height)
    radius = size * (0.25 + 0.75 * (rh - lo) / jnp.maximum(hi - lo, 1e-12))
    noise = jax.random.uniform(k_walk, (steps, count, 3), dtype, -jitter, jitter)

    def advect(xy, a):
        x = jnp.clip(xy[:, 0] + drift + a[:, 0], 0.0, (nx - 1) * maps.spacing)
        y = jnp.clip(xy[:, 1] + a[:, 1], 0.0, (ny - 1) * maps.spacing)
        return jnp.stack([x, y], axis=-1), a[:, 2]

    xy, az = jax.lax.scan(advect, xy, noise)
    z = triangle_height(maps.z, xy, spacing=maps.spacing) + lift + az[-1] + radius
    return DustParticles(jnp.concatenate([xy, z[:, None]], axis=-1), radius, jnp.full((count,), 0.1, dtype))


def billboard_alpha(rho: Array, opacity: Array) -> Array:
    """Opacity of a spherical cloud at normalised distance `rho` (0 centre, 1 rim) from its centre
    on the billboard: density falling as 1 - (r/R)^2 inside the sphere integrates along the line
    of sight to a column proportional to (1 - rho^2)^(3/2); alpha = 1 - exp(-opacity * column)."""
    column = jnp.maximum(1.0 - rho * rho, 0.0) ** 1.5
    return 1.0 - jnp.exp(-opacity * column)


def composite_billboards(image: Float[Array, "H W 3"], depth: Float[Array, "H W"], camera: Camera,
                         particles: DustParticles, sun: Sun, sky_irradiance: Float[Array, "3"], *,
                         sunlit: Float[Array, " P"] | None = None, max_radius_px: int = 16) -> Float[Array, "H W 3"]:
    """Alpha-blend the clouds over `image`, farthest first (sorted by depth, then a scan), each
    hidden where the scene at that pixel (`depth`, distance along the ray) is nearer than it.
    Billboards are squares facing the camera; their screen radius is clamped to
    `max_radius_px` (the static patch each one updates). `sunlit` (0..1 per cloud, default 1)
    scales the sunlight a cloud receives (0 inside a dune's shadow)."""
    dtype = image.dtype
    h, w = depth.shape
    pix, zview = camera.project(particles.position.astype(dtype))
    dist = jnp.sqrt(jnp.sum((particles.position - jnp.reshape(camera.eye.astype(dtype), (1, 3))) ** 2, axis=-1))
    focal = h / (2.0 * camera.tan_half_fov.astype(dtype))
    rad_px = jnp.minimum(particles.radius * focal / jnp.maximum(zview, 1e-6), float(max_radius_px))
    order = jnp.argsort(-dist)
    m = max_radius_px
    size = 2 * m + 1
    img = jnp.pad(image, ((m, m), (m, m), (0, 0)))
    dep = jnp.pad(depth, ((m, m), (m, m)), constant_values=jnp.inf)
    off = jnp.arange(size, dtype=dtype) - m
    rgb3 = (1, 1, 3)
    lit = jnp.ones(particles.radius.shape, dtype) if sunlit is None else sunlit.astype(dtype)
    # single scattering of sunlight (isotropic phase, ~1/4 of the incident flux) plus sky light
    albedo = jnp.asarray(DUST_ALBEDO, dtype) / jnp.pi
    sun_part = 0.25 * sun.irradiance.astype(dtype) * albedo
    sky_part = sky_irradiance.astype(dtype) * albedo

    def draw(img, i):
        cx, cy = pix[i, 0], pix[i, 1]
        c0 = jnp.floor(cx).astype(jnp.int32)
        r0 = jnp.floor(cy).astype(jnp.int32)
        # patch of pixels (r0 - m .. r0 + m, c0 - m .. c0 + m) in image coordinates, + m in padded ones
        start_r = jnp.clip(r0, 0, h - 1).astype(jnp.int32)  # padded row start_r + k is image row start_r + k - m
        start_c = jnp.clip(c0, 0, w - 1).astype(jnp.int32)
        zero = jnp.zeros((), jnp.int32)
        patch = jax.lax.dynamic_slice(img, (start_r, start_c, zero), (size, size, 3))
        dpatch = jax.lax.dynamic_slice(dep, (start_r, start_c), (size, size))
        py = start_r.astype(dtype) + off + 0.5  # pixel centres of the patch rows
        px = start_c.astype(dtype) + off + 0.5
        rho = jnp.sqrt((py[:, None] - cy) ** 2 + (px[None, :] - cx) ** 2) / jnp.maximum(rad_px[i], 1e-6)
        alpha = billboard_alpha(rho, particles.opacity[i])
        alpha = jnp.where((dpatch > dist[i]) & (zview[i] > 0), alpha, 0.0)[..., None]
        colour = sky_part + lit[i] * sun_part
        patch = patch * (1 - alpha) + alpha * jnp.reshape(colour, rgb3)
        return jax.lax.dynamic_update_slice(img, patch, (start_r, start_c, zero)), None

    img, _ = jax.lax.scan(draw, img, order.astype(jnp.int32))
    return img[m:m + h, m:m + w]

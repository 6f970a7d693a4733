"""Physically based clear sky (Nishita et al. 1993, paper 001's [14]): single Rayleigh and Mie
scattering in a spherical exponential atmosphere, y up, linear RGB; `sky_envmap` returns it as a
lat-long map in Mitsuba 3's `envmap` orientation. The integral, its quadrature's accuracy and the
map's orientation: docs/rendering.md.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

__all__ = ["Atmosphere", "sky_radiance", "sky_envmap", "envmap_directions", "direction_to_envmap_uv",
           "sun_direction_y_up", "optical_depth"]


class Atmosphere(eqx.Module):
    """Earth and atmosphere constants (SI units: metres, 1/m). Defaults: Earth radius 6360 km,
    top of the atmosphere at 6420 km, scale heights 8 km (Rayleigh) and 1.2 km (Mie), sea-level
    Rayleigh scattering (5.8, 13.5, 33.1) e-6 /m at (680, 550, 440) nm (Bruneton & Neyret 2008),
    Mie scattering 21e-6 /m with extinction = scattering / 0.9 and asymmetry g = 0.76 (Nishita)."""

    earth_radius: float = 6360e3
    atmosphere_radius: float = 6420e3
    rayleigh_scale_height: float = 8000.0
    mie_scale_height: float = 1200.0
    rayleigh_scattering: tuple[float, float, float] = (5.8e-6, 13.5e-6, 33.1e-6)
    mie_scattering: float = 21e-6
    mie_extinction: float = 21e-6 / 0.9
    mie_g: float = 0.76


def sun_direction_y_up(elevation_deg: ArrayLike, azimuth_deg: ArrayLike = 0.0) -> Float[Array, "3"]:
    """Unit vector toward the sun (y up): elevation above the horizon; azimuth from -z toward +x,
    which is the envmap's u times 360 (azimuth 0: -z, u = 0; 90: +x; 180: +z, the map's centre)."""
    el = jnp.deg2rad(jnp.asarray(elevation_deg, dtype=jnp.result_type(float)))
    az = jnp.deg2rad(jnp.asarray(azimuth_deg, dtype=jnp.result_type(float)))
    return jnp.stack([jnp.cos(el) * jnp.sin(az), jnp.sin(el), -jnp.cos(el) * jnp.cos(az)])


def _components(v: Array) -> tuple[Array, Array, Array]:
    return v[..., 0], v[..., 1], v[..., 2]


def _unit(v: Array) -> Array:
    x, y, z = _components(v)
    n = jnp.sqrt(x * x + y * y + z * z)
    n = jnp.where(n > 0, n, 1.0)
    return v / n[..., None]


def _rayleigh_phase(mu: Array) -> Array:
    return 3.0 / (16.0 * math.pi) * (1.0 + mu * mu)


def _mie_phase(mu: Array, g: Array) -> Array:
    """Cornette-Shanks phase function (normalised over the sphere)."""
    g2 = g * g
    return (3.0 / (8.0 * math.pi) * (1.0 - g2) * (1.0 + mu * mu)
            / ((2.0 + g2) * jnp.power(1.0 + g2 - 2.0 * g * mu, 1.5)))


def _heights(c_earth: Array, b: Array, t: Array, radius: Array) -> Array:
    """Height above the ground of origin + t dir, from c_earth = |origin|^2 - R^2 and b = origin.dir,
    without cancellation: |Q|^2 - R^2 = c_earth + 2 t b + t^2, h = that / (|Q| + R)."""
    excess = c_earth + t * (2.0 * b + t)
    norm = jnp.sqrt(jnp.maximum(excess + radius * radius, 0.0))
    return excess / (norm + radius)


def _quadrature(t_max: Array, n: int) -> tuple[Array, Array]:
    """Sample distances t_k = t_max u_k^2 at midpoints u_k and weights dt_k (sum = t_max); shape (..., n)."""
    u = (jnp.arange(n, dtype=t_max.dtype) + 0.5) / n
    t = t_max[..., None] * (u * u)[None, :].reshape((1,) * t_max.ndim + (n,))
    w = t_max[..., None] * (2.0 * u / n).reshape((1,) * t_max.ndim + (n,))
    return t, w


def _exit_distance(c_atm: Array, b: Array) -> Array:
    """Far intersection with the top of the atmosphere (origin inside it: c_atm <= 0)."""
    return -b + jnp.sqrt(jnp.maximum(b * b - c_atm, 0.0))


def _depth_to_sun(c_earth: Array, b: Array, atm: Atmosphere, n: int, dtype) -> tuple[Array, Array, Array]:
    """Rayleigh and Mie optical depths (density integrals, metres) from points with
    |P|^2 - R^2 = c_earth and P.s = b toward the sun, and a 0/1 mask of Earth shadow."""
    R = jnp.asarray(atm.earth_radius, dtype)
    top2 = jnp.asarray((atm.atmosphere_radius - atm.earth_radius) * (atm.atmosphere_radius + atm.earth_radius), dtype)
    c_atm = c_earth - top2
    t_exit = _exit_distance(c_atm, b)
    t, w = _quadrature(t_exit, n)
    h = _heights(c_earth[..., None], b[..., None], t, R)
    tau_r = jnp.sum(w * jnp.exp(-h / atm.rayleigh_scale_height), axis=-1)
    tau_m = jnp.sum(w * jnp.exp(-h / atm.mie_scale_height), axis=-1)
    lit = jnp.logical_not((b < 0.0) & (b * b - c_earth > 0.0))  # the sun ray does not hit the Earth
    return tau_r, tau_m, lit.astype(dtype)


def optical_depth(view_dirs: Float[ArrayLike, "... 3"], *, altitude: float = 1.0, samples: int = 16,
                  atmosphere: Atmosphere = Atmosphere()) -> tuple[Float[Array, "..."], Float[Array, "..."]]:
    """Rayleigh and Mie optical depths (integrals of the relative density, in metres: multiply by
    a scattering coefficient) from the viewer to the top of the atmosphere or the ground."""
    d = _unit(jnp.asarray(view_dirs))
    dtype = d.dtype
    t_max, c_earth, b = _view_segment(d, altitude, atmosphere)
    t, w = _quadrature(t_max, samples)
    h = _heights(c_earth[..., None], b[..., None], t, jnp.asarray(atmosphere.earth_radius, dtype))
    return (jnp.sum(w * jnp.exp(-h / atmosphere.rayleigh_scale_height), axis=-1),
            jnp.sum(w * jnp.exp(-h / atmosphere.mie_scale_height), axis=-1))


def _view_segment(d: Array, altitude, atm: Atmosphere) -> tuple[Array, Array, Array]:
    dtype = d.dtype
    R = jnp.asarray(atm.earth_radius, dtype)
    alt = jnp.asarray(altitude, dtype)
    c_earth = jnp.broadcast_to(alt * (2.0 * R + alt), d.shape[:-1])  # |O|^2 - R^2, O = (0, R + alt, 0)
    b = (R + alt) * d[..., 1]  # O . d
    top2 = jnp.asarray((atm.atmosphere_radius - atm.earth_radius) * (atm.atmosphere_radius + atm.earth_radius), dtype)
    t_top = _exit_distance(c_earth - top2, b)
    disc = b * b - c_earth
    hits_ground = (b < 0.0) & (disc > 0.0)
    t_ground = c_earth / (-b + jnp.sqrt(jnp.maximum(disc, 0.0)))  # near root, cancellation-free
    t_max = jnp.where(hits_ground, jnp.minimum(t_ground, t_top), t_top)
    return t_max, c_earth, b


@functools.partial(jax.jit, static_argnames=("samples", "light_samples", "sun_disk", "sun_angular_radius_deg"))
def sky_radiance(view_dirs: Float[ArrayLike, "... 3"], sun_dir: Float[ArrayLike, "3"], *,
                 sun_intensity: float = 20.0, samples: int = 16, light_samples: int = 8,
                 altitude: float = 1.0, atmosphere: Atmosphere = Atmosphere(),
                 sun_disk: bool = False, sun_angular_radius_deg: float = 0.27) -> Float[Array, "... 3"]:
    """Single-scattered sky radiance (linear RGB) along unit view directions (world frame, y up).

    `sun_intensity` is the solar irradiance E_sun (the radiance scale: 20 gives a noon zenith
    of about 1-2 in the blue). With `sun_disk`, directions within `sun_angular_radius_deg` of the
    sun also see the attenuated disk, radiance E_sun T / (solid angle of the disk). Works for a
    sun below the horizon (dusk): only the sample points still in sunlight scatter.
    """
    d = _unit(jnp.asarray(view_dirs))
    dtype = d.dtype
    s = _unit(jnp.asarray(sun_dir, dtype))
    s_b = s.reshape((1,) * (d.ndim - 1) + (3,))  # explicit rank for broadcasting against d
    atm = atmosphere
    R = jnp.asarray(atm.earth_radius, dtype)
    beta_r = jnp.asarray(atm.rayleigh_scattering, dtype)
    beta_m = jnp.asarray(atm.mie_scattering, dtype)
    ext_m = jnp.asarray(atm.mie_extinction, dtype)

    t_max, c_earth, b = _view_segment(d, altitude, atm)
    t, w = _quadrature(t_max, samples)  # (..., n)
    h = _heights(c_earth[..., None], b[..., None], t, R)
    rho_r = jnp.exp(-h / atm.rayleigh_scale_height)
    rho_m = jnp.exp(-h / atm.mie_scale_height)
    # optical depth from the viewer to each sample: trapezoid-like cumulative midpoint sum
    cum_r = jnp.cumsum(w * rho_r, axis=-1) - 0.5 * w * rho_r
    cum_m = jnp.cumsum(w * rho_m, axis=-1) - 0.5 * w * rho_m
    # sample points P = O + t d: |P|^2 - R^2 and P.s
    alt = jnp.asarray(altitude, dtype)
    cp = c_earth[..., None] + t * (2.0 * b[..., None] + t)
    ps = (R + alt) * s[1] + t * jnp.sum(d * s_b, axis=-1)[..., None]
    tau_r_sun, tau_m_sun, lit = _depth_to_sun(cp, ps, atm, light_samples, dtype)
    tau_r = (cum_r + tau_r_sun)[..., None]
    tau_m = (cum_m + tau_m_sun)[..., None]
    beta_rb = beta_r.reshape((1,) * (tau_r.ndim - 1) + (3,))
    trans = jnp.exp(-(beta_rb * tau_r + ext_m * tau_m))  # (..., n, 3)
    mu = jnp.sum(d * s_b, axis=-1)
    phase_r = _rayleigh_phase(mu)[..., None, None]
    phase_m = _mie_phase(mu, jnp.asarray(atm.mie_g, dtype))[..., None, None]
    scatter = (beta_rb * (rho_r * lit * w)[..., None] * phase_r
               + beta_m * (rho_m * lit * w)[..., None] * phase_m)
    radiance = sun_intensity * jnp.sum(trans * scatter, axis=-2)
    if sun_disk:
        cos_r = math.cos(math.radians(sun_angular_radius_deg))
        solid = 2.0 * math.pi * (1.0 - cos_r)
        tr_r, tr_m = cum_r[..., -1] + 0.5 * (w * rho_r)[..., -1], cum_m[..., -1] + 0.5 * (w * rho_m)[..., -1]
        beta_rv = beta_r.reshape((1,) * (d.ndim - 1) + (3,))
        t_view = jnp.exp(-(beta_rv * tr_r[..., None] + ext_m * tr_m[..., None]))
        visible = ((mu >= cos_r) & (t_max > 0.0) & jnp.logical_not((b < 0.0) & (b * b - c_earth > 0.0))).astype(dtype)
        radiance = radiance + (sun_intensity / solid) * visible[..., None] * t_view
    return radiance


def envmap_directions(width: int, height: int, *, dtype=None) -> Float[Array, "H W 3"]:
    """Unit direction of every texel of a lat-long map as Mitsuba 3's envmap reads it:
    column j at u = (j + 1/2) / W, row i at v = i / (H - 1) (rows from zenith to nadir)."""
    dtype = dtype or jnp.result_type(float)
    u = (jnp.arange(width, dtype=dtype) + 0.5) / width
    v = jnp.arange(height, dtype=dtype) / max(height - 1, 1)
    phi = 2.0 * math.pi * u[None, :]
    theta = math.pi * v[:, None]
    x = jnp.sin(phi) * jnp.sin(theta)
    y = jnp.broadcast_to(jnp.cos(theta), (height, width))
    z = -jnp.cos(phi) * jnp.sin(theta)
    return jnp.stack([x, y, z], axis=-1)


def direction_to_envmap_uv(dirs: Float[ArrayLike, "... 3"]) -> Float[Array, "... 2"]:
    """Mitsuba 3 envmap mapping: u = atan2(x, -z) / 2 pi mod 1, v = acos(y) / pi."""
    d = _unit(jnp.asarray(dirs))
    x, y, z = _components(d)
    u = jnp.arctan2(x, -z) / (2.0 * math.pi)
    u = u - jnp.floor(u)
    v = jnp.arccos(jnp.clip(y, -1.0, 1.0)) / math.pi
    return jnp.stack([u, v], axis=-1)


@functools.partial(jax.jit, static_argnames=("width", "height", "samples", "light_samples", "sun_disk"))
def sky_envmap(sun_dir: Float[ArrayLike, "3"], *, width: int = 256, height: int = 128,
               sun_intensity: float = 20.0, samples: int = 16, light_samples: int = 8, altitude: float = 1.0,
               atmosphere: Atmosphere = Atmosphere(), sun_disk: bool = False) -> Float[Array, "H W 3"]:
    """Sky radiance on a lat-long map (Mitsuba 3 envmap orientation, see the module docstring).

    With `sun_disk`, the sun's attenuated irradiance E_sun T is put into the texel nearest to
    the sun direction (radiance E_sun T / texel solid angle), so the map carries the sun's energy
    whatever its resolution; a sun below the horizon adds nothing. Jitted (sizes, sample counts
    and the disk switch static).
    """
    dirs = envmap_directions(width, height)
    radiance = _envmap_radiance(dirs, jnp.asarray(sun_dir, dirs.dtype), sun_intensity, samples, light_samples,
                                altitude, atmosphere)
    if sun_disk:
        s = _unit(jnp.asarray(sun_dir, dirs.dtype))
        uv = direction_to_envmap_uv(s)
        col = jnp.mod(jnp.round(uv[0] * width - 0.5).astype(jnp.int32), width)
        row = jnp.clip(jnp.round(uv[1] * (height - 1)).astype(jnp.int32), 0, height - 1)
        row_f = row.astype(dirs.dtype)
        theta0 = jnp.clip(math.pi * (row_f - 0.5) / (height - 1), 0.0, math.pi)
        theta1 = jnp.clip(math.pi * (row_f + 0.5) / (height - 1), 0.0, math.pi)
        texel_solid = (2.0 * math.pi / width) * (jnp.cos(theta0) - jnp.cos(theta1))
        tr, tm = optical_depth(s, altitude=altitude, samples=samples * 4, atmosphere=atmosphere)
        beta_r = jnp.asarray(atmosphere.rayleigh_scattering, dirs.dtype)
        t_view = jnp.exp(-(beta_r * tr + atmosphere.mie_extinction * tm))
        _, c_earth, b = _view_segment(s, altitude, atmosphere)
        above = jnp.logical_not((b < 0.0) & (b * b - c_earth > 0.0))  # the sun ray misses the Earth
        radiance = radiance.at[row, col].add(sun_intensity * t_view / texel_solid * above.astype(dirs.dtype))
    return radiance


def _envmap_radiance(dirs, sun_dir, sun_intensity, samples, light_samples, altitude, atmosphere):
    return sky_radiance(dirs, sun_dir, sun_intensity=sun_intensity, samples=samples,
                        light_samples=light_samples, altitude=altitude, atmosphere=atmosphere)

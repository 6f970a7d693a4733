"""The sun: a distant directional light given by elevation and azimuth."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

__all__ = ["Sun", "sun_direction_z_up"]

# Rayleigh optical depth of the clear atmosphere at the zenith for the sRGB primaries (~ 680, 550, 440 nm)
_RAYLEIGH_TAU = (0.042, 0.097, 0.236)
_AEROSOL_TAU = 0.06


def sun_direction_z_up(elevation_deg: float, azimuth_deg: float) -> tuple[float, float, float]:
    """Unit vector toward the sun, z up; azimuth from +x toward +y."""
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    return (math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el))


def _air_mass(elevation_deg: float) -> float:
    """Kasten & Young (1989) relative optical air mass."""
    el = max(elevation_deg, -0.5)
    return 1.0 / (math.sin(math.radians(el)) + 0.50572 * (el + 6.07995) ** -1.6364)


class Sun(eqx.Module):
    """Directional light: `direction` points toward the sun; `irradiance` (linear RGB) is on a
    surface facing it."""

    direction: Float[Array, "3"]
    irradiance: Float[Array, "3"]

    @classmethod
    def from_angles(cls, elevation_deg: float, azimuth_deg: float, *, intensity: float = 3.0) -> "Sun":
        """A sun whose colour is the solar white attenuated by Rayleigh and aerosol extinction
        along the Kasten-Young air mass (redder when low)."""
        m = _air_mass(elevation_deg)
        colour = [intensity * math.exp(-(tau + _AEROSOL_TAU) * m) for tau in _RAYLEIGH_TAU]
        return cls(jnp.asarray(sun_direction_z_up(elevation_deg, azimuth_deg), dtype=float),
                   jnp.asarray(colour, dtype=float))

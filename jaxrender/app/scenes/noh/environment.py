"""The Noh stage's sky: twilight from `jaxrender.sky`, scaled to a chosen irradiance."""

from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np

from jaxrender.io import luminance
from jaxrender.lights import EnvMap
from jaxrender.maths import default_float
from jaxrender.sky import sky_envmap, sun_direction_y_up


@functools.lru_cache(maxsize=4)
def _sky(width: int, height: int, elevation: float, azimuth: float) -> np.ndarray:
    return np.asarray(sky_envmap(sun_direction_y_up(elevation, azimuth), width=width, height=height, sun_disk=True))


def default_environment(*, width: int = 128, height: int = 64, sun_elevation_deg: float = -2.0,
                        sun_azimuth_deg: float = 235.0, irradiance: float = 0.08) -> EnvMap:
    """Twilight from `jaxrender.sky.sky_envmap` (the sun just below the horizon, behind-left of
    the stage), scaled so that the sky's irradiance on the horizontal stage is `irradiance`
    (the bonfires then dominate, as at a takigi Noh after sunset)."""
    sky = _sky(width, height, float(sun_elevation_deg), float(sun_azimuth_deg))
    rows = np.arange(height)
    omega = 2 * np.pi / width * (np.cos(np.pi * rows / height) - np.cos(np.pi * (rows + 1) / height))
    cos_t = np.cos(np.pi * (rows + 0.5) / height)
    lum = np.asarray(luminance(sky))
    e = float(np.sum(lum * (np.maximum(cos_t, 0) * omega)[:, None]))
    return EnvMap.from_array(jnp.asarray(sky, dtype=default_float()), scale=irradiance / max(e, 1e-12))

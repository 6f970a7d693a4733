"""Sand-grain texture (paper 001 section 3.6): a random heightfield seen from straight above."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..maths import normalize

__all__ = ["sand_grain_texture"]


def sand_grain_texture(key: Array, size: int = 64, *, grain_height: float = 0.6, contrast: float = 1.0,
                       light: tuple[float, float, float] = (0.4, 0.3, 0.87)) -> Float[Array, "S S"]:
    """Brightness (mean 1) of a periodic random heightfield of grains, lit from `light` and seen
    from above: the albedo multiplier that gives the sand its grainy look.

    Heights are uniform random per texel, smoothed by a 3x3 periodic tent so grains span a few
    texels; the image is Lambert shading of that field, normalised to mean 1, with its deviation
    scaled by `contrast`."""
    h = jax.random.uniform(key, (size, size)) * grain_height
    tent = jnp.asarray([0.25, 0.5, 0.25], dtype=h.dtype)
    h = sum(w * jnp.roll(h, s, axis=0) for w, s in zip(tent, (-1, 0, 1)))
    h = sum(w * jnp.roll(h, s, axis=1) for w, s in zip(tent, (-1, 0, 1)))
    dx = (jnp.roll(h, -1, axis=1) - jnp.roll(h, 1, axis=1)) / 2.0
    dy = (jnp.roll(h, -1, axis=0) - jnp.roll(h, 1, axis=0)) / 2.0
    n = normalize(jnp.stack([-dx, -dy, jnp.ones_like(h)], axis=-1))
    l = normalize(jnp.asarray(light, dtype=h.dtype))
    shade = jnp.maximum(jnp.sum(n * jnp.reshape(l, (1, 1, 3)), axis=-1), 0.0)
    shade = shade / jnp.mean(shade)
    return 1.0 + contrast * (shade - 1.0)

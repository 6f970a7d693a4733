"""Ripple normal maps and their mip pyramid (paper 001 sections 3.2 and 3.3.2)."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ..maths import normalize
from ..textures import downsample2

__all__ = ["ripple_normal_map", "normal_pyramid"]


def ripple_normal_map(height: Float[ArrayLike, "H W"], *, texel_size: float = 1.0) -> Float[Array, "H W 3"]:
    """Unit normals of a periodic heightfield by central differences with periodic wrap.

    x runs along columns, y along rows, z up; `height` in the same length unit as `texel_size`:
    n = normalize(-dh/dx, -dh/dy, 1)."""
    h = jnp.asarray(height)
    dhdx = (jnp.roll(h, -1, axis=1) - jnp.roll(h, 1, axis=1)) / (2.0 * texel_size)
    dhdy = (jnp.roll(h, -1, axis=0) - jnp.roll(h, 1, axis=0)) / (2.0 * texel_size)
    return normalize(jnp.stack([-dhdx, -dhdy, jnp.ones_like(h)], axis=-1))


def normal_pyramid(normals: Float[ArrayLike, "H W 3"], *, levels: int = 4) -> tuple[Float[Array, "h w 3"], ...]:
    """Level 0 = `normals`; level l+1 = the average of 4 normals of level l, renormalized (the
    paper's 64 -> 32 -> 16 -> 8 per dune quad)."""
    pyramid = [jnp.asarray(normals)]
    for _ in range(levels - 1):
        pyramid.append(normalize(downsample2(pyramid[-1])))
    return tuple(pyramid)

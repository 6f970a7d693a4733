"""Micro relief of its own over a window of dune quads: the footprints of paper 001 Fig. 18.

Footprints are finer than the 64 x 64 dune grid and are not periodic like the ripple map, so
they live where the ripple detail lives, at ripple-texel resolution: a window of
`quads` = (nx, ny) dune quads starting at quad `origin` = (qi0, qj0) gets its own height field,
(ny texels) x (nx texels) texels, normally the ripples that window shows (`window_ripples`, the
same tiling `shade_quads` uses) with the prints pressed in (`sims.footprints`). `DetailMaps`
holds its normal pyramid, horizon maps and slope bands per level, exactly as `TerrainMaps` holds
the ripple map's, and `shade_quads` reads them instead of the ripple maps for the quads inside
the window: the prints are bump-mapped with the ripples' level of detail and cast horizon-map
shadows.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ..shadows import horizon_band, horizon_map
from ..textures import downsample2
from ._normals import normal_pyramid, ripple_normal_map

__all__ = ["DetailMaps", "build_detail_maps", "window_ripples"]


class DetailMaps(eqx.Module):
    """Per level l (n = texels / 2^l texels per quad): normals (ny n, nx n, 3), horizon slopes
    and slope bands (ny n, nx n, D) of the window of quads starting at `origin` (column, row)."""

    normals: tuple[Float[Array, "h w 3"], ...]
    horizon: tuple[Float[Array, "h w D"], ...]
    horizon_band: tuple[Float[Array, "h w D"], ...]
    origin: tuple[int, int] = eqx.field(static=True)
    quads: tuple[int, int] = eqx.field(static=True)


def window_ripples(ripple_z: Float[ArrayLike, "R R"], origin: tuple[int, int], quads: tuple[int, int], *,
                   texels: int) -> Float[Array, "Hd Wd"]:
    """The ripple heights the window of quads shows at level 0: quad (qi, qj) shows the ripple
    map from row qj texels, column qi texels on (wrapped), as `shade_quads` tiles it."""
    z = jnp.asarray(ripple_z)
    r = z.shape[0]
    (qi0, qj0), (nx, ny) = origin, quads
    rows = jnp.mod(qj0 * texels + jnp.arange(ny * texels), r)
    cols = jnp.mod(qi0 * texels + jnp.arange(nx * texels), r)
    return z[rows][:, cols]


def build_detail_maps(detail_z: Float[ArrayLike, "Hd Wd"], origin: tuple[int, int], *, spacing: float = 1.0,
                      texels: int = 64, levels: int = 4, directions: int = 8) -> DetailMaps:
    """The maps of a window's height field (world units, `texels` per dune quad of `spacing`).
    Its normals and horizons are computed as for a periodic field: keep the prints away from the
    window's border (the ripples it shows are periodic across it when its size is a multiple of
    the ripple map's period)."""
    z = jnp.asarray(detail_z)
    hd, wd = z.shape
    if hd % texels or wd % texels or texels % 2 ** (levels - 1):
        raise ValueError(f"detail field {z.shape} must be whole quads of {texels} texels, "
                         f"and {texels} a multiple of 2^(levels-1)")
    texel = spacing / texels
    normals = normal_pyramid(ripple_normal_map(z, texel_size=texel), levels=levels)
    hor = [jnp.moveaxis(horizon_map(z, directions=directions, texel_size=texel), 0, -1)]
    for _ in range(levels - 1):
        hor.append(downsample2(hor[-1]))
    band = tuple(jnp.moveaxis(horizon_band(jnp.moveaxis(h, -1, 0)), 0, -1) for h in hor)
    return DetailMaps(normals, tuple(hor), band, (int(origin[0]), int(origin[1])), (wd // texels, hd // texels))

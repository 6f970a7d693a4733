"""A trail of footprints across the showcase desert (paper 001 section 4 and Fig. 18, prints after
Sumner et al. 1998).

A walker crosses the dunes in front of the default camera: `trail_window` picks a window of dune
quads there, `footprint_detail` takes the ripples that window shows (`jaxrender.terrain.
window_ripples`), presses the prints of a gently curving walk into them and relaxes the sand to
its angle of repose (`sims.press_trail`), and builds the window's maps (normals, horizons per
ripple level: `jaxrender.terrain.build_detail_maps`), which `with_detail` hands to the renderer.
The prints therefore live at ripple-texel resolution, with the ripples' level of detail and
horizon-map shadows. Units: one dune quad = 1; a 0.28 x 0.10 foot sinking 0.03.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from jaxrender.terrain import DetailMaps, build_detail_maps, window_ripples
from sims import FootParams, press_trail, trail_steps

__all__ = ["trail_window", "trail_waypoints", "footprint_detail"]


def trail_window(n_quads: int) -> tuple[tuple[int, int], tuple[int, int]]:
    """(origin, size) in quads of the window the trail crosses: the foreground of the default
    camera (which looks from the field's southern edge toward +y, the image's lower edge about 10
    quads ahead), 12 x 6 quads of a 64-quad field."""
    origin = (round(0.36 * n_quads), round(0.16 * n_quads))
    size = (max(2, round(0.19 * n_quads)), max(2, round(0.09 * n_quads)))
    return origin, size


def trail_waypoints(origin: tuple[int, int], size: tuple[int, int]) -> Float[Array, "P 2"]:
    """A gently curving walk across the window, a quad in from its ends (window coordinates)."""
    nx, ny = size
    return jnp.asarray([[1.0, 0.70 * ny], [0.35 * nx, 0.45 * ny], [0.65 * nx, 0.40 * ny], [nx - 1.0, 0.20 * ny]])


@functools.partial(jax.jit, static_argnames=("origin", "size", "texels", "levels", "directions", "foot",
                                             "iterations"))
def _pressed(ripple_height: Array, centres: Array, headings: Array, *, origin, size, texels, levels, directions, foot,
             iterations) -> tuple[Array, DetailMaps]:
    relief = window_ripples(ripple_height, origin, size, texels=texels)
    pressed = press_trail(relief, centres, headings, foot, spacing=1.0 / texels, iterations=iterations)
    return pressed, build_detail_maps(pressed, origin, spacing=1.0, texels=texels, levels=levels,
                                      directions=directions)


def footprint_detail(ripple_height: Float[Array, "R R"], n_quads: int, *, texels: int = 64, levels: int = 4,
                     directions: int = 8, foot: FootParams = FootParams(), stride: float = 0.7, gait: float = 0.16,
                     iterations: int = 300) -> tuple[DetailMaps, Float[Array, "Hd Wd"]]:
    """The trail's detail maps for a desert of `n_quads` quads, and the pressed relief itself."""
    origin, size = trail_window(n_quads)
    centres, headings = trail_steps(trail_waypoints(origin, size), stride=stride, gait=gait)
    dtype = ripple_height.dtype
    pressed, detail = _pressed(ripple_height, centres.astype(dtype), headings.astype(dtype), origin=origin, size=size,
                               texels=texels, levels=levels, directions=directions, foot=foot, iterations=iterations)
    return detail, pressed

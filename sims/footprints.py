"""Footprints pressed into sand (paper 001 Fig. 18, after Sumner et al. 1998): `press_footprint`
sinks a sole and piles the sand on a rim, `relax_to_repose` slides it to the angle of repose,
`press_trail` presses and relaxes a walking trail; sand conserved to rounding, differentiable in
the heights. The two steps in detail: docs/desert.md.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

__all__ = ["FootParams", "sole_shape", "press_footprint", "relax_to_repose", "repose_excess", "trail_steps",
           "press_trail"]

TAN_REPOSE_SAND = math.tan(math.radians(34.0))  # dry sand's angle of repose, ~34 degrees


class FootParams(eqx.Module):
    """A foot: `length` and `width` of the sole, how deep it sinks (`depth`), the width of the
    rim that receives the displaced sand (`rim`), all in world units, and the tangent of the
    angle of repose. Defaults: a 28 x 10 cm shoe sinking 3 cm into dry sand."""

    length: float = eqx.field(static=True, default=0.28)
    width: float = eqx.field(static=True, default=0.10)
    depth: float = eqx.field(static=True, default=0.03)
    rim: float = eqx.field(static=True, default=0.05)
    tan_repose: float = eqx.field(static=True, default=TAN_REPOSE_SAND)


def _cell_centres(shape: tuple[int, int], spacing: float, dtype) -> tuple[Array, Array]:
    y, x = jnp.meshgrid((jnp.arange(shape[0], dtype=dtype) + 0.5) * spacing,
                        (jnp.arange(shape[1], dtype=dtype) + 0.5) * spacing, indexing="ij")
    return x, y


def sole_shape(x: Float[Array, "..."], y: Float[Array, "..."], centre: Float[ArrayLike, "2"],
               heading: Float[ArrayLike, ""], foot: FootParams) -> tuple[Float[Array, "..."], Float[Array, "..."]]:
    """(sole, rim) weights at points (x, y): `sole` in [0, 1] is how much of the print's depth the
    foot reaches there (1 on the flat of the sole, falling to 0 at its outline over the outer
    quarter), `rim` in [0, 1] the share of the ring around the outline (0 on the sole, peaking
    `rim` / 2 outside it). The sole is the union of a heel and a forefoot ellipse."""
    centre = jnp.asarray(centre, x.dtype)
    heading = jnp.asarray(heading, x.dtype)
    dx, dy = x - centre[0], y - centre[1]
    along = dx * jnp.cos(heading) + dy * jnp.sin(heading)
    across = -dx * jnp.sin(heading) + dy * jnp.cos(heading)
    length, width = foot.length, foot.width
    # normalised elliptic radius of each part (1 on its outline)
    heel = jnp.sqrt(((along + 0.26 * length) / (0.24 * length)) ** 2 + (across / (0.40 * width)) ** 2)
    ball = jnp.sqrt(((along - 0.14 * length) / (0.36 * length)) ** 2 + (across / (0.50 * width)) ** 2)
    rho = jnp.minimum(heel, ball)
    sole = jnp.clip((1.0 - rho) / 0.25, 0.0, 1.0)
    ring = foot.rim / (0.45 * width)  # the rim's width in units of rho (across the foot)
    rim = jnp.clip(1.0 - jnp.abs(rho - 1.0 - 0.5 * ring) / (0.5 * ring), 0.0, 1.0)
    return sole, rim


def press_footprint(height: Float[Array, "H W"], centre: Float[ArrayLike, "2"], heading: Float[ArrayLike, ""],
                    foot: FootParams = FootParams(), *, spacing: float = 1.0) -> Float[Array, "H W"]:
    """Press one foot at `centre` (x, y in world units from the field's corner), pointing along
    `heading` (radians from +x toward +y), and put the sand it displaces on the rim."""
    x, y = _cell_centres(height.shape, spacing, height.dtype)
    sole, rim = sole_shape(x, y, centre, heading, foot)
    on_sole = sole > 0
    # the foot sinks `depth` below the mean sand height under it (it follows the local surface)
    mean = jnp.sum(jnp.where(on_sole, height, 0.0)) / jnp.maximum(jnp.sum(on_sole.astype(height.dtype)), 1.0)
    bottom = mean - foot.depth * sole
    pressed = jnp.where(on_sole, jnp.minimum(height, bottom), height)
    removed = jnp.sum(height - pressed)
    share = rim / jnp.maximum(jnp.sum(rim), jnp.finfo(height.dtype).tiny)
    return pressed + removed * share


def _pair_flux(a: Array, b: Array, limit: Array, rate: Array) -> Array:
    """Sand moved from a to b (negative: b to a): `rate` times the height difference beyond the
    repose limit."""
    diff = a - b
    excess = jnp.sign(diff) * jnp.maximum(jnp.abs(diff) - limit, 0.0)
    return rate * excess


def _relax_step(h: Array, edge_limit: Array, diag_limit: Array, rate: Array) -> Array:
    east = _pair_flux(h[:, :-1], h[:, 1:], edge_limit, rate)         # (H, W-1): from (i, j) to (i, j+1)
    south = _pair_flux(h[:-1, :], h[1:, :], edge_limit, rate)        # (H-1, W): from (i, j) to (i+1, j)
    south_east = _pair_flux(h[:-1, :-1], h[1:, 1:], diag_limit, rate)  # (H-1, W-1)
    south_west = _pair_flux(h[:-1, 1:], h[1:, :-1], diag_limit, rate)  # (H-1, W-1): from (i, j+1) to (i+1, j)
    zero_col = jnp.zeros((h.shape[0], 1), h.dtype)
    zero_row = jnp.zeros((1, h.shape[1]), h.dtype)
    zero_col1 = jnp.zeros((h.shape[0] - 1, 1), h.dtype)
    out_e = jnp.concatenate([east, zero_col], axis=1)
    in_e = jnp.concatenate([zero_col, east], axis=1)
    out_s = jnp.concatenate([south, zero_row], axis=0)
    in_s = jnp.concatenate([zero_row, south], axis=0)
    se = jnp.concatenate([south_east, zero_col1], axis=1)
    out_se = jnp.concatenate([se, zero_row], axis=0)
    in_se = jnp.concatenate([zero_row, jnp.concatenate([zero_col1, south_east], axis=1)], axis=0)
    out_sw = jnp.concatenate([jnp.concatenate([zero_col1, south_west], axis=1), zero_row], axis=0)
    in_sw = jnp.concatenate([zero_row, jnp.concatenate([south_west, zero_col1], axis=1)], axis=0)
    return h + ((in_e - out_e) + (in_s - out_s)) + ((in_se - out_se) + (in_sw - out_sw))


def relax_to_repose(height: Float[Array, "H W"], *, spacing: float = 1.0, tan_repose: float = TAN_REPOSE_SAND,
                    iterations: int = 200, rate: float = 0.1) -> Float[Array, "H W"]:
    """`iterations` synchronous slides toward the angle of repose (module docstring): each pair of
    neighbours whose height difference exceeds `tan_repose` times their distance exchanges `rate`
    times the excess. With 8 neighbours per column, `rate` <= 1/8 keeps a column from giving more
    than its excess (no overshoot)."""
    dtype = height.dtype
    edge_limit = jnp.asarray(tan_repose * spacing, dtype)
    diag_limit = jnp.asarray(tan_repose * spacing * math.sqrt(2.0), dtype)
    r = jnp.asarray(rate, dtype)
    return jax.lax.fori_loop(0, iterations, lambda _, h: _relax_step(h, edge_limit, diag_limit, r), height)


def repose_excess(height: Float[Array, "H W"], *, spacing: float = 1.0,
                  tan_repose: float = TAN_REPOSE_SAND) -> Float[Array, ""]:
    """The largest slope between neighbours (edge and diagonal) beyond `tan_repose` (<= 0 when
    the field is everywhere at or below the angle of repose)."""
    h = height
    edge = jnp.maximum(jnp.max(jnp.abs(h[:, 1:] - h[:, :-1])), jnp.max(jnp.abs(h[1:, :] - h[:-1, :]))) / spacing
    diag = jnp.maximum(jnp.max(jnp.abs(h[1:, 1:] - h[:-1, :-1])), jnp.max(jnp.abs(h[1:, :-1] - h[:-1, 1:])))
    return jnp.maximum(edge, diag / (spacing * math.sqrt(2.0))) - tan_repose


def trail_steps(waypoints: Float[ArrayLike, "P 2"], *, stride: float = 0.7, gait: float = 0.16,
                first: float | None = None) -> tuple[Float[Array, "K 2"], Float[Array, " K"]]:
    """Footprint centres and headings of a walk along the polyline `waypoints`: one print every
    `stride` / 2 of arc length (starting `first` in, default a quarter stride), alternately left
    and right of the path by `gait` / 2, each pointing along the path."""
    p = jnp.asarray(waypoints)
    seg = p[1:] - p[:-1]
    seg_len = jnp.sqrt(jnp.sum(seg * seg, -1))
    arc = jnp.concatenate([jnp.zeros((1,), p.dtype), jnp.cumsum(seg_len)])
    total = float(arc[-1])
    start = 0.25 * stride if first is None else first
    count = int(math.floor((total - start) / (0.5 * stride))) + 1
    s = start + 0.5 * stride * jnp.arange(count, dtype=p.dtype)
    x = jnp.interp(s, arc, p[:, 0])
    y = jnp.interp(s, arc, p[:, 1])
    k = jnp.clip(jnp.searchsorted(arc, s, side="right") - 1, 0, seg.shape[0] - 1)
    heading = jnp.arctan2(seg[k, 1], seg[k, 0])
    side = jnp.where(jnp.arange(count) % 2 == 0, 1.0, -1.0).astype(p.dtype)  # left foot first
    normal = jnp.stack([-jnp.sin(heading), jnp.cos(heading)], -1)
    centres = jnp.stack([x, y], -1) + (0.5 * gait * side)[:, None] * normal
    return centres, heading


def press_trail(height: Float[Array, "H W"], centres: Float[Array, "K 2"], headings: Float[Array, " K"],
                foot: FootParams = FootParams(), *, spacing: float = 1.0, iterations: int = 200,
                rate: float = 0.1) -> Float[Array, "H W"]:
    """Press every print in order (a later print overlapping an earlier one presses into it),
    then relax the field to the angle of repose."""

    def press(h, step):
        centre, heading = step
        return press_footprint(h, centre, heading, foot, spacing=spacing), None

    pressed, _ = jax.lax.scan(press, height, (centres.astype(height.dtype), headings.astype(height.dtype)))
    return relax_to_repose(pressed, spacing=spacing, tan_repose=foot.tan_repose, iterations=iterations, rate=rate)

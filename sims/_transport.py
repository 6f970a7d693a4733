"""Sand transport shared by the ripple and dune automata (paper 001 eqs. 1-4, Nishimori-Ouchi):
saltation (`deposit`: every cell sends an amount a hop downwind, one scatter-add; hop modes
"split" (differentiable) and "nearest" (the paper)) and creep (isotropic smoothing), on periodic
`(..., H, W)` fields with sand conserved bit for bit on a fixed-point grid (`sand_quantum`).
Conventions, the scatter's design and the conservation argument: docs/desert.md.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Float

HOP_MODES = ("split", "nearest")


def wind_vector(wind_deg: float) -> tuple[float, float]:
    """Unit wind vector (cx, cy) in cells for a static direction; components below 1e-9 snap
    to 0, so that an axis-aligned wind hops along one axis only."""
    angle = math.radians(float(wind_deg))
    snap = lambda c: 0.0 if abs(c) < 1e-9 else c  # noqa: E731
    return snap(math.cos(angle)), snap(math.sin(angle))


HEADROOM_BITS = 1  # sums up to 2x the largest |height| or amount stay on the grid exactly


def sand_quantum(field: Float[Array, "... H W"], amount: ArrayLike = 0.0) -> Float[Array, "... 1 1"]:
    """The power of two on whose multiples sand moves, per field (`(..., 1, 1)`): the float's last
    bit for a value 2^HEADROOM_BITS times above the largest |height| or |amount|, so sums of
    heights and of what moves stay exact (no gradient: it is piecewise constant)."""
    field = lax.stop_gradient(jnp.asarray(field))
    amount = lax.stop_gradient(jnp.broadcast_to(jnp.asarray(amount, field.dtype), field.shape))
    scale = jnp.maximum(jnp.max(jnp.abs(field), axis=(-2, -1), keepdims=True),
                        jnp.max(jnp.abs(amount), axis=(-2, -1), keepdims=True))
    _, exponent = jnp.frexp(scale)  # scale < 2^exponent
    digits = jnp.finfo(field.dtype).nmant + 1  # 24 in float32, 53 in float64
    return jnp.ldexp(jnp.ones_like(scale), exponent + HEADROOM_BITS - digits)


@jax.custom_jvp
def to_grid(x: Array, quantum: Array) -> Array:
    """x rounded to the nearest multiple of the power of two `quantum` (x / quantum and the product
    are exact). Tangent: the identity in x, so derivatives are those of the unrounded update."""
    return jnp.round(x / quantum) * quantum


@to_grid.defjvp
def _to_grid_jvp(primals, tangents):
    x, quantum = primals
    return to_grid(x, quantum), jnp.broadcast_to(tangents[0], x.shape)


def _base_and_shares(amount: Array, h: Array, mode: str, quantum: Array) -> tuple[Array, tuple[Array, ...]]:
    """Integer offset of the first receiving cell and the shares of `amount` (on the grid) sent to
    the window that starts there: split gives far = amount f on the grid and near = amount - far,
    so near + far == amount exactly."""
    if mode == "split":
        base = jnp.floor(h)
        far = to_grid(amount * (h - base), quantum)
        return base.astype(jnp.int32), (amount - far, far)
    if mode == "nearest":
        return jnp.round(h).astype(jnp.int32), (amount,)
    raise ValueError(f"unknown hop mode {mode!r}: use one of {HOP_MODES}")


def deposit(amount: Float[Array, "... H W"], hop_x: Float[Array, "... H W"] | None,
            hop_y: Float[Array, "... H W"] | None, *, mode: str = "split",
            quantum: Float[Array, "... 1 1"] | None = None) -> Float[Array, "... H W"]:
    """Sand received by every cell when each cell sends `amount` a hop (hop_x, hop_y) in cells
    (`None` = no hop along that axis, a static choice that keeps the window small).

    Per axis the hop end falls between two cells: `split` gives them 1 - f and f (bilinear over
    4 cells for an off-axis hop), `nearest` gives everything to the nearest one. A hop along one
    axis is one window-1 scatter-add (`_deposit_one_axis`); an off-axis hop is one windowed
    scatter-add into a field padded by one row/column, whose padding is then folded back
    (periodic wrap). Amounts and shares are multiples of `quantum` (default `sand_quantum` of
    the amounts; `amount` is rounded to it), so the total received equals the total sent exactly.
    """
    if mode not in HOP_MODES:
        raise ValueError(f"unknown hop mode {mode!r}: use one of {HOP_MODES}")
    amount = jnp.asarray(amount)
    if quantum is None:
        quantum = sand_quantum(amount)
    amount = to_grid(amount, quantum)
    if (hop_x is None) != (hop_y is None):
        return _deposit_one_axis(amount, hop_x if hop_y is None else hop_y, axis=-1 if hop_y is None else -2,
                                 mode=mode, quantum=quantum)
    shape = amount.shape
    height, width = shape[-2], shape[-1]
    amount = amount.reshape((-1, height, width))
    quantum = jnp.broadcast_to(quantum, shape[:-2] + (1, 1)).reshape((-1, 1, 1))
    n_fields = amount.shape[0]
    rows = jnp.broadcast_to(jnp.arange(height, dtype=jnp.int32)[None, :, None], amount.shape)
    cols = jnp.broadcast_to(jnp.arange(width, dtype=jnp.int32)[None, None, :], amount.shape)
    # shares along y first (an exact split of the amount), then each split along x (exact again):
    # the window's shares sum to the amount sent, bit for bit
    if hop_y is not None:
        base_y, by_row = _base_and_shares(amount, jnp.asarray(hop_y).reshape(amount.shape), mode, quantum)
        rows = jnp.mod(rows + base_y, height)
    else:
        by_row = (amount,)
    if hop_x is not None:
        hop_x = jnp.asarray(hop_x).reshape(amount.shape)
        shares = [_base_and_shares(row_share, hop_x, mode, quantum) for row_share in by_row]
        base_x = shares[0][0]
        cols = jnp.mod(cols + base_x, width)
        shares = [s for _, s in shares]
    else:
        shares = [(row_share,) for row_share in by_row]
    ny, nx = len(shares), len(shares[0])
    rows_p, cols_p = height + ny - 1, width + nx - 1  # padded by one row/column per split axis
    # updates: (N, ny, nx) window shares
    updates = jnp.stack([jnp.stack(row, axis=-1) for row in shares], axis=-2)
    field_row = rows + rows_p * jnp.arange(n_fields, dtype=jnp.int32)[:, None, None]
    if ny == 1:
        # one row per update: a flat operand and a 1-component index are fastest on CPU
        index = (field_row * cols_p + cols).reshape((-1, 1))
        padded = jnp.zeros((n_fields * rows_p * cols_p + nx - 1,), amount.dtype)
        numbers = lax.ScatterDimensionNumbers(update_window_dims=(1,), inserted_window_dims=(),
                                              scatter_dims_to_operand_dims=(0,))
        padded = lax.scatter_add(padded, index, updates.reshape((-1, nx)), numbers,
                                 mode=lax.GatherScatterMode.PROMISE_IN_BOUNDS)
        padded = padded[: n_fields * rows_p * cols_p]
    else:
        index = jnp.stack([field_row.reshape(-1), cols.reshape(-1)], axis=-1)
        padded = jnp.zeros((n_fields * rows_p, cols_p), amount.dtype)
        numbers = lax.ScatterDimensionNumbers(update_window_dims=(1, 2), inserted_window_dims=(),
                                              scatter_dims_to_operand_dims=(0, 1))
        padded = lax.scatter_add(padded, index, updates.reshape((-1, ny, nx)), numbers,
                                 mode=lax.GatherScatterMode.PROMISE_IN_BOUNDS)
    padded = padded.reshape((n_fields, rows_p, cols_p))
    # fold the padding back (periodic wrap) with broadcasts and `where`, which XLA fuses into
    # the following elementwise pass (`.at[].add` would be a separate scatter)
    out = padded[:, :height, :width]
    if nx == 2:
        first_col = (jnp.arange(width) == 0)[None, None, :]
        out = out + jnp.where(first_col, padded[:, :height, width:], 0.0)
    if ny == 2:
        first_row = (jnp.arange(height) == 0)[None, :, None]
        wrapped = padded[:, height:, :width]
        if nx == 2:
            wrapped = wrapped + jnp.where(first_col, padded[:, height:, width:], 0.0)
        out = out + jnp.where(first_row, wrapped, 0.0)
    return out.reshape(shape)


def _deposit_one_axis(amount: Array, hop: Array, *, axis: int, mode: str, quantum: Array) -> Array:
    """`deposit` for a hop along one grid axis (`axis` = -1: x, -2: y), the axis-aligned wind.

    One window-1 scatter-add with no padding: the sending cell's index along the hop axis is
    shifted by the integer part of the hop and wrapped (periodic). For the split hop the two
    shares travel as one complex number, (1 - f) + i f, scattered to the first receiving cell;
    the imaginary (far) share is then rolled one cell along the hop, which is its periodic wrap.
    A window-1 scatter of one complex value is cheaper on CPU than a window-2 scatter of two
    reals, and it needs no padded operand to fold back.
    """
    shape = amount.shape
    n = shape[axis]
    base, shares = _base_and_shares(amount, jnp.asarray(hop).reshape(shape), mode, quantum)
    pos = jnp.arange(n, dtype=jnp.int32)
    pos = pos[:, None] if axis == -2 else pos[None, :]
    pos = jnp.broadcast_to(pos.reshape((1,) * (len(shape) - 2) + pos.shape), shape)
    target = jnp.mod(pos + base, n)
    # flat index: the source cell's own index with its hop-axis coordinate replaced by the target
    stride = shape[-1] if axis == -2 else 1
    flat_self = jnp.arange(math.prod(shape), dtype=jnp.int32).reshape(shape)
    index = (flat_self + (target - pos) * stride).reshape(-1)
    if mode == "nearest":
        updates = shares[0].reshape(-1)
        return jnp.zeros(updates.shape, amount.dtype).at[index].add(
            updates, mode="promise_in_bounds").reshape(shape)
    updates = lax.complex(*shares).reshape(-1)
    received = jnp.zeros(updates.shape, updates.dtype).at[index].add(updates, mode="promise_in_bounds")
    received = received.reshape(shape)
    return jnp.real(received) + jnp.roll(jnp.imag(received), 1, axis=axis)


def saltate(field: Float[Array, "... H W"], amount: Float[Array, "... H W"], hop_x: Float[Array, "... H W"] | None,
            hop_y: Float[Array, "... H W"] | None, *, mode: str = "split",
            quantum: Float[Array, "... 1 1"] | None = None) -> Float[Array, "... H W"]:
    """Eqs. 1-2: every cell loses `amount`, which lands a hop (hop_x, hop_y) downwind.
    All cells move from the same state (synchronous update). Field and amount are rounded to
    the sand grid `quantum` (default `sand_quantum(field, amount)`), so the total is unchanged
    exactly."""
    field = jnp.asarray(field)
    if quantum is None:
        quantum = sand_quantum(field, amount)
    field = to_grid(field, quantum)
    amount = to_grid(jnp.broadcast_to(jnp.asarray(amount, field.dtype), field.shape), quantum)
    return field - amount + deposit(amount, hop_x, hop_y, mode=mode, quantum=quantum)


def creep(field: Float[Array, "... H W"], D: ArrayLike, *,
          quantum: Float[Array, "... 1 1"] | None = None) -> Float[Array, "... H W"]:
    """Eq. 4: H + D [1/6 sum of the 4 nearest + 1/12 sum of the 4 diagonal - H], periodic.

    Written as fluxes between neighbours, so that the total is conserved exactly: every pair of
    neighbours exchanges one computed amount, w D (H_b - H_a) (w = 1/6 across an edge, 1/12 across
    a corner) rounded to the sand grid `quantum` (default `sand_quantum(field)`), added to one
    cell and subtracted from the other. (The stencil form H + D (conv(H) - H) gains sand whenever
    the rounded weights do not sum to 1, in float32 4/6 + 4/12 = 1 + 3e-8, i.e. 2.4e-8 of the total
    per step at D = 0.8, and rounds what leaves a cell apart from what arrives.) Each flux field
    is the difference of neighbouring slices of the periodically padded field, one fused pass.
    """
    field = jnp.asarray(field)
    dtype = field.dtype
    D = jnp.asarray(D, dtype)
    if quantum is None:
        quantum = sand_quantum(field)
    field = to_grid(field, quantum)
    side, corner = D / 6.0, D / 12.0
    pad = [(0, 0)] * (field.ndim - 2) + [(1, 1), (1, 1)]
    p = jnp.pad(field, pad, mode="wrap")  # (H + 2, W + 2); p[i + 1, j + 1] = H[i, j]
    # flux into the earlier cell of each pair, over every pair touching the H x W interior
    east = to_grid(side * (p[..., 1:-1, 1:] - p[..., 1:-1, :-1]), quantum)  # (H, W + 1): (i, j) -> (i, j - 1)
    south = to_grid(side * (p[..., 1:, 1:-1] - p[..., :-1, 1:-1]), quantum)  # (H + 1, W): (i, j) -> (i - 1, j)
    south_east = to_grid(corner * (p[..., 1:, 1:] - p[..., :-1, :-1]), quantum)  # (H + 1, W + 1)
    south_west = to_grid(corner * (p[..., 1:, :-1] - p[..., :-1, 1:]), quantum)  # (H + 1, W + 1)
    edges = (east[..., :, 1:] - east[..., :, :-1]) + (south[..., 1:, :] - south[..., :-1, :])
    corners = ((south_east[..., 1:, 1:] - south_east[..., :-1, :-1])
               + (south_west[..., 1:, :-1] - south_west[..., :-1, 1:]))
    return field + (edges + corners)


def directional_slope(field: Float[Array, "... H W"], cx: float, cy: float) -> Float[Array, "... H W"]:
    """Slope along the wind by central differences: cx dH/dx + cy dH/dy (periodic)."""
    slope = jnp.zeros_like(field)
    if cx != 0.0:
        slope = slope + cx * 0.5 * (jnp.roll(field, -1, axis=-1) - jnp.roll(field, 1, axis=-1))
    if cy != 0.0:
        slope = slope + cy * 0.5 * (jnp.roll(field, -1, axis=-2) - jnp.roll(field, 1, axis=-2))
    return slope


def hop_components(hop: Array, cx: float, cy: float) -> tuple[Array | None, Array | None]:
    """Hop length along the (static) wind split into x and y; `None` for an axis it does not use."""
    return (cx * hop if cx != 0.0 else None), (cy * hop if cy != 0.0 else None)


def random_field(key: Array, shape: tuple[int, ...], *, low: float, high: float, dtype=None) -> Array:
    """Uniform random heights in [low, high); `shape` may carry leading batch axes."""
    dtype = dtype or jnp.result_type(float)
    if len(shape) < 2:
        raise ValueError(f"a field needs at least 2 axes (..., H, W), got shape {shape}")
    return jax.random.uniform(key, shape, dtype=dtype, minval=low, maxval=high)

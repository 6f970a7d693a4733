"""Dunes: the Nishimori-Ouchi automaton with slope-dependent saltation (paper 001 eqs. 5-6).

One step, all cells from the same state (synchronous):
1. slope s = dH/ds along the wind by central differences (periodic);
2. saltation: q = clip(q0 + b' tanh(s), 0, H) leaves every cell (eq. 5; clamped because eq. 5
   goes negative on steep lee slopes and no cell gives sand it does not have), and lands
   L = L0 - b tanh(s) cells downwind (eq. 6): windward faces (s > 0) send more sand a shorter way;
3. creep (eq. 4), as for ripples.
Grid, wind and hop conventions, and the exact conservation of sand: `sims._transport` (the one
hop and creep implementation shared with `sims.ripples`).

Example::

    h0 = init_dunes(jax.random.key(0), (64, 64))
    h = simulate_dunes(h0, DuneParams(wind_deg=30.0), steps=2000)
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Float

from ._transport import (
    HOP_MODES,
    creep,
    directional_slope,
    hop_components,
    random_field,
    saltate,
    sand_quantum,
    wind_vector,
)


class DuneParams(eqx.Module):
    """Parameters of the dune automaton; paper defaults (L0 = 7.0, q0 = 1.5, b = 2.0, b' = 2.0;
    creep D = 0.8 as for ripples). `hop` and `wind_deg` (degrees from +x toward +y) are static."""

    L0: Float[ArrayLike, ""] = 7.0
    q0: Float[ArrayLike, ""] = 1.5
    b: Float[ArrayLike, ""] = 2.0
    b_prime: Float[ArrayLike, ""] = 2.0
    D: Float[ArrayLike, ""] = 0.8
    wind_deg: float = eqx.field(static=True, default=0.0)
    hop: str = eqx.field(static=True, default="split")

    def __check_init__(self):
        if self.hop not in HOP_MODES:
            raise ValueError(f"unknown hop mode {self.hop!r}: use one of {HOP_MODES}")


def dune_transport(field: Float[Array, "... H W"], params: DuneParams = DuneParams()
                   ) -> tuple[Float[Array, "... H W"], Float[Array, "... H W"]]:
    """Eqs. 5-6: the amount each cell sends (clamped to [0, H]) and its hop length."""
    dtype = field.dtype
    cx, cy = wind_vector(params.wind_deg)
    t = jnp.tanh(directional_slope(field, cx, cy))
    amount = jnp.asarray(params.q0, dtype) + jnp.asarray(params.b_prime, dtype) * t
    amount = jnp.clip(amount, 0.0, jnp.maximum(field, 0.0))
    hop = jnp.asarray(params.L0, dtype) - jnp.asarray(params.b, dtype) * t
    return amount, hop


def dune_step(field: Float[Array, "... H W"], params: DuneParams = DuneParams()) -> Float[Array, "... H W"]:
    """One synchronous step (slope-dependent saltation, then creep) of a field or a batch."""
    field = jnp.asarray(field)
    cx, cy = wind_vector(params.wind_deg)
    amount, hop = dune_transport(field, params)
    hop_x, hop_y = hop_components(hop, cx, cy)
    quantum = sand_quantum(field, amount)  # one sand grid for the whole step: the total is exact
    field = saltate(field, amount, hop_x, hop_y, mode=params.hop, quantum=quantum)
    return creep(field, jnp.asarray(params.D, field.dtype), quantum=quantum)


@functools.partial(jax.jit, static_argnames=("steps",))
def simulate_dunes(field: Float[Array, "... H W"], params: DuneParams = DuneParams(), *,
                   steps: int) -> Float[Array, "... H W"]:
    """`steps` steps as one jitted `lax.scan`; leading axes are a batch of independent fields."""
    field = jnp.asarray(field)
    if not jnp.issubdtype(field.dtype, jnp.floating):
        field = field.astype(jnp.result_type(float))
    out, _ = lax.scan(lambda h, _: (dune_step(h, params), None), field, None, length=steps)
    return out


def init_dunes(key: Array, shape: tuple[int, ...], *, low: float = 2.0, high: float = 4.0,
               dtype=None) -> Float[Array, "... H W"]:
    """Initial sand depth, uniform in [low, high); `shape` is (H, W) or (batch..., H, W)."""
    return random_field(key, tuple(shape), low=low, high=high, dtype=dtype)

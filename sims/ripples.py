"""Wind ripples: the Nishimori-Ouchi saltation + creep automaton (paper 001 eqs. 1-4), synchronous
steps on periodic fields, sand conserved exactly, differentiable in L0, b, q with the split hop.
How long runs behave under differentiation, and an example: docs/desert.md.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Float

from ._transport import HOP_MODES, creep, hop_components, random_field, saltate, sand_quantum, wind_vector


class RippleParams(eqx.Module):
    """Parameters of the ripple automaton; paper defaults (L0 = 7.3, q = 0.6, b = 2.0; D = 0.8,
    which the paper does not give). Numeric fields are pytree leaves (traceable, differentiable
    in either mode); `hop` and `wind_deg` (degrees from +x toward +y) are static."""

    L0: Float[ArrayLike, ""] = 7.3
    q: Float[ArrayLike, ""] = 0.6
    b: Float[ArrayLike, ""] = 2.0
    D: Float[ArrayLike, ""] = 0.8
    wind_deg: float = eqx.field(static=True, default=0.0)
    hop: str = eqx.field(static=True, default="split")

    def __check_init__(self):
        if self.hop not in HOP_MODES:
            raise ValueError(f"unknown hop mode {self.hop!r}: use one of {HOP_MODES}")


def ripple_step(field: Float[Array, "... H W"], params: RippleParams = RippleParams()) -> Float[Array, "... H W"]:
    """One synchronous step (saltation then creep) of one field or a batch `(..., H, W)`."""
    field = jnp.asarray(field)
    dtype = field.dtype
    cx, cy = wind_vector(params.wind_deg)
    hop = jnp.asarray(params.L0, dtype) + jnp.asarray(params.b, dtype) * field
    amount = jnp.broadcast_to(jnp.asarray(params.q, dtype), field.shape)
    hop_x, hop_y = hop_components(hop, cx, cy)
    quantum = sand_quantum(field, amount)  # one sand grid for the whole step: the total is exact
    field = saltate(field, amount, hop_x, hop_y, mode=params.hop, quantum=quantum)
    return creep(field, jnp.asarray(params.D, dtype), quantum=quantum)


@functools.partial(jax.jit, static_argnames=("steps",))
def simulate_ripples(field: Float[Array, "... H W"], params: RippleParams = RippleParams(), *,
                     steps: int) -> Float[Array, "... H W"]:
    """`steps` steps of the automaton as one jitted `lax.scan`; leading axes are a batch of
    independent fields (also fine under `jax.vmap`)."""
    field = jnp.asarray(field)
    if not jnp.issubdtype(field.dtype, jnp.floating):
        field = field.astype(jnp.result_type(float))
    out, _ = lax.scan(lambda h, _: (ripple_step(h, params), None), field, None, length=steps)
    return out


def init_ripples(key: Array, shape: tuple[int, ...], *, low: float = 1.0, high: float = 1.5,
                 dtype=None) -> Float[Array, "... H W"]:
    """Initial heights, uniform in [low, high); `shape` is (H, W) or
    (batch..., H, W)."""
    return random_field(key, tuple(shape), low=low, high=high, dtype=dtype)


def power_spectrum_along(field: Float[Array, "... H W"], *, axis: int = -1) -> Float[Array, "... K"]:
    """Power spectrum along one grid axis (FFT of each line, mean removed), averaged over the
    lines and any batch axes except the leading ones; index k is k cycles per grid length."""
    field = jnp.asarray(field)
    other = -2 if axis in (-1, field.ndim - 1) else -1
    centred = field - jnp.mean(field, axis=(-2, -1), keepdims=True)
    power = jnp.abs(jnp.fft.rfft(centred, axis=axis)) ** 2
    return jnp.mean(power, axis=other)


def dominant_wavelength(field: Float[Array, "... H W"], *, axis: int = -1) -> Float[Array, "..."]:
    """Wavelength (cells) of the strongest Fourier mode along `axis` (x = -1, the default wind
    axis), refined by a parabola through the log power around the peak. Piecewise constant in
    the field's parameters: differentiate `spectral_centroid_wavelength` instead."""
    field = jnp.asarray(field)
    n = field.shape[axis]
    power = power_spectrum_along(field, axis=axis)
    k = jnp.argmax(power[..., 1:], axis=-1) + 1
    logp = jnp.log(power + jnp.finfo(power.dtype).tiny)
    take = lambda i: jnp.take_along_axis(logp, jnp.clip(i, 1, power.shape[-1] - 1)[..., None], axis=-1)[..., 0]  # noqa: E731
    left, mid, right = take(k - 1), take(k), take(k + 1)
    denom = left - 2.0 * mid + right
    shift = jnp.where(jnp.abs(denom) > 1e-12, 0.5 * (left - right) / jnp.where(jnp.abs(denom) > 1e-12, denom, 1.0), 0.0)
    shift = jnp.clip(shift, -0.5, 0.5)
    return n / (k.astype(power.dtype) + shift)


def spectral_centroid_wavelength(field: Float[Array, "... H W"], *, axis: int = -1, power_exponent: float = 2.0
                                 ) -> Float[Array, "..."]:
    """n / (power-weighted mean wavenumber) along `axis`, weights |F|^(2 p) with p = power_exponent
    (a larger p concentrates the weight on the peak): a smooth wavelength estimate with a gradient."""
    field = jnp.asarray(field)
    n = field.shape[axis]
    power = power_spectrum_along(field, axis=axis)[..., 1:]
    weights = power ** power_exponent
    k = jnp.arange(1, power.shape[-1] + 1, dtype=power.dtype)
    k_mean = jnp.sum(weights * k, axis=-1) / jnp.sum(weights, axis=-1)
    return n / k_mean

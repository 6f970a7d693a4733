"""Wind ripples: the Nishimori-Ouchi saltation + creep automaton (paper 001 eqs. 1-4).

One step, all cells from the same state (synchronous):
1. saltation (eqs. 1-3): every cell loses `q`, which lands L = L0 + b H cells downwind;
2. creep (eq. 4): H + D [1/6 sum_NN H + 1/12 sum_NNN H - H].
Periodic boundaries; H is the absolute height (sand depth). Grid and wind conventions, and the
hop modes ``"split"`` (default, differentiable in L0, b, q) and ``"nearest"`` (the paper), are
described in `sims._transport`.
Sand is conserved exactly, in float32 too: what leaves a cell is what arrives elsewhere, bit for
bit, on a fixed-point grid (`sims._transport`; 10,000 float32 steps of `sims ripples` at 128x128,
L0 = 9 change the total by 2.4e-8, from rounding onto a coarser grid as the ripples grow).

Derivatives: the split hop makes a run piecewise linear in L0, b, q, so `jax.grad` and
`jax.jvp` agree with central differences over a few steps (tests/test_ripples.py). The automaton
is chaotic, though: the pathwise derivative of a long run grows exponentially with the number of
steps (d spectral-centroid wavelength / d L0 on 32x64 from the same initial field: -1.8 after
100 steps, -660 after 300, 2e13 after 1000), while the wavelength itself is a smooth
statistical function of L0 (benchmarks/ripples_wavelength.py). Differentiate short runs, or
average over many initial fields and small perturbations, rather than one long run.

Example::

    key = jax.random.key(0)
    h0 = init_ripples(key, (128, 128))                  # heights uniform in [1.0, 1.5)
    h = simulate_ripples(h0, RippleParams(), steps=3000)
    hs = simulate_ripples(init_ripples(key, (4, 64, 64)), RippleParams(L0=5.0), steps=500)  # a batch
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
    """Initial heights, uniform in [low, high) (the issue's 1.0-1.5); `shape` is (H, W) or
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

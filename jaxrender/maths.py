"""Maths shared by every kernel: gradient-safe vector operations (no NaN gradients at zero length),
fast vectorizable arctan, short-axis sums, and the default float dtype."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float


def default_float() -> jnp.dtype:
    """float32, or float64 when `jax_enable_x64` is on: the dtype kernels create arrays in."""
    return jnp.dtype(jnp.float64 if jax.config.jax_enable_x64 else jnp.float32)


def safe_norm(x: Float[ArrayLike, "... 3"], *, eps: float = 1e-12) -> Float[Array, "..."]:
    """Euclidean norm whose gradient at 0 is 0 instead of NaN."""
    x = jnp.asarray(x)
    sq = dot(x, x)
    positive = sq > eps * eps
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def normalize(x: Float[ArrayLike, "... 3"], *, eps: float = 1e-12) -> Float[Array, "... 3"]:
    """x / |x|, with 0 (and a finite gradient) for a zero vector."""
    x = jnp.asarray(x)
    n = safe_norm(x, eps=eps)
    return x / jnp.where(n > 0, n, 1.0)[..., None]


def safe_div(a: ArrayLike, b: ArrayLike, *, eps: float = 1e-12) -> Array:
    """a / b with b pushed away from 0 (keeping its sign); finite value and gradient."""
    b = jnp.asarray(b)
    return jnp.asarray(a) / jnp.where(jnp.abs(b) > eps, b, jnp.where(b < 0, -eps, eps))


def dot(a: Float[ArrayLike, "... D"], b: Float[ArrayLike, "... D"]) -> Float[Array, "..."]:
    a, b = jnp.asarray(a), jnp.asarray(b)
    if a.shape[-1:] == b.shape[-1:] and a.shape[-1] in (2, 3):
        # Written out: XLA on CPU vectorizes this elementwise form, while a reduction over a
        # minor axis of length 3 runs ~10-100x slower (measured on the BRDF and its Jacobian;
        # length 2, the spot light's |w.xy|: the five-spot stage's surface pass 0.092 -> 0.084 s CPU)
        return functools.reduce(jnp.add, [a[..., i] * b[..., i] for i in range(a.shape[-1])])
    return jnp.sum(a * b, axis=-1)


def outer(s: ArrayLike, v: Float[ArrayLike, "3"]) -> Array:
    """s[..., None] * v without implicit rank promotion: shape s.shape + v.shape."""
    s, v = jnp.asarray(s), jnp.asarray(v)
    return jnp.expand_dims(s, -1) * jnp.reshape(v, (1,) * s.ndim + v.shape)


SHORT_AXIS = 16  # axes up to this length are summed as written-out elementwise adds


def sum_short(a: ArrayLike, axis: int | tuple[int, ...]) -> Array:
    """`jnp.sum` over `axis` (int or tuple); axes of at most SHORT_AXIS entries (the 9 nodes of a
    lobe, the 6 sub-planes of an interval) are added slice by slice, which XLA on CPU fuses into
    one vectorized elementwise loop. Use it where measured faster, which depends on the producer
    as much as on the axis: XLA's reduction was several times slower for a short MIDDLE axis (the
    EM E-step) and YNNPACK slower for the EM M-step, lobe conversion and ISE sums over leading
    axes, while `jnp.sum` stayed faster for the EM node moments and the light-shaft forward pass."""
    a = jnp.asarray(a)
    axes = sorted(ax % a.ndim for ax in ((axis,) if isinstance(axis, int) else axis))
    for ax in reversed(axes):
        if a.shape[ax] <= SHORT_AXIS:
            a = functools.reduce(jnp.add, [jax.lax.index_in_dim(a, i, ax, keepdims=False) for i in range(a.shape[ax])])
        else:
            a = jnp.sum(a, axis=ax)
    return a


def sum_last(a: ArrayLike) -> Array:
    """Sum over the last axis by halving it (x[:n/2] + x[n/2:]) while its length is even, then
    adding the rest slice by slice: elementwise adds XLA fuses with their producer into one loop.
    A reduction there may become a YNNPACK fusion on XLA's CPU backend, which ran the light-shaft
    sample loop (24-48 samples a ray, the samples' whole computation fused in) 3-7x slower. From 32
    on, a product with a vector of ones instead: there XLA fused the samples' whole computation into
    the first halving (each output element computing two samples 16 apart), 15x slower per sample
    than the stored (rays, samples) array the product reads (720 x 480 adaptive spot frames on an
    Intel Xeon: 0.35 s at 32 samples and 0.53 s at 48 that way, 0.11 and 0.12 s with the product,
    0.10 s at 24)."""
    a = jnp.asarray(a)
    if a.shape[-1] >= 32:
        return a @ jnp.ones((a.shape[-1],), a.dtype)
    while a.shape[-1] > 1 and a.shape[-1] % 2 == 0:
        half = a.shape[-1] // 2
        a = a[..., :half] + a[..., half:]
    return functools.reduce(jnp.add, [a[..., i] for i in range(a.shape[-1])])


@jax.custom_jvp
def atan_nonneg(x: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """arctan(x) for x >= 0 as vectorizable polynomial arithmetic (Cephes `atanf`: range reduction
    to |x| <= tan(pi/8) and a degree-9 odd polynomial; |error| < 2e-7). XLA's CPU arctan2 is a
    scalar libm call per element (~50 ns), this is a few fused flops. Its derivative is arctan's,
    1 / (1 + x^2) (a custom JVP: differentiating the range reduction and the polynomial cost ~1.3x
    a light-shaft frame in reverse mode; the two derivatives differ by ~1e-6)."""
    x = jnp.asarray(x)
    big = x > 2.414213562373095
    mid = (x > 0.41421356237309503) & ~big
    safe_big = jnp.where(big, x, 1.0)
    xr = jnp.where(big, -1.0 / safe_big, jnp.where(mid, (x - 1.0) / (x + 1.0), x))
    y0 = jnp.where(big, 0.5 * jnp.pi, jnp.where(mid, 0.25 * jnp.pi, 0.0))
    z = xr * xr
    poly = (((8.05374449538e-2 * z - 1.38776856032e-1) * z + 1.99777106478e-1) * z - 3.33329491539e-1) * z
    return (y0 + (xr + xr * poly)).astype(x.dtype)


@atan_nonneg.defjvp
def _atan_nonneg_jvp(primals, tangents):
    (x,), (dx,) = primals, tangents
    x = jnp.asarray(x)
    return atan_nonneg(x), dx / (1.0 + x * x)

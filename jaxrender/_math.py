"""Gradient-safe vector maths shared by every kernel (no NaN gradients at zero length)."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float


def safe_norm(x: Float[ArrayLike, "... 3"], *, eps: float = 1e-12) -> Float[Array, "..."]:
    """Euclidean norm whose gradient at 0 is 0 instead of NaN."""
    x = jnp.asarray(x)
    sq = jnp.sum(x * x, axis=-1)
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


def dot(a: Float[ArrayLike, "... 3"], b: Float[ArrayLike, "... 3"]) -> Float[Array, "..."]:
    return jnp.sum(jnp.asarray(a) * jnp.asarray(b), axis=-1)


def outer(s: ArrayLike, v: Float[ArrayLike, "3"]) -> Array:
    """s[..., None] * v without implicit rank promotion: shape s.shape + v.shape."""
    s, v = jnp.asarray(s), jnp.asarray(v)
    return jnp.expand_dims(s, -1) * jnp.reshape(v, (1,) * s.ndim + v.shape)

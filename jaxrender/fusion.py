"""Control over XLA's fusion where it costs time: compute a value once and store it.

XLA's CPU compiler copies a cheap elementwise producer into every consumer fusion and recomputes
it there: a primary ray cast read by the surface shading, the shadow lookups and five cone
intersections is cast once per consumer. `jax.lax.optimization_barrier` does not prevent it (the
CPU pipeline expands barriers before fusion: none is left in the optimized HLO), but fusion never
crosses the boundary of a conditional. `materialize` runs a function as both branches of a
`lax.cond`, so its outputs are computed once, stored, and read by every consumer.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

__all__ = ["materialize"]


def materialize(fn: Callable[..., Any], *args: Any) -> Any:
    """fn(*args), computed as its own XLA computation whose outputs are stored once.

    Both branches of the `lax.cond` are `fn`, so the result is fn(*args) whichever runs; the
    predicate (is the first floating-point input NaN) is data XLA cannot fold away. Differentiable
    like fn (a cond differentiates branch-wise). Under `vmap` with batched inputs the cond becomes
    a select and fn is evaluated twice: use it in per-image code, not inside a vmapped kernel."""
    floats = [x for x in jax.tree_util.tree_leaves(args)
              if isinstance(x, jax.Array | jnp.ndarray) and jnp.issubdtype(x.dtype, jnp.floating) and x.size]
    if not floats:
        return fn(*args)
    pred = jnp.isnan(jnp.ravel(floats[0])[0])
    return jax.lax.cond(pred, lambda a: fn(*a), lambda a: fn(*a), args)

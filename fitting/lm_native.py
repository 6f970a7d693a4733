"""A plain Levenberg-Marquardt loop (Nielsen's damping update) on the projected fit: vmappable, no
residual function, the objective's gradient and Gauss-Newton matrix straight from
`fitting.residual.linearize`."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .residual import chol_solve, linearize, rounding_floor

__all__ = ["solve"]


def solve(fn, theta0, problem, max_steps, rtol, atol):
    """(theta, converged, steps) of the projected fit of `problem` from theta0 (`fn.model`: the model form).

    One pass over the lights per step gives cost, gradient g and Gauss-Newton matrix M at the
    trial point together; the damped step solves (M + lam I) d = -g by an unrolled Cholesky.
    Termination on an accepted step as optimistix's: |d_i| <= atol + rtol |theta_i| and a cost
    change <= atol + rtol cost; or when no step can reduce the cost any more in the working
    precision (a stationary point).
    """
    dt = theta0.dtype

    def linearized(theta):
        objective, grad, matrix = linearize(theta, problem, fn.model)
        return objective, matrix, grad

    # The loop's first pass evaluates the start itself (d = 0, accepted, not counted as a step):
    # one copy of the linearization in the compiled program.
    two = jnp.asarray(2.0, dt)

    def cond(st):
        return (st["step"] < max_steps) & ~st["done"]

    def body(st):
        theta, cost, a, g, lam, nu, first = st["theta"], st["cost"], st["a"], st["g"], st["lam"], st["nu"], st["first"]
        d = jnp.where(first, 0.0, chol_solve(a + lam * jnp.eye(4, dtype=dt), -g))
        t_new = theta + d
        c_new, a_new, g_new = linearized(t_new)
        pred = 0.5 * jnp.dot(d, lam * d - g)  # predicted reduction of the linear model (> 0)
        actual = cost - c_new
        ratio = actual / jnp.maximum(pred, jnp.finfo(dt).tiny)
        accept = first | ((ratio > 0) & jnp.isfinite(c_new))
        small_step = jnp.all(jnp.abs(d) <= atol + rtol * jnp.abs(theta))
        small_df = jnp.abs(actual) <= atol + rtol * cost
        # a rejected step that could gain at most a rounding-level change of the cost: the cost is
        # at its minimum up to rounding (in float32 the cost is only known to ~1e-6 relative)
        stalled = ~accept & (pred <= rounding_floor(dt, rtol) * cost)
        done = ~first & jnp.where(accept, small_step & small_df, stalled)
        lam_acc = lam * jnp.maximum(1 / 3, 1 - (2 * ratio - 1) ** 3)
        lam_first = 1e-6 * jnp.max(jnp.diagonal(a_new)) + jnp.finfo(dt).tiny ** 0.5
        return {"theta": jnp.where(accept, t_new, theta), "cost": jnp.where(accept, c_new, cost),
                "a": jnp.where(accept, a_new, a), "g": jnp.where(accept, g_new, g),
                "lam": jnp.where(first, lam_first, jnp.where(accept, lam_acc, lam * nu)),
                "nu": jnp.where(accept, two, nu * 2), "step": st["step"] + jnp.where(first, 0, 1).astype(jnp.int32),
                "done": done, "first": jnp.zeros((), bool)}

    st0 = {"theta": theta0, "cost": jnp.asarray(jnp.inf, dt), "a": jnp.eye(4, dtype=dt), "g": jnp.zeros(4, dt),
           "lam": jnp.ones((), dt), "nu": two, "step": jnp.zeros((), jnp.int32), "done": jnp.zeros((), bool),
           "first": jnp.ones((), bool)}
    st = jax.lax.while_loop(cond, body, st0)
    return st["theta"], st["done"], st["step"]

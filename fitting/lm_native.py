"""A plain Levenberg-Marquardt loop (Nielsen's damping update) on the projected fit: vmappable, no
residual function, the objective's gradient and Gauss-Newton matrix straight from
`fitting.residual.linearize`. It steps (`Steps`), so a batch of texels is solved in lanes
(`fitting.lanes`): the default backend."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from .residual import chol_solve, linearize, rounding_floor

__all__ = ["Steps", "solve"]

FIRST_DAMPING = 1e-6


class Steps(eqx.Module):
    """One texel's solve, step by step (`fitting.lanes`). One pass over the lights per step gives
    cost, gradient g and Gauss-Newton matrix M at the trial point together; the damped step solves
    (M + lam I) d = -g by an unrolled Cholesky. Termination on an accepted step as optimistix's:
    |d_i| <= atol + rtol |theta_i| and a cost change <= atol + rtol cost; or when no step can
    reduce the cost any more in the working precision (a stationary point)."""

    model: str = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    rtol: float = eqx.field(static=True)
    atol: float = eqx.field(static=True)

    def start(self, theta0, problem):
        # The first step evaluates the start itself (d = 0, accepted, not counted as a step): one
        # copy of the linearization in the compiled program.
        dt = theta0.dtype
        return {"theta": theta0, "cost": jnp.asarray(jnp.inf, dt), "a": jnp.eye(4, dtype=dt), "g": jnp.zeros(4, dt),
                "lam": jnp.ones((), dt), "nu": jnp.asarray(2.0, dt), "step": jnp.zeros((), jnp.int32),
                "done": jnp.zeros((), bool), "first": jnp.ones((), bool)}

    def running(self, st):
        return (st["step"] < self.max_steps) & ~st["done"]

    def result(self, st):
        return st["theta"], st["done"], st["step"]

    def step(self, st, problem):
        theta, cost, a, g, lam, nu, first = st["theta"], st["cost"], st["a"], st["g"], st["lam"], st["nu"], st["first"]
        dt = theta.dtype
        rtol, atol = self.rtol, self.atol
        d = jnp.where(first, 0.0, chol_solve(a + lam * jnp.eye(4, dtype=dt), -g))
        t_new = theta + d
        c_new, g_new, a_new = linearize(t_new, problem, self.model)
        pred = 0.5 * jnp.dot(d, lam * d - g)  # predicted reduction of the linear model (> 0)
        actual = cost - c_new
        ratio = actual / jnp.maximum(pred, jnp.finfo(dt).tiny)
        accept = first | ((ratio > 0) & jnp.isfinite(c_new))
        small_step = jnp.all(jnp.abs(d) <= atol + rtol * jnp.abs(theta))
        # the change of the residual's norm sqrt(2 cost) as optimistix's test on the residual: |d sqrt(2c)| =
        # |dc| / sqrt(2c) <= atol + rtol sqrt(2c) (an absolute atol on the cost itself stops small costs early)
        root = jnp.sqrt(2 * jnp.maximum(cost, 0.0))
        small_df = jnp.abs(actual) <= root * (atol + rtol * root)
        # a rejected step that could gain at most a rounding-level change of the cost: the cost is
        # at its minimum up to rounding (in float32 the cost is only known to ~1e-6 relative)
        stalled = ~accept & (pred <= rounding_floor(dt, rtol) * cost)
        done = ~first & jnp.where(accept, small_step & small_df, stalled)
        lam_acc = lam * jnp.maximum(1 / 3, 1 - (2 * ratio - 1) ** 3)
        lam_first = FIRST_DAMPING * jnp.max(jnp.diagonal(a_new)) + jnp.finfo(dt).tiny ** 0.5
        two = jnp.asarray(2.0, dt)
        return {"theta": jnp.where(accept, t_new, theta), "cost": jnp.where(accept, c_new, cost),
                "a": jnp.where(accept, a_new, a), "g": jnp.where(accept, g_new, g),
                "lam": jnp.where(first, lam_first, jnp.where(accept, lam_acc, lam * nu)),
                "nu": jnp.where(accept, two, nu * 2), "step": st["step"] + jnp.where(first, 0, 1).astype(jnp.int32),
                "done": done, "first": jnp.zeros((), bool)}


def solve(fn, theta0, problem, max_steps, rtol, atol):
    """(theta, converged, steps) of the projected fit of `problem` from theta0 (`fn.model`: the model
    form), in one while loop."""
    steps = Steps(fn.model, max_steps, rtol, atol)
    st = jax.lax.while_loop(steps.running, lambda s: steps.step(s, problem), steps.start(theta0, problem))
    return steps.result(st)

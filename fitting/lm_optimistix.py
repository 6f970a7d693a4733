"""optimistix's Levenberg-Marquardt (damped Newton descent in a classical trust region) on the
compressed residual of the projected fit (`fitting.residual.VarProResidual`): the default backend.

At the optimum of a float32 fit the cost is known to ~1e-7 relative: a trial step whose predicted
and actual changes are both below that is rejected by the classical ratio test (0 / tiny), the
region shrinks and the solve runs to max_steps at the minimum, reporting failure. Here such a step
is accepted (`RoundingAwareTrustRegion`), so optimistix's own termination test (small change of y
and of the residuals) decides, as it does on every accepted step.
"""

from __future__ import annotations

from collections.abc import Callable

import jax.numpy as jnp
import lineax as lx
import optimistix as optx

from .residual import rounding_floor

__all__ = ["RoundingAwareTrustRegion", "LevenbergMarquardt", "solve"]


class RoundingAwareTrustRegion(optx.AbstractSearch):
    """optimistix's classical trust region that also accepts a step whose predicted and actual
    changes of the cost are both at its rounding level (`floor` relative)."""

    floor: float
    inner: optx.ClassicalTrustRegion

    def init(self, y, f_info_struct):
        return self.inner.init(y, f_info_struct)

    def step(self, first_step, y, y_eval, f_info, f_eval_info, state):
        step_size, accept, result, new_state = self.inner.step(first_step, y, y_eval, f_info, f_eval_info, state)
        f, f_eval = f_info.as_min(), f_eval_info.as_min()
        predicted = self.inner.predict_reduction(y_eval - y, f_info)   # <= 0
        noise = self.floor * jnp.abs(f)
        at_floor = ~first_step & (-predicted <= noise) & (jnp.abs(f_eval - f) <= noise)
        return step_size, accept | at_floor, result, new_state


class LevenbergMarquardt(optx.AbstractGaussNewton):
    """Levenberg-Marquardt with the rounding-aware trust region; the normal equations of the
    compressed 5 x 4 problem solved by Cholesky (the damping keeps them definite)."""

    rtol: float
    atol: float
    norm: Callable
    descent: optx.DampedNewtonDescent
    search: RoundingAwareTrustRegion
    verbose: Callable

    def __init__(self, rtol, atol, floor):
        self.rtol, self.atol, self.norm = rtol, atol, optx.max_norm
        self.descent = optx.DampedNewtonDescent(linear_solver=lx.Normal(lx.Cholesky()))
        self.search = RoundingAwareTrustRegion(floor, optx.ClassicalTrustRegion())
        self.verbose = _silent


def _silent(**kwargs):
    return None


def solve(fn, theta0, problem, max_steps, rtol, atol):
    """(theta, converged, steps) of `fn` (`VarProResidual`) from theta0."""
    solver = LevenbergMarquardt(rtol, atol, rounding_floor(theta0.dtype, rtol))
    sol = optx.least_squares(fn, solver, theta0, problem, max_steps=max_steps, throw=False)
    ok = sol.result == optx.RESULTS.successful
    return sol.value, ok, sol.stats["num_steps"]

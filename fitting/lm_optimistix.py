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

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx

from .residual import VarProResidual, rounding_floor

__all__ = ["RoundingAwareTrustRegion", "LevenbergMarquardt", "Steps", "solve"]


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


class Steps(eqx.Module):
    """One texel's solve, step by step (`fitting.lanes`): the iterations of `optx.least_squares`
    (`solver.init`, then `solver.step` and `solver.terminate` until it terminates, fails or has
    taken `max_steps` steps), the solver's state carried by the lane."""

    model: str = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    rtol: float = eqx.field(static=True)
    atol: float = eqx.field(static=True)

    def _parts(self, theta, problem):
        solver = LevenbergMarquardt(self.rtol, self.atol, rounding_floor(theta.dtype, self.rtol))
        residual = VarProResidual(self.model)

        def fn(y, args):
            return residual(y, args), None

        state = solver.init(fn, theta, problem, {}, jax.ShapeDtypeStruct((5,), theta.dtype), None, frozenset())
        return solver, fn, state

    def start(self, theta0, problem):
        _, _, state = self._parts(theta0, problem)
        dynamic, _ = eqx.partition(state, eqx.is_array)
        return {"y": theta0, "state": dynamic, "steps": jnp.zeros((), jnp.int32), "terminate": state.terminate,
                "result": state.result}

    def running(self, st):
        return ~st["terminate"] & (st["result"] == optx.RESULTS.successful) & (st["steps"] < self.max_steps)

    def result(self, st):
        ok = st["terminate"] & (st["result"] == optx.RESULTS.successful)
        return st["y"], ok, st["steps"]

    def step(self, st, problem):
        solver, fn, init = self._parts(st["y"], problem)
        static = eqx.partition(init, eqx.is_array)[1]
        state = eqx.combine(st["state"], static)
        y, new_state, _ = solver.step(fn, st["y"], problem, {}, state, frozenset())
        terminate, result = solver.terminate(fn, st["y"], problem, {}, new_state, frozenset())
        finite = jnp.all(jnp.isfinite(st["y"]))
        result = optx.RESULTS.where(finite, result, optx.RESULTS.nonfinite)
        return {"y": y, "state": eqx.partition(new_state, eqx.is_array)[0], "steps": st["steps"] + 1,
                "terminate": terminate, "result": result}


def solve(fn, theta0, problem, max_steps, rtol, atol):
    """(theta, converged, steps) of `fn` (`VarProResidual`) from theta0."""
    solver = LevenbergMarquardt(rtol, atol, rounding_floor(theta0.dtype, rtol))
    sol = optx.least_squares(fn, solver, theta0, problem, max_steps=max_steps, throw=False)
    ok = sol.result == optx.RESULTS.successful
    return sol.value, ok, sol.stats["num_steps"]

"""jaxopt's Levenberg-Marquardt on the compressed residual of the projected fit
(`fitting.residual.VarProResidual`); jaxopt is imported when this backend is first used."""

from __future__ import annotations

import warnings

import jax

__all__ = ["solve"]


def solve(fn, theta0, problem, max_steps, rtol, atol):
    """(theta, converged, steps) of `fn` from theta0 (Madsen-Nielsen stopping criterion)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        import jaxopt

    solver = jaxopt.LevenbergMarquardt(fn, maxiter=max_steps,
                                       stop_criterion="madsen-nielsen", xtol=rtol, gtol=atol, tol=atol,
                                       solver="cholesky", materialize_jac=True, jit=True)
    with jax.numpy_dtype_promotion("standard"):  # jaxopt multiplies bools into floats internally
        value, state = solver.run(theta0, problem)
    # The loop stops early only when the stopping criterion holds.
    ok = state.iter_num < max_steps
    return value, ok, state.iter_num

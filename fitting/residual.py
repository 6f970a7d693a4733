"""The projected fit of one texel as the Levenberg-Marquardt backends see it (`fitting.lm_optimistix`,
`lm_jaxopt`, `lm_native`).

A solve minimizes the variable-projection objective of `fitting._varpro` over theta = (p, q, s_x,
s_y) for a `Problem` (the texel's channel-major observations, weights, lights, an optional prior
and an optional `Stage`: parameters held, an ambient term). `linearize` gives the objective, its
gradient and Gauss-Newton matrix from one pass over the lights; `VarProResidual` wraps them as a
5-component residual with the same value and Gauss-Newton model (`compress`) for the backends
that take residual functions. Small dense linear algebra is unrolled (`chol_solve`).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._varpro import Lights, Prior, gauss_newton

__all__ = ["Stage", "Problem", "linearize", "compress", "VarProResidual", "rounding_floor", "cholesky",
           "forward_sub", "chol_solve"]


def cholesky(a):
    """Lower Cholesky factor of a small symmetric positive definite matrix, unrolled: scalar
    operations only, which vmapped over texels are elementwise array ops (much faster on XLA:CPU
    than batched LAPACK calls on tiny matrices). Pivots are floored at `tiny`."""
    n = a.shape[0]
    low = [[jnp.zeros((), a.dtype)] * n for _ in range(n)]
    tiny = jnp.finfo(a.dtype).tiny
    for i in range(n):
        for j in range(i + 1):
            s = a[i, j]
            for k in range(j):
                s = s - low[i][k] * low[j][k]
            low[i][j] = jnp.sqrt(jnp.maximum(s, tiny)) if i == j else s / low[j][j]
    return jnp.stack([jnp.stack(row) for row in low])


def forward_sub(low, b):
    n = low.shape[0]
    y = []
    for i in range(n):
        s = b[i]
        for k in range(i):
            s = s - low[i, k] * y[k]
        y.append(s / low[i, i])
    return jnp.stack(y)


def chol_solve(a, b):
    """Solve a x = b for a small symmetric positive definite `a` (unrolled, see `cholesky`)."""
    low = cholesky(a)
    return forward_sub(low.T[::-1, ::-1], forward_sub(low, b)[::-1])[::-1]


class Stage(NamedTuple):
    """What a solve of the robust method fits: `ambient` 1/0 (a constant per channel projected out,
    `fitting._varpro.centre`) and `free` (4: 1 where the parameter moves, 0 where it is held)."""

    ambient: Float[Array, ""]
    free: Float[Array, "4"]


class Problem(NamedTuple):
    """One texel's solve: channel-major observations `ratio_cl` (3 L), normalized weights `w` (L),
    the lights, an optional prior on the lobe and an optional `Stage` (None: every parameter free,
    no ambient term)."""

    ratio_cl: Float[Array, "3 L"]
    w: Float[Array, " L"]
    lights: Lights
    prior: Prior | None
    stage: Stage | None


def linearize(theta, problem: Problem, model: str):
    """(objective, gradient, Gauss-Newton matrix) of the projected fit at theta; a held parameter's
    row and column of the matrix are the identity's and its gradient 0: a damped step leaves it."""
    stage = problem.stage
    gn = gauss_newton(theta, problem.ratio_cl, problem.w, problem.lights, model, problem.prior,
                      ambient=None if stage is None else stage.ambient)
    if stage is None:
        return gn.objective, gn.grad, gn.matrix
    f = stage.free
    return gn.objective, f * gn.grad, jnp.outer(f, f) * gn.matrix + jnp.diag(1.0 - f)


def compress(theta, problem: Problem, model: str):
    """(r, J): a 5-residual problem with the same value and Gauss-Newton model as the projected fit.

    With objective c, gradient g and Gauss-Newton matrix M of the projected fit (`linearize`, one
    pass over the lights) and M = L L^T: J = L^T and r = (L^-1 g, sqrt(2c - |L^-1 g|^2)) give
    0.5 |r|^2 = c, J^T r = g and J^T J = M, so 0.5 |r + J d|^2 is the projected fit's own
    Gauss-Newton model in d (J's fifth row is 0). (This is the QR compression of least squares: the 3L residuals and
    their `3L x 4` Jacobian are replaced by 5 numbers and a 4 x 4 triangle.) M is lifted by 1e-7 of
    its mean diagonal to stay definite where a parameter has no effect (a black texel).
    """
    objective, grad, m = linearize(theta, problem, model)
    dt = m.dtype
    lift = 1e-7 * jnp.trace(m) / 4 + jnp.finfo(dt).tiny ** 0.5
    low = cholesky(m + lift * jnp.eye(4, dtype=dt))
    r_lin = forward_sub(low, grad)
    two_c = 2 * objective
    lin2 = jnp.sum(r_lin * r_lin)
    # |L^-1 g|^2 <= 2c in exact arithmetic (a projection of the residual); keep 0.5 |r|^2 = c under rounding
    r_lin = r_lin * jnp.where(lin2 > two_c, jnp.sqrt(two_c / jnp.where(lin2 > 0, lin2, 1.0)), 1.0)
    rest = jnp.sqrt(jnp.maximum(two_c - jnp.sum(r_lin * r_lin), 0.0))
    r = jnp.concatenate([r_lin, rest[None]])
    jac = jnp.concatenate([low.T, jnp.zeros((1, 4), dt)])
    # Any orthogonal map of (r, J) keeps the model; this reflection spreads the large `rest` over
    # all five components so that optimistix's per-component test of the change in r (relative
    # to |r_i|) sees no component that is zero at the optimum (as L^-1 g is) and only rounding.
    v = jnp.full((5,), -1 / 5**0.5, dt).at[4].add(1.0)   # e5 - u, u = (1, 1, 1, 1, 1) / sqrt(5)
    reflect = jnp.eye(5, dtype=dt) - 2 * jnp.outer(v, v) / jnp.sum(v * v)
    return reflect @ r, reflect @ jac


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def _residual(theta, problem, model):
    return compress(theta, problem, model)[0]


@_residual.defjvp
def _residual_jvp(model, primals, tangents):
    """The tangent J d of the compressed residual (`compress`); the observations (`problem`) are
    data, not parameters: their tangents are ignored."""
    theta, problem = primals
    d_theta, _ = tangents
    r, jac = compress(theta, problem, model)
    return r, jac @ d_theta


class VarProResidual(eqx.Module):
    """theta, problem -> the compressed residual of the projected fit (`compress`): the residual
    function the optimistix and jaxopt backends minimize."""

    model: str = eqx.field(static=True)

    def __call__(self, theta, problem):
        return _residual(theta, problem, self.model)


def rounding_floor(dt, rtol: float) -> float:
    """Relative change of the cost below which a step cannot be told from rounding."""
    return max(rtol * rtol, 8 * float(jnp.finfo(dt).eps))

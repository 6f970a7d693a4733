"""Per-texel Levenberg-Marquardt fit of the anisotropic model (paper 004 eq. 1, design.md):
rho_d and rho_s eliminated by variable projection (`fitting._varpro`), the normal and two slopes
fitted by optimistix's LM (default), jaxopt's or a native loop, from photometric-stereo and
brightest-highlight starts. The parametrization, the objective and the starts: docs/fitting.md,
"The per-texel fit".
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from jaxrender.brdf import MODELS, BTFTexel, reflectance, tangent_frame
from jaxrender.maths import normalize

from ._varpro import (
    RIDGE,
    S_MAX,
    S_MIN,
    Lights,
    Prior,
    centre,
    columns,
    columns_from_frame,
    gauss_newton,
    geometry_to_theta,
    lights_of,
    project_rho_columns,
    projected_cost_offset,
    projected_cost_offset_and_rho_d,
    theta_to_geometry,
)

__all__ = ["TexelFit", "MaterialTable", "SOLVERS", "fit_texels", "fit_texel", "initial_theta", "theta_to_geometry",
           "geometry_to_theta", "basis", "project_rho", "texel_cost", "texel_residuals",
           "default_tolerances", "DEFAULT_SOLVER", "S_MIN", "S_MAX", "SIGMA_STARTS"]

SOLVERS = ("native", "optimistix", "jaxopt")
DEFAULT_SOLVER = "optimistix"
SIGMA_STARTS = (0.03, 0.1, 0.3)
DEFAULT_MAX_STEPS = 40
_ALIGN = 16   # float32 lanes of a 64-byte vector


class TexelFit(eqx.Module):
    """Fitted parameters and diagnostics; leading axes are texels (`T`) or absent (one texel)."""

    rho_d: Float[Array, "*T 3"]
    rho_s: Float[Array, "*T 3"]
    normal: Float[Array, "*T 3"]
    sigma_x: Float[Array, "*T"]
    sigma_y: Float[Array, "*T"]
    residual: Float[Array, "*T"]   # RMS of R - model over valid observations and channels
    cost: Float[Array, "*T"]       # the solver's objective at the fitted parameters
    converged: Bool[Array, "*T"]   # the solver met its tolerance or fitted exactly (and the texel had observations)
    num_steps: Int[Array, "*T"]
    n_valid: Int[Array, "*T"]
    material: Int[Array, "*T"]     # the row of the `MaterialTable` whose prior the texel took (-1: none)

    def texel(self) -> BTFTexel:
        """The fit as a one-lobe `BTFTexel` (for `jaxrender.brdf.reflectance` / rendering)."""
        return BTFTexel.single(self.rho_d, self.rho_s, self.normal, self.sigma_x, self.sigma_y)


# The priors a `MaterialTable` gives a texel (one setting for every capture): log-slopes within
# TAU_LOG_SLOPE of the material's (a factor e^0.35 = 1.4 at one standard deviation), rho_s within
# TAU_RHO_REL of the material's plus TAU_RHO_FLOOR of the texel's RMS observation (so a material
# without a lobe still lets a texel's lobe through where its data pin it).
TAU_LOG_SLOPE = 0.35
TAU_RHO_REL = 0.35
TAU_RHO_FLOOR = 0.05
DIM_FRACTION = 0.08
ROBUST_SCALE = 2.5  # Cauchy weights: an observation ROBUST_SCALE times the median residual off weighs 1/2
COLOUR_EPS = 1e-3   # log(rho_d + eps): the colour a texel's material is recognised by


class MaterialTable(eqx.Module):
    """Materials shared by the texels of a capture (estimated by `fitting.materials`): per row
    the centre of a Gaussian prior on a texel's lobe, and the capture's noise level.

    A texel fitted with a table takes the prior of the row that explains its start best (the
    MAP class: projected objective plus the row's log share); the prior's weights are the noise
    variance (`noise` times the texel's mean squared observation) over the prior's variance.
    Rows with `log_share` = -inf are unused (tables are padded to one shape)."""

    rho_s: Float[Array, "M 3"]
    s: Float[Array, "M 2"]         # the solver's log-slopes (`geometry_to_theta`) of the material's lobe
    log_share: Float[Array, " M"]  # log of the fraction of the sample's texels in the material
    colour: Float[Array, "M 3"]    # mean log(rho_d + COLOUR_EPS) of the material's texels
    colour_spread: Float[Array, " M"]   # their standard deviation (per channel, pooled)
    noise: Float[Array, ""]        # residual variance of the sample's fits / their mean squared observation

    @property
    def size(self) -> int:
        return int(self.rho_s.shape[0])


def _material_priors(table: MaterialTable, mean_sq: Float[Array, ""]) -> Prior:
    """The `M` priors of a table for a texel of mean squared observation `mean_sq` (stacked)."""
    var = table.noise * mean_sq
    tau_rho = TAU_RHO_REL * jnp.mean(table.rho_s, axis=-1) + TAU_RHO_FLOOR * jnp.sqrt(mean_sq)
    rho_weight = var / jnp.maximum(tau_rho * tau_rho, jnp.finfo(mean_sq.dtype).tiny)
    s_weight = jnp.broadcast_to(var / TAU_LOG_SLOPE**2, rho_weight.shape)
    return Prior(table.rho_s, rho_weight, table.s, s_weight)


def default_tolerances(dtype) -> tuple[float, float]:
    """(rtol, atol) of the solver's termination test for the observations' dtype."""
    if jnp.dtype(dtype) == jnp.float64:
        return 1e-8, 1e-10
    # float32: the cost is known to ~1e-7 relative; atol 1e-4 on theta is ~0.006 deg of normal or
    # 1e-4 relative sigma, far below what the noise of a capture determines
    return 1e-4, 1e-4


# ---------------------------------------------------------------------------------------------
# the model's columns, for explicit geometry

def basis(normal: Float[Array, "3"], sigma_x: Float[Array, ""], sigma_y: Float[Array, ""],
          light_dirs: Float[Array, "L 3"], view_dir: Float[Array, "3"], *,
          model: str = "reciprocal") -> Float[Array, "L 2"]:
    """Columns (a, b) of the model: R = rho_d a + rho_s b, per channel (`normal` a unit vector).

    The same terms as `jaxrender.brdf.reflectance` of a one-lobe texel (tested equal), evaluated
    on the light directions as structure of arrays.
    """
    t, b, n = tangent_frame(jnp.asarray(normal))
    lights = lights_of(jnp.asarray(light_dirs), jnp.asarray(view_dir))
    return jnp.stack(columns_from_frame((n, t, b, sigma_x, sigma_y), lights, model), axis=-1)


def project_rho(ab: Float[Array, "L 2"], ratio_cl: Float[Array, "3 L"], w: Float[Array, " L"], *,
                ridge: float = RIDGE) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
    """Per channel: argmin_{rho_d, rho_s >= 0} sum_l w_l (R_l - rho_d a_l - rho_s b_l)^2 + lam |rho|^2
    (closed form, `fitting._varpro.nnls2`); the observations are channel-major (`3 L`)."""
    return project_rho_columns(ab[:, 0], ab[:, 1], ratio_cl, w, ridge=ridge)


def _normalized_weights(weight: Float[Array, " L"]) -> Float[Array, " L"]:
    valid = weight > 0
    n = jnp.sum(valid).astype(weight.dtype)
    total = jnp.sum(jnp.where(valid, weight, 0.0))
    scale = jnp.where(total > 0, n / jnp.where(total > 0, total, 1.0), 0.0)
    return jnp.where(valid, weight * scale, 0.0)


def texel_residuals(rho_d: Float[Array, "3"], rho_s: Float[Array, "3"], normal: Float[Array, "3"],
                    sigma_x, sigma_y, ratio: Float[Array, "L 3"], weight: Float[Array, " L"],
                    light_dirs: Float[Array, "L 3"], view_dir: Float[Array, "3"], *,
                    model: str = "reciprocal") -> Float[Array, "L 3"]:
    """sqrt(w_l) (R_lc - model_lc) for explicit parameters (`weight` raw; normalized here)."""
    texel = BTFTexel.single(rho_d, rho_s, normal, sigma_x, sigma_y)
    pred = jax.vmap(lambda wi: reflectance(texel, wi, view_dir, model=model))(light_dirs)
    sw = jnp.sqrt(_normalized_weights(weight))
    return sw[:, None] * (ratio - pred)


def texel_cost(rho_d, rho_s, normal, sigma_x, sigma_y, ratio, weight, light_dirs, view_dir, *,
               model: str = "reciprocal") -> Float[Array, ""]:
    """The fit's objective 0.5 * sum w (R - model)^2 at explicit parameters."""
    r = texel_residuals(rho_d, rho_s, normal, sigma_x, sigma_y, ratio, weight, light_dirs, view_dir, model=model)
    return 0.5 * jnp.sum(r * r)


def _cholesky(a):
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


def _forward_sub(low, b):
    n = low.shape[0]
    y = []
    for i in range(n):
        s = b[i]
        for k in range(i):
            s = s - low[i, k] * y[k]
        y.append(s / low[i, i])
    return jnp.stack(y)


def _chol_solve(a, b):
    """Solve a x = b for a small symmetric positive definite `a` (unrolled, see `_cholesky`)."""
    low = _cholesky(a)
    return _forward_sub(low.T[::-1, ::-1], _forward_sub(low, b)[::-1])[::-1]


class Stage(NamedTuple):
    """What a solve of a real-capture fit (`fit_texel`'s rounds) fits: `ambient` 1/0 (a constant
    per channel projected out, `fitting._varpro.centre`) and `free` (4: 1 where the parameter
    moves, 0 where it is held)."""

    ambient: Float[Array, ""]
    free: Float[Array, "4"]


def _staged(gn, stage: Stage | None):
    """(objective, gradient, Gauss-Newton matrix) with the held parameters' rows and columns of
    the matrix replaced by the identity and their gradient by 0: a damped step leaves them."""
    if stage is None:
        return gn.objective, gn.grad, gn.matrix
    f = stage.free
    return gn.objective, f * gn.grad, jnp.outer(f, f) * gn.matrix + jnp.diag(1.0 - f)


def _ambient(stage: Stage | None):
    return None if stage is None else stage.ambient


def _compress(theta, args, model):
    """(r, J): a 5-residual problem with the same value and Gauss-Newton model as the projected fit.

    With objective c, gradient g and Gauss-Newton matrix M of the projected fit (`gauss_newton`, one
    pass over the lights) and M = L L^T: J = L^T and r = (L^-1 g, sqrt(2c - |L^-1 g|^2)) give
    0.5 |r|^2 = c, J^T r = g and J^T J = M, so 0.5 |r + J d|^2 is the projected fit's own
    Gauss-Newton model in d (J's fifth row is 0). (This is the QR compression of least squares: the 3L residuals and
    their `3L x 4` Jacobian are replaced by 5 numbers and a 4 x 4 triangle.) M is lifted by 1e-7 of
    its mean diagonal to stay definite where a parameter has no effect (a black texel).
    """
    ratio_cl, w, lights, prior, stage = args
    objective, grad, m = _staged(gauss_newton(theta, ratio_cl, w, lights, model, prior, ambient=_ambient(stage)), stage)
    dt = m.dtype
    lift = 1e-7 * jnp.trace(m) / 4 + jnp.finfo(dt).tiny ** 0.5
    low = _cholesky(m + lift * jnp.eye(4, dtype=dt))
    r_lin = _forward_sub(low, grad)
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
def _residual(theta, args, model):
    return _compress(theta, args, model)[0]


@_residual.defjvp
def _residual_jvp(model, primals, tangents):
    """The tangent J d of the compressed residual (`_compress`); the observations (`args`) are
    data, not parameters: their tangents are ignored."""
    theta, args = primals
    d_theta, _ = tangents
    r, jac = _compress(theta, args, model)
    return r, jac @ d_theta


class _VarProResidual(eqx.Module):
    """theta -> the compressed residual of the projected fit (`_compress`): the solvers' residual."""

    model: str = eqx.field(static=True)

    def __call__(self, theta, args):
        return _residual(theta, args, self.model)


# ---------------------------------------------------------------------------------------------
# starting values

def _photometric_stereo(ratio_cl: Float[Array, "3 L"], w: Float[Array, " L"], lights: Lights) -> Float[Array, "3"]:
    """Lambertian normal from the luminance, re-solved without specular outliers and shadows."""
    dt = ratio_cl.dtype
    y = (ratio_cl[0] + ratio_cl[1] + ratio_cl[2]) / 3
    l = lights.l
    valid = w > 0
    use = valid
    g = jnp.zeros(3, dt)
    for _ in range(3):
        u = jnp.where(use, w, 0.0)
        a = jnp.stack([jnp.stack([jnp.sum(u * l[i] * l[j]) for j in range(3)]) for i in range(3)])
        a = a + (1e-6 * jnp.trace(a) + jnp.finfo(dt).tiny ** 0.5) * jnp.eye(3, dtype=dt)
        g = _chol_solve(a, jnp.stack([jnp.sum(l[i] * u * y) for i in range(3)]))
        pred = l[0] * g[0] + l[1] * g[1] + l[2] * g[2]
        e = y - pred
        scale = jnp.sqrt(jnp.sum(u * e * e) / jnp.maximum(jnp.sum(u), 1e-30))
        keep = valid & (e <= 2.0 * scale + 1e-6) & (pred > 0)
        use = jnp.where(jnp.sum(keep) >= 3, keep, use)
    n = normalize(g)
    z = jnp.array([0.0, 0.0, 1.0], dt)
    return jnp.where(n[2] > 0.05, n, z)


def initial_theta(ratio: Float[Array, "L 3"], weight: Float[Array, " L"], light_dirs: Float[Array, "L 3"],
                  view_dir: Float[Array, "3"], *, model: str = "reciprocal") -> Float[Array, "4"]:
    """The starting point of the solver (see the module docstring)."""
    return _initial_theta(jnp.asarray(ratio).T, _normalized_weights(jnp.asarray(weight)),
                          lights_of(jnp.asarray(light_dirs), jnp.asarray(view_dir)), model)


def _start_normals(ratio_cl, w, lights):
    """The photometric-stereo normal and the half vector of the brightest observation."""
    n_ps = _photometric_stereo(ratio_cl, w, lights)
    y = jnp.where(w > 0, ratio_cl[0] + ratio_cl[1] + ratio_cl[2], -jnp.inf)
    brightest = jnp.argmax(y)
    n_peak = normalize(jnp.stack([c[brightest] for c in lights.h]))  # the half vector of the brightest light
    return n_ps, jnp.where(n_peak[2] > 0.05, n_peak, n_ps)


def _material_start(ratio_cl, w, lights, model, table: MaterialTable, ambient=None):
    """(theta0, prior, row) of a texel fitted with a material table (`MaterialTable`).

    Each row's lobe at the better of the two start normals is scored by its projected objective
    under the row's prior plus the noise variance times -log(share) (a MAP class); the best row's
    prior is the texel's. The start is the best, under that prior, of the rows' lobes and the
    generic 3 x 3 slope grid (`_initial_theta`)."""
    dt = ratio_cl.dtype
    sq = ratio_cl[0] ** 2 + ratio_cl[1] ** 2 + ratio_cl[2] ** 2
    mean_sq = jnp.sum(w * sq) / (3 * jnp.maximum(jnp.sum(w), 1e-30))
    priors = _material_priors(table, mean_sq)
    normals = jnp.stack(_start_normals(ratio_cl, w, lights))

    def row_score(prior, colour, spread):
        def at(n):
            th = jnp.concatenate([geometry_to_theta(n, 1.0, 1.0)[:2], prior.s])
            score, rho_d = projected_cost_offset_and_rho_d(th, ratio_cl, w, lights, model, prior, ambient=ambient)
            d = (jnp.log(rho_d + COLOUR_EPS) - colour) / spread
            # the Gaussian colour likelihood of the material (negative log, up to a constant)
            return th, score, 0.5 * jnp.sum(d * d) + 3 * jnp.log(spread)
        ths, sc, nll = jax.vmap(at)(normals)
        k = jnp.argmin(sc)
        return ths[k], sc[k], nll[k]

    thetas, scores, colour_nll = jax.vmap(row_score)(priors, table.colour, table.colour_spread)
    var = table.noise * mean_sq
    total = jnp.where(jnp.isfinite(table.log_share), scores + 2 * var * (colour_nll - table.log_share), jnp.inf)
    row = jnp.argmin(total)
    prior = jax.tree_util.tree_map(lambda x: x[row], priors)
    generic = _initial_theta(ratio_cl, w, lights, model, prior=prior, normals=normals, ambient=ambient)
    cand = jnp.concatenate([thetas, generic[None]])
    score = jax.vmap(lambda th: projected_cost_offset(th, ratio_cl, w, lights, model, prior, ambient=ambient))(cand)
    score = jnp.where(jnp.concatenate([jnp.isfinite(table.log_share), jnp.ones(1, bool)]), score, jnp.inf)
    return cand[jnp.argmin(score)].astype(dt), prior, row.astype(jnp.int32)


def _initial_theta(ratio_cl, w, lights, model, prior: Prior | None = None, normals=None, ambient=None):
    dt = ratio_cl.dtype
    normals = jnp.stack(_start_normals(ratio_cl, w, lights)) if normals is None else normals
    sig = jnp.asarray(SIGMA_STARTS, dt)
    score = jax.vmap(lambda th: projected_cost_offset(th, ratio_cl, w, lights, model, prior, ambient=ambient))
    # the better normal at the middle slopes, then the 3 x 3 slopes with that normal
    mid = sig[len(SIGMA_STARTS) // 2]
    normal = normals[jnp.argmin(score(jax.vmap(lambda n: geometry_to_theta(n, mid, mid))(normals)))]
    sx, sy = jnp.meshgrid(sig, sig, indexing="ij")
    cand = jax.vmap(lambda a, b: geometry_to_theta(normal, a, b))(sx.reshape(-1), sy.reshape(-1))
    return cand[jnp.argmin(score(cand))]


# ---------------------------------------------------------------------------------------------
# the solve

def _rounding_floor(dt, rtol: float) -> float:
    """Relative change of the cost below which a step cannot be told from rounding."""
    return max(rtol * rtol, 8 * float(jnp.finfo(dt).eps))


@functools.cache
def _optimistix_lm():
    """optimistix's Levenberg-Marquardt (damped Newton descent in a classical trust region), its
    trust region told the cost's rounding level.

    At the optimum of a float32 fit the cost is known to ~1e-7 relative: a trial step whose
    predicted and actual changes are both below that is rejected by the classical ratio test
    (0 / tiny), the region shrinks and the solve runs to max_steps at the minimum, reporting
    failure. Here such a step is accepted, so optimistix's own termination test (small change of
    y and of the residuals) decides, as it does on every accepted step.
    """
    from collections.abc import Callable

    import lineax as lx
    import optimistix as optx

    class RoundingAwareTrustRegion(optx.AbstractSearch):
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
        rtol: float
        atol: float
        norm: Callable
        descent: optx.DampedNewtonDescent
        search: RoundingAwareTrustRegion
        verbose: Callable

        def __init__(self, rtol, atol, floor):
            self.rtol, self.atol, self.norm = rtol, atol, optx.max_norm
            # normal equations of the compressed 5 x 4 problem (`_compress`) by Cholesky; lam > 0
            # keeps them definite
            self.descent = optx.DampedNewtonDescent(linear_solver=lx.Normal(lx.Cholesky()))
            self.search = RoundingAwareTrustRegion(floor, optx.ClassicalTrustRegion())
            self.verbose = lambda **kwargs: None

    return LevenbergMarquardt


def _solve_optimistix(fn, theta0, args, max_steps, rtol, atol):
    import optimistix as optx

    solver = _optimistix_lm()(rtol, atol, _rounding_floor(theta0.dtype, rtol))
    sol = optx.least_squares(fn, solver, theta0, args, max_steps=max_steps, throw=False)
    ok = sol.result == optx.RESULTS.successful
    return sol.value, ok, sol.stats["num_steps"]


def _solve_jaxopt(fn, theta0, args, max_steps, rtol, atol):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        import jaxopt

    solver = jaxopt.LevenbergMarquardt(fn, maxiter=max_steps,
                                       stop_criterion="madsen-nielsen", xtol=rtol, gtol=atol, tol=atol,
                                       solver="cholesky", materialize_jac=True, jit=True)
    with jax.numpy_dtype_promotion("standard"):  # jaxopt multiplies bools into floats internally
        value, state = solver.run(theta0, args)
    # The loop stops early only when the stopping criterion holds.
    ok = state.iter_num < max_steps
    return value, ok, state.iter_num


def _solve_native(fn, theta0, args, max_steps, rtol, atol):
    """A plain Levenberg-Marquardt loop (Nielsen's damping update) on the projected fit.

    One pass over the lights per step gives cost, gradient g and Gauss-Newton matrix M at the
    trial point together (`gauss_newton`); the damped step solves (M + lam I) d = -g by an
    unrolled Cholesky. Termination on an accepted step as optimistix's: |d_i| <= atol + rtol |theta_i|
    and a cost change <= atol + rtol cost; or when no step can reduce the cost any more in the working
    precision (a stationary point).
    """
    dt = theta0.dtype
    ratio_cl, w, lights, prior, stage = args

    def linearized(theta):
        objective, grad, matrix = _staged(gauss_newton(theta, ratio_cl, w, lights, fn.model, prior,
                                                       ambient=_ambient(stage)), stage)
        return objective, matrix, grad

    # The loop's first pass evaluates the start itself (d = 0, accepted, not counted as a step):
    # one copy of the linearization in the compiled program.
    two = jnp.asarray(2.0, dt)

    def cond(st):
        return (st["step"] < max_steps) & ~st["done"]

    def body(st):
        theta, cost, a, g, lam, nu, first = st["theta"], st["cost"], st["a"], st["g"], st["lam"], st["nu"], st["first"]
        d = jnp.where(first, 0.0, _chol_solve(a + lam * jnp.eye(4, dtype=dt), -g))
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
        stalled = ~accept & (pred <= _rounding_floor(dt, rtol) * cost)
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


def _robust_weights(theta, ratio_cl, w, lights, model, prior, ambient=None):
    """Weights of an iteratively reweighted fit (Cauchy): w_l / (1 + (e_l / (ROBUST_SCALE m))^2),
    e_l the RMS residual of light l over the channels at the fit `theta`, m the median of e over
    the valid lights; normalized to mean 1 over them. Shadows the model cannot cast, highlights
    it cannot shape and interreflections weigh little; a capture the model explains keeps
    nearly uniform weights."""
    a, b = columns(theta, lights, model)
    if ambient is not None:
        a, b, ratio_cl = centre(w, ambient, a, b, ratio_cl)
    rho_d, rho_s = project_rho_columns(a, b, ratio_cl, w, prior=prior)
    e2 = sum((ratio_cl[c] - rho_d[c] * a - rho_s[c] * b) ** 2 for c in range(3))
    return _cauchy(w, e2)


def _diffuse_weights(ratio_cl, w, lights, model, ambient):
    """The Cauchy weights of `_robust_weights` for the lobeless fit at the photometric-stereo normal:
    the first geometry round's, so that a bright observation is an outlier unless the rounds find
    a lobe it is consistent with (a start fitted to it would keep it: a sharp lobe explains any one
    observation, and the normal tilts to put its mirror direction there)."""
    n_ps = _photometric_stereo(ratio_cl, w, lights)
    theta = jnp.concatenate([geometry_to_theta(n_ps, 1.0, 1.0)[:2], jnp.zeros(2, ratio_cl.dtype)])
    a, b = columns(theta, lights, model)
    a, _, r = centre(w, ambient, a, b, ratio_cl)
    saa = jnp.maximum(jnp.sum(w * a * a), jnp.finfo(a.dtype).tiny)
    e2 = jnp.zeros_like(a)
    for c in range(3):
        rho_d = jnp.maximum(jnp.sum(w * a * r[c]) / saa, 0.0)
        e2 = e2 + (r[c] - rho_d * a) ** 2
    return _cauchy(w, e2)


def _cauchy(w, e2):
    """w / (1 + e2 / (ROBUST_SCALE^2 median(e2))) over the valid lights, normalized to mean 1."""
    valid = w > 0
    n = jnp.sum(valid)
    order = jnp.sort(jnp.where(valid, e2, jnp.inf))
    med = order[jnp.maximum((n - 1) // 2, 0)]
    med = jnp.where(jnp.isfinite(med) & (med > 0), med, 1.0)
    return _normalized_weights(w / (1.0 + e2 / (ROBUST_SCALE**2 * med)))


def _staged_rounds(run, fn, theta0, ratio_cl, w, lights, model, prior, robust_rounds, max_steps, rtol, atol):
    """The solves of a real-capture fit, one solver body in a loop (compiled once):
    `robust_rounds` geometry rounds (every parameter, an ambient term projected out, the
    observations reweighted by how badly the lobeless fit at the photometric-stereo normal
    explains them in the first round, `_diffuse_weights`, and the previous round's parameters
    in the others, `_robust_weights`, without the dimmest ones, `_bright_enough`), then an
    appearance round (the slopes alone, every valid observation at its weight, no ambient term:
    the parameters that predict new lights).
    Returns (theta, converged, steps): converged when the last geometry round and the appearance
    round met their tolerance (earlier rounds only move the start of the next one)."""
    dt = theta0.dtype
    w_geo = _normalized_weights(w * _bright_enough(ratio_cl, w))
    geometry = Stage(jnp.ones((), dt), jnp.ones(4, dt))
    appearance = Stage(jnp.zeros((), dt), jnp.asarray([0.0, 0.0, 1.0, 1.0], dt))
    w_first = _diffuse_weights(ratio_cl, w_geo, lights, model, geometry.ambient)

    def round_(i, st):
        th, ok, n = st
        last = i == robust_rounds
        stage = jax.tree_util.tree_map(lambda a, b: jnp.where(last, a, b), appearance, geometry)
        w_later = _robust_weights(th, ratio_cl, w_geo, lights, model, prior, ambient=stage.ambient)
        w_r = jnp.where(last, w, jnp.where(i == 0, w_first, w_later))
        th_r, ok_r, n_r = run(fn, th, (ratio_cl, w_r, lights, prior, stage), max_steps, rtol, atol)
        bad = ~jnp.all(jnp.isfinite(th_r))
        counts = i >= robust_rounds - 1   # the rounds whose result the fit keeps
        return jnp.where(bad, th, th_r), jnp.where(counts, ok & ok_r & ~bad, ok), n + n_r

    return jax.lax.fori_loop(0, robust_rounds + 1, round_, (theta0, jnp.ones((), bool), jnp.zeros((), jnp.int32)))


def _bright_enough(ratio_cl, w):
    """1 where an observation's luminance reaches DIM_FRACTION of the texel's upper quartile, else 0:
    the dimmest observations (cast and attached shadows, the terminator, ambient light) carry
    little of the geometry and much of what the model cannot explain."""
    y = ratio_cl[0] + ratio_cl[1] + ratio_cl[2]
    valid = w > 0
    n = jnp.sum(valid)
    order = jnp.sort(jnp.where(valid, y, jnp.inf))
    q75 = order[jnp.clip((3 * n) // 4, 0, y.shape[0] - 1)]
    q75 = jnp.where(jnp.isfinite(q75), q75, 0.0)
    keep = y >= DIM_FRACTION * q75
    return jnp.where(jnp.sum(valid & keep) >= 8, keep, True).astype(w.dtype)


def fit_texel(ratio: Float[Array, "L 3"], weight: Float[Array, " L"], light_dirs: Float[Array, "L 3"],
              view_dir: Float[Array, "3"], *, model: str = "reciprocal", solver: str = DEFAULT_SOLVER,
              max_steps: int = DEFAULT_MAX_STEPS, rtol: float | None = None, atol: float | None = None,
              theta0: Float[Array, "4"] | None = None, materials: MaterialTable | None = None,
              robust_rounds: int = 0) -> TexelFit:
    """Fit one texel (not jitted; `fit_texels` is the jitted, vmapped version). `materials`: fit
    under the prior of the texel's material (`MaterialTable`); None: no prior. `robust_rounds`:
    reweight the observations by their residuals and solve again, this many times (`_robust_weights`)."""
    if model not in MODELS:
        raise ValueError(f"unknown model {model!r}: use one of {MODELS}")
    if solver not in SOLVERS:
        raise ValueError(f"unknown solver {solver!r}: use one of {SOLVERS}")
    ratio = jnp.asarray(ratio)
    dt = ratio.dtype
    weight, light_dirs, view_dir = (jnp.asarray(x, dt) for x in (weight, light_dirs, view_dir))
    d_rtol, d_atol = default_tolerances(dt)
    rtol = d_rtol if rtol is None else rtol
    atol = d_atol if atol is None else atol
    # Non-finite observations are invalid; keep them out of every product.
    finite = jnp.all(jnp.isfinite(ratio), axis=-1) & jnp.isfinite(weight)
    weight = jnp.where(finite, jnp.maximum(weight, 0.0), 0.0)
    ratio_cl = jnp.where(finite[None, :], ratio.T, 0.0)
    w = _normalized_weights(weight)
    n_valid = jnp.sum(w > 0)
    lights = lights_of(light_dirs, view_dir)
    prior, row = None, jnp.asarray(-1, jnp.int32)
    ambient = jnp.ones((), dt) if robust_rounds else None
    if materials is not None:
        start, prior, row = _material_start(ratio_cl, w, lights, model, materials, ambient=ambient)
        theta0 = start if theta0 is None else theta0
    elif theta0 is None:
        theta0 = _initial_theta(ratio_cl, w, lights, model, ambient=ambient)
    run = {"optimistix": _solve_optimistix, "jaxopt": _solve_jaxopt, "native": _solve_native}[solver]
    if robust_rounds:
        theta, ok, steps = _staged_rounds(run, _VarProResidual(model), theta0, ratio_cl, w, lights, model, prior,
                                          robust_rounds, max_steps, rtol, atol)
        bad = jnp.zeros((), bool)
    else:
        theta, ok, steps = run(_VarProResidual(model), theta0, (ratio_cl, w, lights, prior, None), max_steps, rtol,
                               atol)
        bad = ~jnp.all(jnp.isfinite(theta))
        theta = jnp.where(bad, theta0, theta)
    normal, sx, sy = theta_to_geometry(theta)
    a, b = columns(theta, lights, model)
    rho_d, rho_s = project_rho_columns(a, b, ratio_cl, w, prior=prior)
    diff = [ratio_cl[c] - rho_d[c] * a - rho_s[c] * b for c in range(3)]
    sq_l = diff[0] * diff[0] + diff[1] * diff[1] + diff[2] * diff[2]
    cost = 0.5 * jnp.sum(w * sq_l)
    sq = jnp.sum(jnp.where(w > 0, sq_l, 0.0))
    residual = jnp.sqrt(sq / jnp.maximum(3 * n_valid, 1).astype(dt))
    # An exact fit (cost 0, e.g. a black texel) is a global minimum; the trust-region ratio of
    # predicted to actual reduction is 0/0 there and optimistix never accepts a step to stop on.
    exact = cost <= jnp.finfo(dt).tiny
    # (A non-finite solver result falls back to the start, whose cost is what `exact` sees.)
    converged = ((ok & ~bad) | exact) & (n_valid > 0)
    return TexelFit(rho_d=rho_d, rho_s=rho_s, normal=normal, sigma_x=sx, sigma_y=sy, residual=residual,
                    cost=cost, converged=converged, num_steps=jnp.asarray(steps, jnp.int32),
                    n_valid=n_valid.astype(jnp.int32), material=row)


@functools.partial(jax.jit, static_argnames=("model", "solver", "max_steps", "rtol", "atol", "robust_rounds"))
def fit_texels(ratio: Float[Array, "T L 3"], weight: Float[Array, "T L"], light_dirs: Float[Array, "L 3"],
               view_dir: Float[Array, "3"], *, model: str = "reciprocal", solver: str = DEFAULT_SOLVER,
               max_steps: int = DEFAULT_MAX_STEPS, rtol: float | None = None,
               atol: float | None = None, materials: MaterialTable | None = None,
               robust_rounds: int = 0) -> TexelFit:
    """Fit a batch of texels (jitted, vmapped over the leading axis of `ratio` and `weight`).

    A texel's fit is bit-identical in any batch, at any place: the lights are padded with
    weight-0 observations and the batch with copies of its last texel to multiples of `_ALIGN`,
    so every texel's rows start equally aligned and every texel falls in a full vector lane
    (XLA:CPU's remainder loops use scalar exp/log, which round differently).
    """
    ratio, weight, light_dirs = jnp.asarray(ratio), jnp.asarray(weight), jnp.asarray(light_dirs)
    n_texels = ratio.shape[0]
    pad_l = -light_dirs.shape[0] % _ALIGN
    pad_t = -n_texels % _ALIGN
    if pad_l:
        ratio = jnp.pad(ratio, ((0, 0), (0, pad_l), (0, 0)))
        weight = jnp.pad(weight, ((0, 0), (0, pad_l)))
        up = jnp.asarray([[0.0, 0.0, 1.0]], light_dirs.dtype)
        light_dirs = jnp.concatenate([light_dirs, jnp.tile(up, (pad_l, 1))])
    if pad_t:
        ratio = jnp.concatenate([ratio, jnp.repeat(ratio[-1:], pad_t, axis=0)])
        weight = jnp.concatenate([weight, jnp.repeat(weight[-1:], pad_t, axis=0)])
    one = functools.partial(fit_texel, model=model, solver=solver, max_steps=max_steps, rtol=rtol, atol=atol,
                            robust_rounds=robust_rounds)
    out = jax.vmap(lambda r, w: one(r, w, light_dirs, view_dir, materials=materials))(ratio, weight)
    return jax.tree_util.tree_map(lambda x: x[:n_texels], out) if pad_t else out

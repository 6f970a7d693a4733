"""Per-texel Levenberg-Marquardt fit of the anisotropic model (paper 004 eq. 1, design.md).

Per texel the observations are `ratio` (`L 3`: reflectance R under each of L distant lights, RGB)
with weights `weight` (`L`: 0 for an invalid observation) for light directions `light_dirs` and
one view direction. The model is `jaxrender.brdf.reflectance` (the one BRDF of the toolkit):

    R_lc = rho_d_c a_l(N) + rho_s_c b_l(N, sigma_x, sigma_y)

with `a` the diffuse and `b` the specular column (`basis`). rho_d and rho_s enter linearly, so
they are eliminated (variable projection): for a given nonlinear parameter vector the best
non-negative (rho_d_c, rho_s_c) per channel is a 2-variable non-negative least-squares problem,
solved in closed form with a small ridge (the specular column vanishes as sigma -> 0). The
nonlinear solver then sees only

    theta = (p, q, s_x, s_y):  N = normalize(p, q, 1)  (always in the upper hemisphere),
                               sigma = SIGMA_FLOOR + exp(clip(s, S_MIN, S_MAX))

shared by the three channels: optimistix `LevenbergMarquardt` (default), jaxopt's
(`solver="jaxopt"`, imported only when asked for) or a hand-written vmappable Levenberg-Marquardt
loop (`solver="native"`: one forward-mode pass per step, 4 x 4 normal equations by an unrolled
Cholesky; several times faster, but not the default: on ill-determined texels that exhaust
max_steps its float32 result is more sensitive to rounding than optimistix's). The objective of both, and of every
comparison in the tests, is `cost = 0.5 * sum_l w_l sum_c (R_lc - model_lc)^2` with the weights
scaled to mean 1 over the valid observations.

Starting values: a photometric-stereo normal (weighted least squares of the luminance on the
light directions, re-solved twice without the specular outliers and attached shadows) and the
half vector of the brightest observation as two normal candidates, times a 3 x 3 grid of
(sigma_x, sigma_y); the candidate with the lowest projected cost starts the solver.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxrender.brdf import MODELS, SIGMA_FLOOR, BTFTexel, reflectance
from jaxrender._math import normalize

__all__ = ["TexelFit", "SOLVERS", "fit_texels", "fit_texel", "initial_theta", "theta_to_geometry",
           "geometry_to_theta", "basis", "project_rho", "texel_cost", "texel_residuals",
           "default_tolerances", "DEFAULT_SOLVER", "S_MIN", "S_MAX", "SIGMA_STARTS"]

SOLVERS = ("native", "optimistix", "jaxopt")
DEFAULT_SOLVER = "optimistix"
S_MIN, S_MAX = -12.0, 3.0   # log(sigma - floor): sigma from SIGMA_FLOOR + 6e-6 to ~20 (a flat lobe)
SIGMA_STARTS = (0.03, 0.1, 0.3)
RIDGE = 1e-7                # relative ridge of the 2 x 2 normal equations of (rho_d, rho_s)
DEFAULT_MAX_STEPS = 40
_LINEAR = "normal"


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

    def texel(self) -> BTFTexel:
        """The fit as a one-lobe `BTFTexel` (for `jaxrender.brdf.reflectance` / rendering)."""
        return BTFTexel.single(self.rho_d, self.rho_s, self.normal, self.sigma_x, self.sigma_y)


def default_tolerances(dtype) -> tuple[float, float]:
    """(rtol, atol) of the solver's termination test for the observations' dtype."""
    if jnp.dtype(dtype) == jnp.float64:
        return 1e-8, 1e-10
    return 1e-4, 1e-6  # float32: the cost itself is only known to ~1e-7 relative


# ---------------------------------------------------------------------------------------------
# parameterization

def theta_to_geometry(theta: Float[Array, "4"]) -> tuple[Float[Array, "3"], Float[Array, ""], Float[Array, ""]]:
    """(normal, sigma_x, sigma_y) of the unconstrained parameters (p, q, s_x, s_y)."""
    one = jnp.ones((), theta.dtype)
    normal = normalize(jnp.stack([theta[0], theta[1], one]))
    sigma = SIGMA_FLOOR + jnp.exp(jnp.clip(theta[2:], S_MIN, S_MAX))
    return normal, sigma[0], sigma[1]


def geometry_to_theta(normal: Float[ArrayLike, "3"], sigma_x: ArrayLike, sigma_y: ArrayLike) -> Float[Array, "4"]:
    """Inverse of `theta_to_geometry` (normals are clamped to 1e-3 above the horizon)."""
    n = jnp.asarray(normal)
    nz = jnp.maximum(n[2], 1e-3)
    sig = jnp.stack([jnp.asarray(sigma_x, n.dtype), jnp.asarray(sigma_y, n.dtype)])
    s = jnp.log(jnp.maximum(sig - SIGMA_FLOOR, 1e-30))
    return jnp.concatenate([jnp.stack([n[0] / nz, n[1] / nz]), jnp.clip(s, S_MIN, S_MAX)])


# ---------------------------------------------------------------------------------------------
# the linear part

def basis(normal: Float[Array, "3"], sigma_x: Float[Array, ""], sigma_y: Float[Array, ""],
          light_dirs: Float[Array, "L 3"], view_dir: Float[Array, "3"], *, model: str = "reciprocal") -> Float[Array, "L 2"]:
    """Columns (a, b) of the model: R = rho_d a + rho_s b, per channel.

    Evaluated with `jaxrender.brdf.reflectance` itself on a two-"channel" texel with
    rho_d = (1, 0) and rho_s = (0, 1), so the fit uses exactly the renderer's model.
    """
    dt = light_dirs.dtype
    texel = BTFTexel.single(jnp.array([1.0, 0.0], dt), jnp.array([0.0, 1.0], dt), normal, sigma_x, sigma_y)
    return jax.vmap(lambda wi: reflectance(texel, wi, view_dir, model=model))(light_dirs)


def project_rho(ab: Float[Array, "L 2"], ratio_cl: Float[Array, "3 L"], w: Float[Array, "L"], *,
                ridge: float = RIDGE) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
    """Per channel: argmin_{rho_d, rho_s >= 0} sum_l w_l (R_l - rho_d a_l - rho_s b_l)^2 + lam |rho|^2.

    The closed form of a 2-variable NNLS: the unconstrained solution when it is feasible, else
    the better of the two clamped one-variable solutions. lam = ridge * (|a|^2 + |b|^2) + tiny.
    The observations are channel-major (`3 L`): XLA on CPU is much faster without a minor axis of 3.
    """
    a, b = ab[:, 0], ab[:, 1]
    wa, wb = w * a, w * b
    saa, sab, sbb = jnp.sum(wa * a), jnp.sum(wa * b), jnp.sum(wb * b)
    tiny = jnp.asarray(jnp.finfo(ab.dtype).tiny ** 0.5, ab.dtype)
    lam = ridge * (saa + sbb) + tiny
    gaa, gbb = saa + lam, sbb + lam
    har = jnp.sum(ratio_cl * wa[None, :], axis=-1)  # (3,); elementwise: batched matvecs are slow on CPU
    hbr = jnp.sum(ratio_cl * wb[None, :], axis=-1)
    det = gaa * gbb - sab * sab
    det = jnp.maximum(det, lam * lam)  # Cauchy-Schwarz: det >= lam^2 in exact arithmetic
    xd = (gbb * har - sab * hbr) / det
    xs = (gaa * hbr - sab * har) / det
    both = (xd >= 0) & (xs >= 0)
    d_only = jnp.maximum(har / gaa, 0.0)
    s_only = jnp.maximum(hbr / gbb, 0.0)
    # q(x) = x^T G x - 2 h^T x for the two one-variable candidates
    q_d = gaa * d_only * d_only - 2 * har * d_only
    q_s = gbb * s_only * s_only - 2 * hbr * s_only
    pick_d = q_d <= q_s
    zero = jnp.zeros_like(xd)
    rho_d = jnp.where(both, xd, jnp.where(pick_d, d_only, zero))
    rho_s = jnp.where(both, xs, jnp.where(pick_d, zero, s_only))
    return rho_d, rho_s


def _normalized_weights(weight: Float[Array, "L"]) -> Float[Array, "L"]:
    valid = weight > 0
    n = jnp.sum(valid).astype(weight.dtype)
    total = jnp.sum(jnp.where(valid, weight, 0.0))
    scale = jnp.where(total > 0, n / jnp.where(total > 0, total, 1.0), 0.0)
    return jnp.where(valid, weight * scale, 0.0)


def texel_residuals(rho_d: Float[Array, "3"], rho_s: Float[Array, "3"], normal: Float[Array, "3"],
                    sigma_x, sigma_y, ratio: Float[Array, "L 3"], weight: Float[Array, "L"],
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


def _projected(theta, ratio_cl, w, light_dirs, view_dir, model):
    """(model `3 L`, rho_d, rho_s) at theta with the projected (optimal) rho."""
    normal, sx, sy = theta_to_geometry(theta)
    ab = basis(normal, sx, sy, light_dirs, view_dir, model=model)
    rho_d, rho_s = project_rho(ab, ratio_cl, w)
    pred = rho_d[:, None] * ab[None, :, 0] + rho_s[:, None] * ab[None, :, 1]
    return pred, rho_d, rho_s


def _raw_residual(theta, args, model):
    ratio_cl, w, light_dirs, view_dir = args
    pred, _, _ = _projected(theta, ratio_cl, w, light_dirs, view_dir, model)
    return (jnp.sqrt(w)[None, :] * (ratio_cl - pred)).reshape(-1)


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def _residual(theta, args, model):
    return _raw_residual(theta, args, model)


@_residual.defjvp
def _residual_jvp(model, primals, tangents):
    """One forward-mode pass gives the whole `3L x 4` Jacobian; every tangent is then J @ t.

    The solvers apply the linearization several times per step (materializing J for the damped
    least-squares solve, predicted reduction of the trust region): with J explicit each of those is
    a small matrix-vector product instead of another pass through the BRDF. The observations
    (`args`) are data, not parameters: their tangents are ignored.
    """
    theta, args = primals
    d_theta, _ = tangents
    r, lin = jax.linearize(lambda th: _raw_residual(th, args, model), theta)
    jac = jax.vmap(lin, out_axes=1)(jnp.eye(theta.shape[0], dtype=theta.dtype))
    return r, jac @ d_theta


class _VarProResidual(eqx.Module):
    """theta -> sqrt(w) (R - projected model), flattened: the nonlinear solver's residual."""

    model: str = eqx.field(static=True)

    def __call__(self, theta, args):
        return _residual(theta, args, self.model)


# ---------------------------------------------------------------------------------------------
# starting values

def _photometric_stereo(ratio_cl: Float[Array, "3 L"], w: Float[Array, "L"], light_dirs: Float[Array, "L 3"]) -> Float[Array, "3"]:
    """Lambertian normal from the luminance, re-solved without specular outliers and shadows."""
    dt = ratio_cl.dtype
    y = (ratio_cl[0] + ratio_cl[1] + ratio_cl[2]) / 3
    valid = w > 0
    use = valid
    eye = jnp.eye(3, dtype=dt)
    g = jnp.zeros(3, dt)
    for _ in range(3):
        u = jnp.where(use, w, 0.0)
        a = (light_dirs * u[:, None]).T @ light_dirs
        a = a + (1e-6 * jnp.trace(a) + jnp.finfo(dt).tiny ** 0.5) * eye
        g = jnp.linalg.solve(a, light_dirs.T @ (u * y))
        pred = light_dirs @ g
        e = y - pred
        scale = jnp.sqrt(jnp.sum(u * e * e) / jnp.maximum(jnp.sum(u), 1e-30))
        keep = valid & (e <= 2.0 * scale + 1e-6) & (pred > 0)
        use = jnp.where(jnp.sum(keep) >= 3, keep, use)
    n = normalize(g)
    z = jnp.array([0.0, 0.0, 1.0], dt)
    return jnp.where(n[2] > 0.05, n, z)


def initial_theta(ratio: Float[Array, "L 3"], weight: Float[Array, "L"], light_dirs: Float[Array, "L 3"],
                  view_dir: Float[Array, "3"], *, model: str = "reciprocal") -> Float[Array, "4"]:
    """The starting point of the solver (see the module docstring)."""
    return _initial_theta(jnp.asarray(ratio).T, _normalized_weights(jnp.asarray(weight)), jnp.asarray(light_dirs),
                          jnp.asarray(view_dir), model)


def _initial_theta(ratio_cl, w, light_dirs, view_dir, model):
    dt = ratio_cl.dtype
    n_ps = _photometric_stereo(ratio_cl, w, light_dirs)
    y = jnp.where(w > 0, ratio_cl[0] + ratio_cl[1] + ratio_cl[2], -jnp.inf)
    brightest = light_dirs[jnp.argmax(y)]
    n_peak = normalize(brightest + view_dir)
    n_peak = jnp.where(n_peak[2] > 0.05, n_peak, n_ps)
    sig = jnp.asarray(SIGMA_STARTS, dt)
    sx, sy = jnp.meshgrid(sig, sig, indexing="ij")
    sx, sy = sx.reshape(-1), sy.reshape(-1)
    normals = jnp.stack([n_ps, n_peak])
    cand = jax.vmap(lambda n: jax.vmap(lambda a, b: geometry_to_theta(n, a, b))(sx, sy))(normals).reshape(-1, 4)
    fn = _VarProResidual(model)
    costs = jax.vmap(lambda th: jnp.sum(fn(th, (ratio_cl, w, light_dirs, view_dir)) ** 2))(cand)
    return cand[jnp.argmin(costs)]


# ---------------------------------------------------------------------------------------------
# the solve

def _solve_optimistix(fn, theta0, args, max_steps, rtol, atol):
    import optimistix as optx

    import lineax as lx

    # The damped step solves [J; sqrt(lam) I] d = [r; 0]: with 4 unknowns and J explicit (see
    # `_residual_jvp`) the normal equations (J^T J + lam I, 4 x 4 Cholesky) compile and run faster
    # than a QR of the (3L + 4) x 4 matrix (measured 1.5x per fit); lam > 0 keeps them definite.
    linear = lx.QR() if _LINEAR == "qr" else lx.Normal(lx.Cholesky())
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol, linear_solver=linear)
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


def _chol_solve4(a, b):
    """Solve the symmetric positive definite 4 x 4 system a x = b by an unrolled Cholesky.

    Scalar operations only: vmapped over texels they are elementwise array ops, much faster on
    XLA:CPU than a batched LU of tiny matrices.
    """
    n = 4
    L = [[None] * n for _ in range(n)]
    tiny = jnp.finfo(a.dtype).tiny
    for i in range(n):
        for j in range(i + 1):
            s = a[i, j]
            for k in range(j):
                s = s - L[i][k] * L[j][k]
            if i == j:
                L[i][i] = jnp.sqrt(jnp.maximum(s, tiny))
            else:
                L[i][j] = s / L[j][j]
    y = [None] * n
    for i in range(n):
        s = b[i]
        for k in range(i):
            s = s - L[i][k] * y[k]
        y[i] = s / L[i][i]
    x = [None] * n
    for i in reversed(range(n)):
        s = y[i]
        for k in range(i + 1, n):
            s = s - L[k][i] * x[k]
        x[i] = s / L[i][i]
    return jnp.stack(x)


def _solve_native(fn, theta0, args, max_steps, rtol, atol):
    """A plain Levenberg-Marquardt loop (Nielsen's damping update) on the explicit 3L x 4 Jacobian.

    One forward-mode pass per step gives the residual and the Jacobian at the trial point together;
    the damped step solves the 4 x 4 normal equations (J^T J + lam I) d = -J^T r by an unrolled
    Cholesky. Termination on an accepted step as optimistix's: |d_i| <= atol + rtol |theta_i| and a
    cost change <= atol + rtol cost; or when no step can reduce the cost any more in the working precision (a stationary point).
    """
    dt = theta0.dtype

    def lin(theta):
        r, f = jax.linearize(lambda th: fn(th, args), theta)
        jac = jax.vmap(f, out_axes=1)(jnp.eye(4, dtype=dt))
        return r, jac

    def norm_eq(r, jac):
        return jac.T @ jac, jac.T @ r

    r0, j0 = lin(theta0)
    c0 = 0.5 * jnp.sum(r0 * r0)
    a0, g0 = norm_eq(r0, j0)
    lam0 = 1e-6 * jnp.max(jnp.diagonal(a0)) + jnp.finfo(dt).tiny ** 0.5
    two = jnp.asarray(2.0, dt)

    def cond(st):
        return (st["step"] < max_steps) & ~st["done"]

    def body(st):
        theta, cost, a, g, lam, nu = st["theta"], st["cost"], st["a"], st["g"], st["lam"], st["nu"]
        d = _chol_solve4(a + lam * jnp.eye(4, dtype=dt), -g)
        t_new = theta + d
        r_new, j_new = lin(t_new)
        c_new = 0.5 * jnp.sum(r_new * r_new)
        pred = 0.5 * jnp.dot(d, lam * d - g)  # predicted reduction of the linear model (> 0)
        actual = cost - c_new
        ratio = actual / jnp.maximum(pred, jnp.finfo(dt).tiny)
        accept = (ratio > 0) & jnp.isfinite(c_new)
        a_new, g_new = norm_eq(r_new, j_new)
        small_step = jnp.all(jnp.abs(d) <= atol + rtol * jnp.abs(theta))
        small_df = jnp.abs(actual) <= atol + rtol * cost
        # a rejected step that could gain at most a rounding-level change of the cost: the cost is
        # at its minimum up to rounding (in float32 the cost is only known to ~1e-6 relative)
        stalled = ~accept & (pred <= max(rtol * rtol, 8 * float(jnp.finfo(dt).eps)) * cost)
        done = jnp.where(accept, small_step & small_df, stalled)
        lam_acc = lam * jnp.maximum(1 / 3, 1 - (2 * ratio - 1) ** 3)
        return {"theta": jnp.where(accept, t_new, theta), "cost": jnp.where(accept, c_new, cost),
                "a": jnp.where(accept, a_new, a), "g": jnp.where(accept, g_new, g),
                "lam": jnp.where(accept, lam_acc, lam * nu), "nu": jnp.where(accept, two, nu * 2),
                "step": st["step"] + 1, "done": done}

    st0 = {"theta": theta0, "cost": c0, "a": a0, "g": g0, "lam": lam0, "nu": two,
           "step": jnp.zeros((), jnp.int32), "done": jnp.zeros((), bool)}
    st = jax.lax.while_loop(cond, body, st0)
    return st["theta"], st["done"], st["step"]


def fit_texel(ratio: Float[Array, "L 3"], weight: Float[Array, "L"], light_dirs: Float[Array, "L 3"],
              view_dir: Float[Array, "3"], *, model: str = "reciprocal", solver: str = DEFAULT_SOLVER,
              max_steps: int = DEFAULT_MAX_STEPS, rtol: float | None = None, atol: float | None = None,
              theta0: Float[Array, "4"] | None = None) -> TexelFit:
    """Fit one texel (not jitted; `fit_texels` is the jitted, vmapped version)."""
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
    if theta0 is None:
        theta0 = _initial_theta(ratio_cl, w, light_dirs, view_dir, model)
    args = (ratio_cl, w, light_dirs, view_dir)
    run = {"optimistix": _solve_optimistix, "jaxopt": _solve_jaxopt, "native": _solve_native}[solver]
    theta, ok, steps = run(_VarProResidual(model), theta0, args, max_steps, rtol, atol)
    bad = ~jnp.all(jnp.isfinite(theta))
    theta = jnp.where(bad, theta0, theta)
    normal, sx, sy = theta_to_geometry(theta)
    pred, rho_d, rho_s = _projected(theta, ratio_cl, w, light_dirs, view_dir, model)
    diff = ratio_cl - pred
    cost = 0.5 * jnp.sum(w[None, :] * diff * diff)
    sq = jnp.sum(jnp.where((w > 0)[None, :], diff * diff, 0.0))
    residual = jnp.sqrt(sq / jnp.maximum(3 * n_valid, 1).astype(dt))
    # An exact fit (cost 0, e.g. a black texel) is a global minimum; the trust-region ratio of
    # predicted to actual reduction is 0/0 there and optimistix never accepts a step to stop on.
    exact = cost <= jnp.finfo(dt).tiny
    # (A non-finite solver result falls back to the start, whose cost is what `exact` sees.)
    converged = ((ok & ~bad) | exact) & (n_valid > 0)
    return TexelFit(rho_d=rho_d, rho_s=rho_s, normal=normal, sigma_x=sx, sigma_y=sy, residual=residual,
                    cost=cost, converged=converged, num_steps=jnp.asarray(steps, jnp.int32),
                    n_valid=n_valid.astype(jnp.int32))


@functools.partial(jax.jit, static_argnames=("model", "solver", "max_steps", "rtol", "atol"))
def fit_texels(ratio: Float[Array, "T L 3"], weight: Float[Array, "T L"], light_dirs: Float[Array, "L 3"],
               view_dir: Float[Array, "3"], *, model: str = "reciprocal", solver: str = DEFAULT_SOLVER,
               max_steps: int = DEFAULT_MAX_STEPS, rtol: float | None = None,
               atol: float | None = None) -> TexelFit:
    """Fit a batch of texels (jitted, vmapped over the leading axis of `ratio` and `weight`)."""
    one = functools.partial(fit_texel, model=model, solver=solver, max_steps=max_steps, rtol=rtol, atol=atol)
    return jax.vmap(one, in_axes=(0, 0, None, None))(ratio, weight, light_dirs, view_dir)

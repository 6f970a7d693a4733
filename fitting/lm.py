"""Per-texel Levenberg-Marquardt fit of the anisotropic model (paper 004 eq. 1, design.md):
rho_d and rho_s eliminated by variable projection (`fitting._varpro`), the normal and two slopes
fitted by one of the backends (`BACKENDS`: `fitting.lm_optimistix`, the default, `lm_jaxopt`,
`lm_native`) from photometric-stereo and brightest-highlight starts; the robust method's material
start, reweighted geometry rounds and appearance round. The parametrization, the objective and
the starts: docs/fitting.md, "The per-texel fit".
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from jaxrender.brdf import BTFTexel, reflectance, tangent_frame
from jaxrender.maths import normalize

from . import lm_jaxopt, lm_native, lm_optimistix
from ._varpro import (
    RIDGE,
    S_MAX,
    S_MIN,
    Lights,
    Prior,
    centre,
    columns,
    columns_from_frame,
    geometry_to_theta,
    lights_of,
    project_rho_columns,
    projected_cost_offset,
    projected_cost_offset_and_rho_d,
    theta_to_geometry,
)
from .lanes import solve_in_lanes
from .materials import COLOUR_EPS, MaterialTable, material_priors, no_materials
from .residual import Problem, Stage, VarProResidual, chol_solve
from .settings import FitSettings

__all__ = ["TexelFit", "fit_texels", "fit_texel", "initial_theta", "theta_to_geometry", "geometry_to_theta", "basis",
           "project_rho", "texel_cost", "texel_residuals", "default_tolerances", "BACKENDS", "STEPPING", "S_MIN",
           "S_MAX", "SIGMA_STARTS", "ROBUST_ROUNDS"]

BACKENDS = {"optimistix": lm_optimistix.solve, "jaxopt": lm_jaxopt.solve, "native": lm_native.solve}
# backends that step: a batch is solved in lanes (`fitting.lanes`); the others texel by texel
STEPPING = {"native": lm_native.Steps, "optimistix": lm_optimistix.Steps}
SIGMA_STARTS = (0.03, 0.1, 0.3)
ROBUST_ROUNDS = 2   # reweighted geometry solves of the robust method, before its appearance solve
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


DIM_FRACTION = 0.08
ROBUST_SCALE = 2.5  # Cauchy weights: an observation ROBUST_SCALE times the median residual off weighs 1/2


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
        g = chol_solve(a, jnp.stack([jnp.sum(l[i] * u * y) for i in range(3)]))
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
    priors = material_priors(table, mean_sq)
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
# the robust method's weights

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


# ---------------------------------------------------------------------------------------------
# fitting a batch

def _solve(settings: FitSettings, theta0, per_texel, lights, stage, active=None):
    """Every texel's solve from theta0 (`N 4`); `per_texel` = (ratio_cl, w, prior or None), each
    with a leading axis of N. A backend that steps solves the batch in lanes (`fitting.lanes`), the
    first `active` texels only (None: all), the others texel by texel (vmapped), every texel."""
    rtol, atol = default_tolerances(theta0.dtype)

    def make(p):
        return Problem(p[0], p[1], lights, p[2], stage)

    if settings.solver in STEPPING:
        return solve_in_lanes(STEPPING[settings.solver](settings.model, settings.max_steps, rtol, atol), theta0,
                              per_texel, make, active)
    solve, fn = BACKENDS[settings.solver], VarProResidual(settings.model)
    return jax.vmap(lambda th, p: solve(fn, th, make(p), settings.max_steps, rtol, atol))(theta0, per_texel)


def _finite_or(theta, fallback):
    bad = ~jnp.all(jnp.isfinite(theta), axis=-1, keepdims=True)
    return jnp.where(bad, fallback, theta), bad[..., 0]


def _plain(ratio_cl, w, lights, settings: FitSettings, active=None):
    """(theta, prior None, row -1, converged, steps) of per-texel least squares."""
    model = settings.model
    theta0 = jax.vmap(lambda r, wi: _initial_theta(r, wi, lights, model))(ratio_cl, w)
    theta, ok, steps = _solve(settings, theta0, (ratio_cl, w, None), lights, None, active)
    theta, bad = _finite_or(theta, theta0)
    return theta, None, jnp.full(theta.shape[0], -1, jnp.int32), ok & ~bad, steps


def _robust(ratio_cl, w, lights, settings: FitSettings, table: MaterialTable, active=None):
    """The robust method on a batch (docs/fitting.md, "Real captures: the robust method"):
    (theta, prior, row, converged, steps). ROBUST_ROUNDS geometry solves (every parameter, an
    ambient term projected out, without the dimmest observations, reweighted by how badly the
    lobeless fit at the photometric-stereo normal explains them in the first, `_diffuse_weights`,
    and the previous solve's fit in the others, `_robust_weights`), then an appearance solve (the
    slopes alone, every valid observation at its weight, no ambient term: the parameters that
    predict new lights). The solves are one loop over rounds around one lanes solve (one copy of
    the solver in the compiled program). Converged: the last geometry solve and the appearance
    solve met their tolerance (earlier solves only move the start of the next one)."""
    model, dt = settings.model, ratio_cl.dtype
    ambient = jnp.ones((), dt)
    theta0, prior, row = jax.vmap(lambda r, wi: _material_start(r, wi, lights, model, table, ambient=ambient))(
        ratio_cl, w)
    w_geo = jax.vmap(lambda r, wi: _normalized_weights(wi * _bright_enough(r, wi)))(ratio_cl, w)
    w_first = jax.vmap(lambda r, wg: _diffuse_weights(r, wg, lights, model, ambient))(ratio_cl, w_geo)
    geometry = Stage(jnp.ones((), dt), jnp.ones(4, dt))
    appearance = Stage(jnp.zeros((), dt), jnp.asarray([0.0, 0.0, 1.0, 1.0], dt))

    def round_(i, carry):
        theta, ok, steps = carry
        last = i == ROBUST_ROUNDS
        stage = jax.tree_util.tree_map(lambda a, b: jnp.where(last, a, b), appearance, geometry)
        # the reweighting (a median over the lights per texel) only in the rounds that use it
        weights = jax.lax.switch(
            jnp.where(i == 0, 0, jnp.where(last, 2, 1)),
            (lambda: w_first,
             lambda: jax.vmap(lambda th, r, wg, pr: _robust_weights(th, r, wg, lights, model, pr, ambient=ambient))(
                 theta, ratio_cl, w_geo, prior),
             lambda: w))
        theta_r, ok_r, steps_r = _solve(settings, theta, (ratio_cl, weights, prior), lights, stage, active)
        theta_r, bad = _finite_or(theta_r, theta)
        kept = i >= ROBUST_ROUNDS - 1   # the rounds whose result the fit keeps
        return theta_r, jnp.where(kept, ok & ok_r & ~bad, ok), steps + steps_r

    n = theta0.shape[0]
    theta, ok, steps = jax.lax.fori_loop(0, ROBUST_ROUNDS + 1, round_,
                                         (theta0, jnp.ones(n, bool), jnp.zeros(n, jnp.int32)))
    return theta, prior, row, ok, steps


def _texel_fit(theta, ratio_cl, w, lights, model, prior, row, ok, steps, n_valid):
    """A texel's `TexelFit` at its parameters, rho projected on every valid observation."""
    dt = ratio_cl.dtype
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
    converged = (ok | exact) & (n_valid > 0)
    return TexelFit(rho_d=rho_d, rho_s=rho_s, normal=normal, sigma_x=sx, sigma_y=sy, residual=residual,
                    cost=cost, converged=converged, num_steps=jnp.asarray(steps, jnp.int32),
                    n_valid=n_valid.astype(jnp.int32), material=row)


def _prepare(ratio, weight):
    """(observations channel-major `3 L`, weights normalized to mean 1 over the valid ones, valid
    count); non-finite observations are invalid and kept out of every product."""
    finite = jnp.all(jnp.isfinite(ratio), axis=-1) & jnp.isfinite(weight)
    weight = jnp.where(finite, jnp.maximum(weight, 0.0), 0.0)
    ratio_cl = jnp.where(finite[None, :], ratio.T, 0.0)
    w = _normalized_weights(weight)
    return ratio_cl, w, jnp.sum(w > 0)


def fit_texels(ratio: Float[Array, "T L 3"], weight: Float[Array, "T L"], light_dirs: Float[Array, "L 3"],
               view_dir: Float[Array, "3"], settings: FitSettings = FitSettings(), *,
               materials: MaterialTable | None = None, active=None) -> TexelFit:
    """Fit a batch of texels as `settings` say (`method`, `solver`, `max_steps`, `model`; `chunk`
    plays no part here); jitted. The robust method fits under the prior of each texel's material in
    `materials` (None: a table without priors, `fitting.materials.no_materials`). `active` (an
    integer, may be traced; None: every texel): only the first `active` texels are solved, the
    rest of the batch is padding whose results are meaningless (the stepping backends, solving in
    lanes, spend no step on them). The observations are fitted as given: the engine first brings a
    capture to one level (`fitting.engine.capture_level`, docs/fitting.md), as a caller of this
    function should where its captures' units vary.

    A texel's fit is bit-identical in any batch, at any place: the lights are padded with
    weight-0 observations and the batch with copies of its last texel to multiples of `_ALIGN`,
    so every texel's rows start equally aligned and every texel falls in a full vector lane
    (XLA:CPU's remainder loops use scalar exp/log, which round differently), and a texel's solve
    runs the same operations whichever lane it takes (`fitting.lanes`).
    """
    return _fit_texels(ratio, weight, light_dirs, view_dir, materials, active, settings=settings.program())


def fit_texel(ratio: Float[Array, "L 3"], weight: Float[Array, " L"], light_dirs: Float[Array, "L 3"],
              view_dir: Float[Array, "3"], settings: FitSettings = FitSettings(), *,
              materials: MaterialTable | None = None) -> TexelFit:
    """Fit one texel (`fit_texels` of a batch of one)."""
    out = fit_texels(jnp.asarray(ratio)[None], jnp.asarray(weight)[None], light_dirs, view_dir, settings,
                     materials=materials)
    return jax.tree_util.tree_map(lambda x: x[0], out)


@functools.partial(jax.jit, static_argnames="settings")
def _fit_texels(ratio, weight, light_dirs, view_dir, materials, active, *, settings: FitSettings) -> TexelFit:
    ratio = jnp.asarray(ratio)
    dt = ratio.dtype
    weight, light_dirs, view_dir = (jnp.asarray(x, dt) for x in (weight, light_dirs, view_dir))
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
    ratio_cl, w, n_valid = jax.vmap(_prepare)(ratio, weight)
    lights = lights_of(light_dirs, view_dir)
    if settings.robust:
        table = no_materials(dt) if materials is None else materials
        fitted = _robust(ratio_cl, w, lights, settings, table, active)
    else:
        fitted = _plain(ratio_cl, w, lights, settings, active)
    theta, prior, row, ok, steps = fitted
    out = jax.vmap(lambda th, r, wi, pr, ro, o, st, nv: _texel_fit(th, r, wi, lights, settings.model, pr, ro, o, st,
                                                                    nv))(theta, ratio_cl, w, prior, row, ok, steps,
                                                                         n_valid)
    return jax.tree_util.tree_map(lambda x: x[:n_texels], out) if pad_t else out

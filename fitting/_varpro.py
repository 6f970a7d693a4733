"""The fit's model, its variable projection and its Gauss-Newton quantities, per texel.

The model (paper 004 eq. 1, `jaxrender.brdf.reflectance` of a one-lobe texel) is linear in
rho_d and rho_s: R_lc = rho_d_c a_l + rho_s_c b_l. With theta = (p, q, s_x, s_y) the nonlinear
parameters (`theta_to_geometry`), the observations R (`3 L`, channel-major) and weights w:

* `columns` gives a and b, `columns_and_derivatives` also da/dtheta and db/dtheta, written out
  (tested against forward-mode autodiff of `columns`) on structure-of-arrays light directions;
* rho is projected out per channel (a 2-variable non-negative least squares in closed form,
  `nnls2`, with a small ridge `ridge_of`), leaving the objective
  F(theta) = min_rho>=0 [cost + 0.5 lam |rho|^2],  cost = 0.5 sum_lc w_l (R_lc - rho_d_c a_l - rho_s_c b_l)^2;
* `gauss_newton` returns F, its gradient g and Gauss-Newton matrix M from one pass over the
  lights: M is the Schur complement of the full (rho, theta) Gauss-Newton matrix at the projected
  rho (Kaufman's variable-projection approximation; rho at a bound is held there), g is exact
  (lam does not depend on theta and the free rho are optimal: the envelope theorem).
  Everything M and g need is a weighted sum over lights of products of a, b, their derivatives
  and the residuals: ~50 row sums instead of a `3L x 4` Jacobian, which XLA on CPU forms and
  multiplies several times slower.

A `Prior` (optional everywhere) adds 0.5 k_rho |rho_s - mu|^2 + 0.5 k_s |(s_x, s_y) - s_mu|^2 to the
objective: a Gaussian prior on the lobe's amplitude and log-slopes (a texel's material, see
`fitting.materials`). The rho term changes the 2 x 2 projection (still closed form); the slope
term adds k_s to the Gauss-Newton matrix and k_s (s - s_mu) to the gradient.

`ambient` (optional everywhere, a 0/1 factor): a constant per channel is fitted with rho and
projected out with it, by centring the observations and the columns (`centre`): light the
model has no term for (ambient light, a diffuse that darkens toward grazing) then bends no normal.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from jaxrender.brdf import (
    COS_FLOOR,
    SIGMA_FLOOR,
    half_vector,
    slope_distribution_from_components,
    specular_factor,
    tangent_frame,
)
from jaxrender.maths import dot, normalize

S_MIN, S_MAX = -12.0, 3.0   # log(sigma - floor): sigma from SIGMA_FLOOR + 6e-6 to ~20 (a flat lobe)
RIDGE = 1e-7                # ridge on rho per valid observation: see `ridge_of`


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
# the columns a, b

class Lights(NamedTuple):
    """The capture's light geometry as structure of arrays (`L` rows, not `L 3`: XLA on CPU
    vectorizes long rows well and a minor axis of 3 badly), with the half vectors precomputed:
    they depend on the light and view directions only, never on the parameters."""

    l: tuple[Float[Array, " L"], Float[Array, " L"], Float[Array, " L"]]
    h: tuple[Float[Array, " L"], Float[Array, " L"], Float[Array, " L"]]
    view: Float[Array, "3"]
    geometric: Bool[Array, " L"]   # light and view above the sample plane


def lights_of(light_dirs: Float[Array, "L 3"], view_dir: Float[Array, "3"]) -> Lights:
    h = half_vector(light_dirs, view_dir[None, :])
    geometric = (light_dirs[:, 2] > 0) & (view_dir[2] > 0)
    return Lights(tuple(light_dirs[:, i] for i in range(3)), tuple(h[:, i] for i in range(3)), view_dir, geometric)


def _along(rows, u):
    """rows (3 arrays) . u (3 scalars)."""
    return rows[0] * u[0] + rows[1] * u[1] + rows[2] * u[2]


def _frame(theta):
    normal, sx, sy = theta_to_geometry(theta)
    t, b, n = tangent_frame(normal)
    return n, t, b, sx, sy


def columns_from_frame(frame, lights: Lights, model: str) -> tuple[Float[Array, " L"], Float[Array, " L"]]:
    """Diffuse and specular columns (a, b) for the lobe frame (N, T, B) and slopes: term for term
    `jaxrender.brdf.reflectance` of a one-lobe texel (the same D and specular factor)."""
    n, t, bt, sx, sy = frame
    cos_i, cos_r = _along(lights.l, n), dot(lights.view, n)
    d = slope_distribution_from_components(_along(lights.h, t), _along(lights.h, bt), _along(lights.h, n), sx, sy)
    a = jnp.where(lights.geometric, jnp.maximum(cos_i, 0.0), 0.0)
    b = jnp.where(lights.geometric, specular_factor(d, cos_i, cos_r, model=model), 0.0)
    return a, b


def columns(theta: Float[Array, "4"], lights: Lights, model: str) -> tuple[Float[Array, " L"], Float[Array, " L"]]:
    """(a, b) at the parameters theta."""
    return columns_from_frame(_frame(theta), lights, model)


def columns_and_derivatives(theta: Float[Array, "4"], lights: Lights, model: str):
    """(a, b, da, db): `columns` and their derivatives, da (2 rows: d/dp, d/dq; a does not depend
    on the slopes) and db (4 rows: d/dp, d/dq, d/ds_x, d/ds_y).

    The per-texel frame and its derivatives come from forward-mode autodiff of `_frame` (scalars);
    the per-light chain rule is written out: with u, v, z the half vector along T, B, N and
    E = (u^2/sx^2 + v^2/sy^2) / z^2, D = exp(-E), dD = -D dE. p and q move the frame only, s_x and
    s_y the slopes only (`theta_to_geometry`), which the rows below use.
    """
    frame = _frame(theta)
    n, t, bt, sx, sy = frame
    dn, dt, dbt, dsx, dsy = jax.jacfwd(_frame)(theta)   # (3, 4), (3, 4), (3, 4), (4,), (4,)
    a, b = columns_from_frame(frame, lights, model)
    geo = lights.geometric
    cos_i, cos_r = _along(lights.l, n), dot(lights.view, n)
    u, v, z = _along(lights.h, t), _along(lights.h, bt), _along(lights.h, n)
    front = z > 1e-6
    zs = jnp.where(front, z, 1.0)
    inv_z2 = 1.0 / (zs * zs)
    e = (u * u / (sx * sx) + v * v / (sy * sy)) * inv_z2
    live = front & (e < 80.0)   # where D = exp(-E) (not the clamp or the back side)
    lit = geo & (cos_i > 0) & (cos_r > 0)   # where b = D / denominator
    # d log(denominator) of the specular factor
    d_log_cr = jnp.where(cos_r > COS_FLOOR, _along(dn, lights.view), 0.0) / jnp.maximum(cos_r, COS_FLOOR)   # (4,)
    da, db = [], []
    for k in (0, 1):
        dci = _along(lights.l, dn[:, k])
        de = 2 * (u * _along(lights.h, dt[:, k]) / (sx * sx) + v * _along(lights.h, dbt[:, k]) / (sy * sy)) * inv_z2 \
            - 2 * e * _along(lights.h, dn[:, k]) / zs
        dlog = -jnp.where(live, de, 0.0) - d_log_cr[k]   # d log(b)
        if model == "paper":
            dlog = dlog - jnp.where(cos_i > COS_FLOOR, dci, 0.0) / jnp.maximum(cos_i, COS_FLOOR)
        da.append(jnp.where(geo & (cos_i > 0), dci, 0.0))
        db.append(jnp.where(lit, b * dlog, 0.0))
    for k, (w, s, ds) in ((2, (u, sx, dsx)), (3, (v, sy, dsy))):
        de = -2 * w * w / (s * s * s) * ds[k] * inv_z2
        db.append(jnp.where(lit & live, -b * de, 0.0))
    return a, b, jnp.stack(da), jnp.stack(db)


# ---------------------------------------------------------------------------------------------
# rho projected out

class Prior(NamedTuple):
    """Gaussian prior on a texel's lobe: amplitude `rho_s` (3) with weight `rho_weight`, log-slopes
    `s` (2, the solver's s_x, s_y) with weight `s_weight` (weights in the cost's units: noise
    variance / prior variance). Weights 0: no prior."""

    rho_s: Float[Array, "3"]
    rho_weight: Float[Array, ""]
    s: Float[Array, "2"]
    s_weight: Float[Array, ""]


def _prior_terms(prior: Prior | None, hbr, lam):
    """(extra weight on rho_s, shifted h_b) of the projection under `prior`."""
    if prior is None:
        return jnp.zeros_like(lam), hbr
    return prior.rho_weight, hbr + prior.rho_weight * prior.rho_s


def _prior_value(prior: Prior | None, theta, rho_s):
    """0.5 k_rho |rho_s - mu|^2 + 0.5 k_s |s - s_mu|^2 (0 without a prior)."""
    if prior is None:
        return jnp.zeros((), theta.dtype)
    dr, ds = rho_s - prior.rho_s, theta[2:] - prior.s
    return 0.5 * prior.rho_weight * jnp.sum(dr * dr) + 0.5 * prior.s_weight * jnp.sum(ds * ds)


def ridge_of(w: Float[Array, " L"], ridge: float = RIDGE) -> Float[Array, ""]:
    """lam of the penalty 0.5 lam |rho|^2 added to the cost: `ridge` per unit of observation
    weight (a, b are O(1): ~1e-7 of the normal equations' diagonal), plus a tiny floor.

    It keeps the 2 x 2 systems definite where the specular column vanishes (sigma -> 0) and
    bounds rho_s on a texel whose lobe is seen by a single light (else a mirror lobe of unbounded
    rho_s fits that one observation exactly). It is constant in theta, so the penalized
    objective's theta-gradient at the projected rho is the data term's (the envelope theorem),
    which is what `gauss_newton` returns.
    """
    return ridge * jnp.sum(w) + jnp.asarray(jnp.finfo(w.dtype).tiny ** 0.5, w.dtype)


def nnls2(saa, sab, sbb, har, hbr, lam, lam_s=0.0):
    """Per channel: argmin_{x >= 0} x^T (G + diag(lam, lam + lam_s)) x - 2 h^T x with
    G = [[saa, sab], [sab, sbb]] (`lam_s`: a prior's extra weight on rho_s, `Prior`).

    The closed form of a 2-variable NNLS: the unconstrained solution when it is feasible, else
    the better of the two clamped one-variable solutions. Returns (rho_d, rho_s).
    """
    gaa, gbb = saa + lam, sbb + lam + lam_s
    det = jnp.maximum(gaa * gbb - sab * sab, lam * lam)  # Cauchy-Schwarz: det >= lam^2 in exact arithmetic
    xd = (gbb * har - sab * hbr) / det
    xs = (gaa * hbr - sab * har) / det
    both = (xd >= 0) & (xs >= 0)
    d_only = jnp.maximum(har / gaa, 0.0)
    s_only = jnp.maximum(hbr / gbb, 0.0)
    q_d = gaa * d_only * d_only - 2 * har * d_only   # x^T G x - 2 h^T x of the two one-variable candidates
    q_s = gbb * s_only * s_only - 2 * hbr * s_only
    pick_d = q_d <= q_s
    zero = jnp.zeros_like(xd)
    rho_d = jnp.where(both, xd, jnp.where(pick_d, d_only, zero))
    rho_s = jnp.where(both, xs, jnp.where(pick_d, zero, s_only))
    return rho_d, rho_s


def centre(w, ambient, *rows):
    """Rows minus `ambient` times their w-weighted means: with `ambient` = 1 a constant column (an
    ambient term per channel, free in sign) is projected out of the fit; with 0 nothing changes."""
    total = jnp.maximum(jnp.sum(w), jnp.finfo(w.dtype).tiny)

    def one(x):
        wx = jnp.reshape(w, (1,) * (x.ndim - 1) + w.shape) * x
        return x - ambient * (jnp.sum(wx, axis=-1, keepdims=True) / total)

    return [one(x) for x in rows]


def _sums(a, b, ratio_cl, w):
    wa, wb = w * a, w * b
    har = jnp.stack([jnp.sum(ratio_cl[c] * wa) for c in range(3)])   # row sums: batched matvecs are slow on CPU
    hbr = jnp.stack([jnp.sum(ratio_cl[c] * wb) for c in range(3)])
    return wa, wb, jnp.sum(wa * a), jnp.sum(wa * b), jnp.sum(wb * b), har, hbr


def project_rho_columns(a: Float[Array, " L"], b: Float[Array, " L"], ratio_cl: Float[Array, "3 L"],
                        w: Float[Array, " L"], *, ridge: float = RIDGE,
                        prior: Prior | None = None) -> tuple[Float[Array, "3"], Float[Array, "3"]]:
    """The best non-negative (rho_d, rho_s) per channel for columns a, b (see `nnls2`, `ridge_of`)."""
    _, _, saa, sab, sbb, har, hbr = _sums(a, b, ratio_cl, w)
    lam = ridge_of(w, ridge)
    lam_s, hbr = _prior_terms(prior, hbr, lam)
    return nnls2(saa, sab, sbb, har, hbr, lam, lam_s)


def projected_cost_offset(theta: Float[Array, "4"], ratio_cl: Float[Array, "3 L"], w: Float[Array, " L"],
                          lights: Lights, model: str, prior: Prior | None = None, *,
                          ambient=None) -> Float[Array, ""]:
    return projected_cost_offset_and_rho_d(theta, ratio_cl, w, lights, model, prior, ambient=ambient)[0]


def projected_cost_offset_and_rho_d(theta: Float[Array, "4"], ratio_cl: Float[Array, "3 L"], w: Float[Array, " L"],
                                    lights: Lights, model: str, prior: Prior | None = None, *,
                                    ambient=None) -> tuple[Float[Array, ""], Float[Array, "3"]]:
    """2 * projected objective - sum w R^2 = sum_c (rho_c^T (G + lam) rho_c - 2 rho_c^T h_c), from the sums of
    one pass (no residuals): enough to rank starting points (it cancels where the fit is close,
    so it is not the cost itself). With a `prior`, its terms are included (twice, as the rest)."""
    a, b = columns(theta, lights, model)
    if ambient is not None:
        a, b, ratio_cl = centre(w, ambient, a, b, ratio_cl)
    _, _, saa, sab, sbb, har, hbr = _sums(a, b, ratio_cl, w)
    lam = ridge_of(w)
    if prior is None:
        rd, rs = nnls2(saa, sab, sbb, har, hbr, lam)
        return jnp.sum((saa + lam) * rd * rd + 2 * sab * rd * rs + (sbb + lam) * rs * rs
                       - 2 * (rd * har + rs * hbr)), rd
    lam_s, hbr_p = _prior_terms(prior, hbr, lam)
    rd, rs = nnls2(saa, sab, sbb, har, hbr_p, lam, lam_s)
    data = jnp.sum((saa + lam) * rd * rd + 2 * sab * rd * rs + (sbb + lam) * rs * rs - 2 * (rd * har + rs * hbr))
    return data + 2 * _prior_value(prior, theta, rs), rd


def projected_objective(theta: Float[Array, "4"], ratio_cl: Float[Array, "3 L"], w: Float[Array, " L"], lights: Lights,
                        model: str, prior: Prior | None = None):
    """(objective, cost, rho_d, rho_s) at theta with the projected rho (`gauss_newton` without
    derivatives)."""
    a, b = columns(theta, lights, model)
    rho_d, rho_s = project_rho_columns(a, b, ratio_cl, w, prior=prior)
    cost = 0.0
    for c in range(3):
        r = ratio_cl[c] - rho_d[c] * a - rho_s[c] * b
        cost = cost + jnp.sum(w * r * r)
    cost = 0.5 * cost
    objective = cost + 0.5 * ridge_of(w) * jnp.sum(rho_d * rho_d + rho_s * rho_s) + _prior_value(prior, theta, rho_s)
    return objective, cost, rho_d, rho_s


# ---------------------------------------------------------------------------------------------
# Gauss-Newton quantities of the projected cost

class GaussNewton(NamedTuple):
    objective: Float[Array, ""]   # cost + 0.5 lam |rho|^2: what the solvers minimize
    cost: Float[Array, ""]        # 0.5 sum w (R - model)^2
    grad: Float[Array, "4"]
    matrix: Float[Array, "4 4"]
    rho_d: Float[Array, "3"]
    rho_s: Float[Array, "3"]


def gauss_newton(theta: Float[Array, "4"], ratio_cl: Float[Array, "3 L"], w: Float[Array, " L"], lights: Lights,
                 model: str, prior: Prior | None = None, *, ambient=None) -> GaussNewton:
    """Cost, exact gradient and Kaufman Gauss-Newton matrix of the projected cost (module docstring)."""
    a, b, da, db = columns_and_derivatives(theta, lights, model)
    if ambient is not None:
        a, b, da, db, ratio_cl = centre(w, ambient, a, b, da, db, ratio_cl)
    wa, wb, saa, sab, sbb, har, hbr = _sums(a, b, ratio_cl, w)   # G and h of the projection
    lam = ridge_of(w)
    lam_s, hbr_p = _prior_terms(prior, hbr, lam)
    rho_d, rho_s = nnls2(saa, sab, sbb, har, hbr_p, lam, lam_s)
    # sums of the derivative rows with the columns and with each other
    x = [da[0], da[1], None, None]   # da/ds = 0
    y = [db[0], db[1], db[2], db[3]]

    def s(p, q):
        return jnp.zeros((), a.dtype) if p is None or q is None else jnp.sum(w * p * q)

    a_dx = jnp.stack([jnp.sum(wa * xi) if xi is not None else jnp.zeros((), a.dtype) for xi in x])
    b_dx = jnp.stack([jnp.sum(wb * xi) if xi is not None else jnp.zeros((), a.dtype) for xi in x])
    a_dy = jnp.stack([jnp.sum(wa * yi) for yi in y])
    b_dy = jnp.stack([jnp.sum(wb * yi) for yi in y])
    sxx = jnp.stack([jnp.stack([s(p, q) for q in x]) for p in x])
    sxy = jnp.stack([jnp.stack([s(p, q) for q in y]) for p in x])
    syy = [[None] * 4 for _ in range(4)]
    for i in range(4):
        for j in range(i + 1):
            syy[i][j] = syy[j][i] = jnp.sum(w * y[i] * y[j])
    syy = jnp.stack([jnp.stack(row) for row in syy])
    # full Gauss-Newton blocks at the projected rho, then the Schur complement over the free rho
    sdd, sds, sss = jnp.sum(rho_d * rho_d), jnp.sum(rho_d * rho_s), jnp.sum(rho_s * rho_s)
    m = sdd * sxx + sds * (sxy + sxy.T) + sss * syy
    free_d, free_s = rho_d > 0, rho_s > 0
    gab = jnp.where(free_d & free_s, sab, 0.0)   # (3,): the pair is coupled only when both are free
    gaa, gbb = saa + lam, sbb + lam + lam_s
    det = jnp.maximum(gaa * gbb - gab * gab, lam * lam)
    for c in range(3):
        cd = jnp.where(free_d[c], rho_d[c] * a_dx + rho_s[c] * a_dy, 0.0)   # (4,) coupling of rho_d_c
        cs = jnp.where(free_s[c], rho_d[c] * b_dx + rho_s[c] * b_dy, 0.0)
        m = m - (gbb * jnp.outer(cd, cd) - gab[c] * (jnp.outer(cd, cs) + jnp.outer(cs, cd))
                 + gaa * jnp.outer(cs, cs)) / det[c]
    # residuals at the projected rho: cost and the exact gradient
    r = [ratio_cl[c] - rho_d[c] * a - rho_s[c] * b for c in range(3)]
    cost = 0.5 * jnp.sum(w * (r[0] * r[0] + r[1] * r[1] + r[2] * r[2]))
    objective = cost + 0.5 * lam * (sdd + sss)
    wed = w * (rho_d[0] * r[0] + rho_d[1] * r[1] + rho_d[2] * r[2])
    wes = w * (rho_s[0] * r[0] + rho_s[1] * r[1] + rho_s[2] * r[2])
    grad = -jnp.stack([jnp.sum(wed * x[k] + wes * y[k]) if x[k] is not None else jnp.sum(wes * y[k]) for k in range(4)])
    if prior is not None:   # the slope prior: value, gradient and curvature (the rho prior is in the projection)
        objective = objective + _prior_value(prior, theta, rho_s)
        grad = grad + jnp.concatenate([jnp.zeros(2, grad.dtype), prior.s_weight * (theta[2:] - prior.s)])
        m = m + prior.s_weight * jnp.diag(jnp.asarray([0.0, 0.0, 1.0, 1.0], m.dtype))
    return GaussNewton(objective, cost, grad, 0.5 * (m + m.T), rho_d, rho_s)

"""The strong scipy peer of benchmarks/fit_speed.py: what a user who knows scipy writes for one
texel. The model is linear in rho_d and rho_s (per channel R = cos_i rho_d + spec rho_s), so they
are projected out (variable projection, Golub & Pereyra 1973): `least_squares` sees only the four
geometry parameters (p, q, s_x, s_y), with the analytic Jacobian of the projected residual
(the full Golub-Pereyra form, derivatives of the basis by hand), same start as the naive peer.
"""

from __future__ import annotations

import numpy as np
import scipy.optimize

from jaxrender.brdf import SIGMA_FLOOR

S_MIN, S_MAX = -12.0, 3.0  # the clip of fit_speed.numpy_model


def basis_and_derivatives(theta, light_dirs, view_dir):
    """B (L 2) = [cos_i, spec] of the model for theta = (p, q, s_x, s_y), and dB/dtheta (4 L 2)."""
    p, q, s_x, s_y = theta
    u = np.array([p, q, 1.0])
    m = np.linalg.norm(u)
    n = u / m
    dn = np.stack([(np.eye(3)[0] - n * n[0]) / m, (np.eye(3)[1] - n * n[1]) / m, np.zeros(3), np.zeros(3)])  # 4 3
    tp = np.array([1.0, 0.0, 0.0]) - n[0] * n
    tl = np.linalg.norm(tp)
    t = tp / tl
    dtp = -dn[:, :1] * n - n[0] * dn
    dt = (dtp - np.outer(dtp @ t, t)) / tl
    b = np.cross(n, t)
    db = np.cross(dn, t) + np.cross(n, dt)
    cx, cy = np.clip(s_x, S_MIN, S_MAX), np.clip(s_y, S_MIN, S_MAX)
    sx, sy = SIGMA_FLOOR + np.exp(cx), SIGMA_FLOOR + np.exp(cy)
    dsx = np.array([0, 0, np.exp(cx) if S_MIN < s_x < S_MAX else 0.0, 0])
    dsy = np.array([0, 0, 0, np.exp(cy) if S_MIN < s_y < S_MAX else 0.0])
    h = light_dirs + view_dir
    h = h / np.linalg.norm(h, axis=1, keepdims=True)
    hn, ht, hb = h @ n, h @ t, h @ b
    dhn, dht, dhb = dn @ h.T, dt @ h.T, db @ h.T  # 4 L
    front = hn > 1e-6
    hn_s = np.where(front, hn, 1.0)
    e = ((ht / sx) ** 2 + (hb / sy) ** 2) / hn_s**2
    de = ((2 * ht * dht / sx**2 - 2 * ht**2 * dsx[:, None] / sx**3 + 2 * hb * dhb / sy**2
           - 2 * hb**2 * dsy[:, None] / sy**3) / hn_s**2 - 2 * e * dhn / hn_s)
    d = np.where(front, np.exp(-np.minimum(e, 80.0)), 0.0)
    dd = np.where(front & (e < 80.0), -d * de, 0.0)
    cos_i, cos_r = light_dirs @ n, view_dir @ n
    dcos_i, dcos_r = dn @ light_dirs.T, dn @ view_dir  # 4 L, 4
    lit = (cos_i > 0) & (cos_r > 0)
    cr = max(cos_r, 1e-4)
    dcr = dcos_r if cos_r > 1e-4 else np.zeros(4)
    spec = np.where(lit, d / cr, 0.0)
    dspec = np.where(lit, dd / cr - d * dcr[:, None] / cr**2, 0.0)
    geo = (light_dirs[:, 2] > 0) & (view_dir[2] > 0)
    diff = np.where(geo, np.maximum(cos_i, 0.0), 0.0)
    ddiff = np.where(geo & (cos_i > 0), dcos_i, 0.0)
    basis = np.stack([diff, np.where(geo, spec, 0.0)], -1)
    dbasis = np.stack([ddiff, np.where(geo, dspec, 0.0)], -1)
    return basis, dbasis


def varpro_fit(ratio, weight, light_dirs, view_dir, x0):
    """Fit one texel: `ratio` (L 3), `weight` (L), x0 the naive peer's 10-vector start; returns
    (x (10,), scipy's result). Cost 0.5 sum w (R - model)^2 as the naive peer's."""
    w = weight / np.mean(weight[weight > 0]) if np.any(weight > 0) else weight
    sw = np.sqrt(w)
    y = sw[:, None] * ratio  # L 3
    cache = {}

    def solve(theta):
        key = theta.tobytes()
        if key not in cache:
            cache.clear()
            basis, dbasis = basis_and_derivatives(theta, light_dirs, view_dir)
            a = sw[:, None] * basis  # L 2
            da = sw[None, :, None] * dbasis  # 4 L 2
            qm, rm = np.linalg.qr(a)
            beta = np.linalg.lstsq(rm, qm.T @ y, rcond=None)[0]  # 2 3
            res = y - a @ beta  # L 3
            cache[key] = (a, da, qm, rm, beta, res)
        return cache[key]

    def residual(theta):
        return solve(theta)[5].T.ravel()

    def jacobian(theta):
        a, da, qm, rm, beta, res = solve(theta)
        cols = []
        for k in range(4):
            g = da[k] @ beta  # L 3: dA beta
            g -= qm @ (qm.T @ g)  # (I - P) dA beta
            rinv_t = np.linalg.lstsq(rm.T, da[k].T @ res, rcond=None)[0]  # R^-T dA^T r: 2 3
            g += qm @ rinv_t  # + (A^+)^T dA^T r
            cols.append(-g.T.ravel())
        return np.stack(cols, -1)

    sol = scipy.optimize.least_squares(residual, np.asarray(x0[6:], np.float64), jac=jacobian)
    beta = solve(sol.x)[4]
    return np.concatenate([beta[0], beta[1], sol.x]), sol

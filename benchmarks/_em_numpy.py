"""Peer for the EM pyramid benchmark: `fitting.em.em_texel` (nodes, 1-or-2 rule, grouped EM,
lobe conversion) written in batched numpy, vectorized over texels (a leading axis N), same dtype
as its input. Not part of the package."""

from __future__ import annotations

import functools
import math

import numpy as np

from fitting.em import DEFAULT_ITERATIONS, DEFAULT_ORDER, ONE_LOBE_TOLERANCE, TWO_LOBE_GAIN, VAR_FLOOR, VIRTUAL
from jaxrender.brdf import SIGMA_FLOOR

_HZ_FLOOR = 0.05
_TINY = 1e-30
_RECENTRE_STEPS = 4


def _normalize(v):
    n = np.sqrt(np.sum(v * v, axis=-1, keepdims=True))
    return v / np.where(n > 1e-12, n, 1.0)


def _tangent_frame(n):
    n = _normalize(n)
    x = np.zeros_like(n)
    x[..., 0] = 1
    t = x - np.sum(x * n, -1, keepdims=True) * n
    y = np.zeros_like(n)
    y[..., 1] = 1
    degenerate = np.sum(t * t, -1, keepdims=True) < 1e-12
    t = _normalize(np.where(degenerate, y - np.sum(y * n, -1, keepdims=True) * n, t))
    return t, np.cross(n, t), n


def _ise_terms(ma, mua, va, mb, mub, vb):
    v = va[:, :, None, :] + vb[:, None, :, :]
    d = mua[:, :, None, :] - mub[:, None, :, :]
    g = np.prod(np.exp(-0.5 * d * d / v) / np.sqrt(2 * np.pi * v), axis=-1)
    return np.einsum("nj,njk,nk->n", ma, g, mb)


def _relative_ise(p, q):
    pp = _ise_terms(*p, *p)
    ise = pp - 2 * _ise_terms(*p, *q) + _ise_terms(*q, *q)
    return np.maximum(ise, 0) / np.maximum(pp, _TINY)


def _log_components(x, means, variances):
    """x: N G Q 2; means, variances: N K 2 -> N G Q K."""
    d = x[:, :, :, None, :] - means[:, None, None, :, :]
    var = variances[:, None, None, :, :]
    return -0.5 * np.sum(np.log(2 * np.pi * var) + d * d / var, axis=-1)


def _e_step(x, qn, weights, means, variances):
    expected = VIRTUAL * np.einsum("ngq,ngqk->ngk", qn, _log_components(x, means, variances))
    log_p = expected + np.log(np.maximum(weights, _TINY))[:, None, :]
    top = np.max(log_p, axis=2, keepdims=True)
    lse = top[..., 0] + np.log(np.sum(np.exp(log_p - top), axis=2))
    return np.exp(log_p - lse[..., None]), lse


def em_fit_numpy(x, w, weights, means, variances, *, iterations, tol):
    """Grouped EM (fitting.em.em_fit with `virtual`=VIRTUAL) for N texels at once: x N G Q 2, w N G Q."""
    w = w / np.maximum(np.sum(w, axis=(1, 2), keepdims=True), _TINY)
    mass = np.sum(w, axis=2)
    qn = w / np.maximum(mass, _TINY)[..., None]
    n_tex = x.shape[0]
    previous = np.full(n_tex, -np.inf, x.dtype)
    current = np.full(n_tex, np.inf, x.dtype)
    count = np.zeros(n_tex, np.int32)
    for _ in range(iterations):
        active = ~(np.abs(current - previous) < tol)
        if not active.any():
            break
        resp, lse = _e_step(x, qn, weights, means, variances)
        rw = resp[:, :, None, :] * w[..., None]                                    # N G Q K
        n = np.sum(rw, axis=(1, 2))                                                # N K
        alive = n > _TINY
        safe_n = np.where(alive, n, 1.0)
        new_means = np.einsum("ngqk,ngqd->nkd", rw, x) / safe_n[..., None]
        d = x[:, :, :, None, :] - new_means[:, None, None, :, :]
        new_var = np.maximum(np.einsum("ngqk,ngqkd->nkd", rw, d * d) / safe_n[..., None], VAR_FLOOR)
        new_means = np.where(alive[..., None], new_means, means)
        new_var = np.where(alive[..., None], new_var, variances)
        new_weights = n / np.maximum(np.sum(n, axis=1, keepdims=True), _TINY)
        a = active[:, None]
        weights = np.where(a, new_weights, weights)
        means = np.where(a[..., None], new_means, means)
        variances = np.where(a[..., None], new_var, variances)
        previous, current = np.where(active, current, previous), np.where(active, np.sum(mass * lse, axis=1), current)
        count = count + active
    return weights, means, variances, count, np.abs(current - previous) < tol


def _component_lobes(h, w, e, resp, mean, mass):
    """h N G Q 3, w N G Q, e N G 3 (child lobes' energies), resp N G, mean N 2, mass N
    -> (rho_s N 3, normal N 3, sx N, sy N)."""
    n_tex = h.shape[0]
    rw = (resp[..., None] * w).reshape(n_tex, -1)
    h = h.reshape(n_tex, -1, 3)
    total = np.maximum(np.sum(rw, axis=1), _TINY)

    def frame_slopes(normal):
        t, b, n = _tangent_frame(normal)
        hn = np.maximum(np.einsum("nsd,nd->ns", h, n), _HZ_FLOOR)
        return t, b, n, np.einsum("nsd,nd->ns", h, t) / hn, np.einsum("nsd,nd->ns", h, b) / hn

    normal = _normalize(np.concatenate([mean, np.ones_like(mean[:, :1])], axis=1))
    for _ in range(_RECENTRE_STEPS):
        t, b, n, p, q = frame_slopes(normal)
        mp, mq = np.sum(rw * p, 1) / total, np.sum(rw * q, 1) / total
        normal = _normalize(n + mp[:, None] * t + mq[:, None] * b)
    _, _, _, p, q = frame_slopes(normal)
    sx = np.maximum(np.sqrt(2 * np.sum(rw * p * p, 1) / total), SIGMA_FLOOR)
    sy = np.maximum(np.sqrt(2 * np.sum(rw * q * q, 1) / total), SIGMA_FLOOR)
    energy = np.einsum("ng,ngc->nc", resp, e)
    denom = (mass * np.pi * sx * sy)[:, None]
    rho_s = np.where(denom > _TINY, energy / np.maximum(denom, _TINY), 0)
    return rho_s.astype(h.dtype), normal.astype(h.dtype), sx.astype(h.dtype), sy.astype(h.dtype)


def em_texels_numpy(children: dict, *, order=DEFAULT_ORDER, iterations=DEFAULT_ITERATIONS, tol=None):
    """`children`: numpy arrays with leading axes N 4 (rho_d N 4 3, lobe0/lobe1 rho_s, normal,
    sigma_x, sigma_y, weight N 4). Returns a dict of the coarse texel's fields (leading axis N)."""
    dtype = children["weight"].dtype
    if tol is None:
        tol = 1e-5 if dtype == np.float32 else 1e-10
    if not np.any(children["weight"]):   # one-lobe children (as fitting.em): lobe 1 carries no mass, skip it
        cat = lambda k: children["lobe0"][k]  # noqa: E731
        mass_l = 0.25 * (1 - children["weight"])                                               # N 4
    else:
        cat = lambda k: np.concatenate([children["lobe0"][k], children["lobe1"][k]], axis=1)  # noqa: E731
        mass_l = 0.25 * np.concatenate([1 - children["weight"], children["weight"]], axis=1)   # N 8
    normal, sx_c, sy_c, rho_s = cat("normal"), cat("sigma_x"), cat("sigma_y"), cat("rho_s")  # N 8 (or 4) ...
    nodes, gw = np.polynomial.hermite.hermgauss(order)
    a, b = (g.ravel().astype(dtype) for g in np.meshgrid(nodes, nodes, indexing="ij"))
    qw = (np.outer(gw, gw).ravel() / math.pi).astype(dtype)
    t, bt, n = _tangent_frame(normal)
    sx = np.maximum(sx_c, SIGMA_FLOOR)
    sy = np.maximum(sy_c, SIGMA_FLOOR)
    # (t, bt, n) is orthonormal: |u t + v bt + n|^2 = 1 + u^2 + v^2 (as fitting.em)
    u, v = a[None, None, :] * sx[..., None], b[None, None, :] * sy[..., None]                       # N 8 Q
    h = (u[..., None] * t[:, :, None, :] + v[..., None] * bt[:, :, None, :] + n[:, :, None, :]) \
        / np.sqrt(1 + u * u + v * v)[..., None]                                             # N 8 Q 3
    hz = np.maximum(h[..., 2], _HZ_FLOOR)
    x = h[..., :2] / hz[..., None]
    # A child lobe's nodes share its energy in the proportions qw (summing to 1): per-lobe energies
    # and moments carry everything (as fitting.em).
    e = (mass_l * np.pi * sx * sy)[..., None] * rho_s                                      # N 8 3
    mass = np.mean(e, axis=-1) + dtype.type(1e-20) * mass_l                                # N 8
    w = qw[None, None, :] * mass[..., None]                                                # N 8 Q
    # p, the one-lobe moment match, init
    total = np.maximum(np.sum(mass, axis=1), _TINY)
    mu = np.einsum("q,njqd->njd", qw, x)
    dev = x - mu[:, :, None, :]
    raw = np.einsum("q,njqd->njd", qw, dev * dev)
    var = np.maximum(raw, VAR_FLOOR)
    frac = mass / total[:, None]
    p = (frac, mu, var)
    n_tex = w.shape[0]
    idx = np.arange(n_tex)
    j1 = np.argmax(mass, axis=1)
    d2 = np.sum((mu - mu[idx, j1][:, None]) ** 2 / (var + var[idx, j1][:, None]), axis=-1)
    j2 = np.argmax(mass * d2, axis=1)
    one_mean = np.einsum("nj,njd->nd", frac, mu)
    one_var = np.maximum(np.einsum("nj,njd->nd", frac, raw + (mu - one_mean[:, None]) ** 2), VAR_FLOOR)
    ones = np.ones((n_tex, 1), dtype)
    error_one = _relative_ise(p, (ones, one_mean[:, None], one_var[:, None]))
    run = error_one > ONE_LOBE_TOLERANCE
    # EM on the texels that need it (a numpy programmer's subset; the others keep their init).
    weights = np.full((n_tex, 2), 0.5, dtype)
    means = np.stack([mu[idx, j1], mu[idx, j2]], axis=1)
    variances = np.stack([var[idx, j1], var[idx, j2]], axis=1)
    iters = np.zeros(n_tex, np.int32)
    if run.any():
        wr, mr, vr, ir, _ = em_fit_numpy(x[run], w[run], weights[run], means[run], variances[run],
                                         iterations=iterations, tol=tol)
        weights[run], means[run], variances[run], iters[run] = wr, mr, vr, ir
    # The EM mixture's error, responsibilities and minor lobe only where they are used (the JAX
    # kernel skips them per block of texels where no texel needs them).
    error_two = error_one.copy()
    error_two[run] = _relative_ise(tuple(a[run] for a in p), (weights[run], means[run], variances[run]))
    two = run & (error_two < TWO_LOBE_GAIN * error_one)
    k0 = np.argmax(weights, axis=1)
    k1 = 1 - k0
    # Lobe 0 (the major component where two lobes are kept, else the single summary), then the
    # minor component's lobe where two are kept.
    first_resp = np.ones(mass.shape, dtype)
    first_mean = one_mean.copy()
    first_mass = np.ones(n_tex, dtype)
    if two.any():
        resp, _ = _e_step(x[two], w[two] / np.maximum(np.sum(w[two], 2, keepdims=True), _TINY), weights[two],
                          means[two], variances[two])
        it = np.arange(int(two.sum()))
        first_resp[two] = resp[it, :, k0[two]]
        first_mean[two] = means[two, k0[two]]
        first_mass[two] = weights[two, k0[two]]
    lobe0 = _component_lobes(h, w, e, first_resp, first_mean, first_mass)
    lobe1 = tuple(u.copy() for u in lobe0)
    if two.any():
        minor = _component_lobes(h[two], w[two], e[two], resp[it, :, k1[two]], means[two, k1[two]],
                                 weights[two, k1[two]])
        for u, m in zip(lobe1, minor):
            u[two] = m
    weight = np.where(two, weights[idx, k1], 0).astype(dtype)
    names = ("rho_s", "normal", "sigma_x", "sigma_y")
    return {"rho_d": np.mean(children["rho_d"], axis=1), "lobe0": dict(zip(names, lobe0)),
            "lobe1": dict(zip(names, lobe1)), "weight": weight, "two_lobes": two, "iterations": iters}


def gather_children_numpy(level: dict) -> dict:
    """`H W` fields -> `h*w 4` children (edge padding as downsample2), flattened row-major."""
    def one(arr):
        hh, ww = arr.shape[:2]
        pad = ((0, hh % 2), (0, ww % 2)) + ((0, 0),) * (arr.ndim - 2)
        arr = np.pad(arr, pad, mode="edge")
        out = np.stack([arr[0::2, 0::2], arr[1::2, 0::2], arr[0::2, 1::2], arr[1::2, 1::2]], axis=2)
        return out.reshape((-1, 4) + out.shape[3:])
    return {k: (one(v) if not isinstance(v, dict) else {kk: one(vv) for kk, vv in v.items()}) for k, v in level.items()}


def pyramid_numpy(level0: dict, *, iterations=DEFAULT_ITERATIONS) -> list[dict]:
    """Every EM level of the pyramid from level 0 (dict of `H W` numpy fields, like BTFTexel)."""
    levels, current = [], level0
    while max(current["weight"].shape[:2]) > 1:
        hh, ww = (s // 2 + s % 2 for s in current["weight"].shape[:2])
        out = em_texels_numpy(gather_children_numpy(current), iterations=iterations)
        current = {k: (v.reshape((hh, ww) + v.shape[1:]) if not isinstance(v, dict)
                       else {kk: vv.reshape((hh, ww) + vv.shape[1:]) for kk, vv in v.items()})
                   for k, v in out.items() if k in ("rho_d", "lobe0", "lobe1", "weight")}
        levels.append(current)
    return levels


def _split(d, parts: int):
    """A dict of arrays (or dicts of arrays) with a leading texel axis N, cut into `parts` pieces."""
    n = d["weight"].shape[0]
    cuts = np.linspace(0, n, parts + 1).astype(int)
    piece = lambda v, a, b: v[a:b] if not isinstance(v, dict) else {k: x[a:b] for k, x in v.items()}  # noqa: E731
    return [{k: piece(v, a, b) for k, v in d.items()} for a, b in zip(cuts[:-1], cuts[1:])]


def _join(pieces):
    first = pieces[0]
    return {k: (np.concatenate([p[k] for p in pieces]) if not isinstance(v, dict)
                else {kk: np.concatenate([p[k][kk] for p in pieces]) for kk in v})
            for k, v in first.items() if k in ("rho_d", "lobe0", "lobe1", "weight")}


def _em_texels_cpu(children: dict, iterations: int) -> tuple[dict, float]:
    """em_texels_numpy in a pool worker, with the worker's CPU seconds (the parent cannot see them)."""
    import time

    start = time.process_time()
    out = em_texels_numpy(children, iterations=iterations)
    return out, time.process_time() - start


def pyramid_numpy_pool(level0: dict, pool, processes: int, *, iterations=DEFAULT_ITERATIONS,
                       min_split: int = 256, worker_cpu: list | None = None) -> list[dict]:
    """`pyramid_numpy` with each level's texels split between the processes of `pool` (a
    multiprocessing pool, one process per core): the peer allowed as many cores as JAX. Levels with
    fewer than `min_split` texels stay in this process (sending them costs more than it saves).
    The workers' CPU seconds of this call are appended to `worker_cpu` if given."""
    levels, current, cpu = [], level0, 0.0
    while max(current["weight"].shape[:2]) > 1:
        hh, ww = (s // 2 + s % 2 for s in current["weight"].shape[:2])
        children = gather_children_numpy(current)
        if hh * ww >= min_split:
            done = pool.map(functools.partial(_em_texels_cpu, iterations=iterations), _split(children, processes))
            out = _join([o for o, _ in done])
            cpu += sum(c for _, c in done)
        else:
            out = em_texels_numpy(children, iterations=iterations)
        current = {k: (v.reshape((hh, ww) + v.shape[1:]) if not isinstance(v, dict)
                       else {kk: vv.reshape((hh, ww) + vv.shape[1:]) for kk, vv in v.items()})
                   for k, v in out.items() if k in ("rho_d", "lobe0", "lobe1", "weight")}
        levels.append(current)
    if worker_cpu is not None:
        worker_cpu.append(cpu)
    return levels

"""EM multi-resolution BTF (paper 004, section 3.2): a texel of level l+1 summarizes the specular
slope distributions of its 4 children as a mixture of at most 2 anisotropic lobes, fitted by
hierarchical EM over Gauss-Hermite nodes in slope space; rho_d is averaged. Batched over texels
with the texel axis last; `em_texel` is the one-texel call. How it works (slope space, energy
weights, the 1-or-2-lobe rule, back to lobes) and why: docs/fitting.md, "The EM pyramid".
"""

from __future__ import annotations

import functools
import math
import threading

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jaxrender.brdf import SIGMA_FLOOR, BTFTexel, Lobe
from jaxrender.maths import normalize, sum_short

__all__ = ["GaussianMixture", "EMInfo", "em_fit", "weighted_log_likelihood", "moment_match", "lobe_slope_nodes",
           "em_texel", "em_texels", "moment_matched_texel", "moment_matched_texels", "mip_texel", "gather_children",
           "em_downsample", "compile_ahead", "ONE_LOBE_TOLERANCE", "TWO_LOBE_GAIN", "DEFAULT_ORDER",
           "DEFAULT_ITERATIONS"]

ONE_LOBE_TOLERANCE = 0.01  # relative ISE of the one-lobe summary above which a second lobe is considered
TWO_LOBE_GAIN = 0.5        # the two-lobe fit must at least halve the one-lobe ISE
VIRTUAL = 16.0             # virtual samples per child lobe in the texel E-step (hierarchical EM)
DEFAULT_ORDER = 3          # Gauss-Hermite nodes per axis and child lobe (exact moments up to degree 5)
DEFAULT_ITERATIONS = 50
VAR_FLOOR = 0.5 * SIGMA_FLOOR**2  # the slope variance of the narrowest lobe the BRDF represents
_HZ_FLOOR = 0.05                  # half vectors flatter than this are clamped (slopes <= 20)
_TINY = 1e-30
_RECENTRE_STEPS = 4         # fixed-point steps putting a lobe's normal at its nodes' mean slope


class GaussianMixture(eqx.Module):
    """K Gaussians with diagonal covariance in 2-D slope space (leading batch axes allowed)."""

    weights: Float[Array, "... K"]
    means: Float[Array, "... K 2"]
    variances: Float[Array, "... K 2"]


class EMInfo(eqx.Module):
    """Diagnostics of one coarse texel's fit."""

    iterations: Int[Array, "..."]
    converged: Bool[Array, "..."]
    two_lobes: Bool[Array, "..."]
    error_one: Float[Array, "..."]   # relative ISE of the one-lobe summary
    error_two: Float[Array, "..."]   # relative ISE of the EM mixture (= error_one where EM did not run)
    log_likelihood: Float[Array, "..."]  # of the EM mixture (0 where EM did not run)


# --------------------------------------------------------------------------------------------
# Layout. XLA on CPU reduces short minor axes (2, 3, 9 nodes) very slowly, so the kernels below
# work on structure-of-arrays data with the texel (problem) axis N LAST: coordinates as separate
# arrays, nodes as `G Q N`, mixture parameters as `K N`. The whole per-texel computation is still
# elementwise in N (texels never interact); the single-texel functions call it with N = 1.


def _normalize3(x, y, z):
    sq = x * x + y * y + z * z
    positive = sq > 1e-24
    inv = jnp.where(positive, jax.lax.rsqrt(jnp.where(positive, sq, 1.0)), 1.0)  # one reciprocal, 3 products
    return x * inv, y * inv, z * inv


def _tangent_frame3(nx, ny, nz):
    """`jaxrender.brdf.tangent_frame` in components: T = x projected onto N's plane, B = N x T."""
    nx, ny, nz = _normalize3(nx, ny, nz)
    tx, ty, tz = 1 - nx * nx, -nx * ny, -nx * nz
    degenerate = tx * tx + ty * ty + tz * tz < 1e-12
    tx, ty, tz = (jnp.where(degenerate, a, b) for a, b in zip((-ny * nx, 1 - ny * ny, -ny * nz), (tx, ty, tz)))
    tx, ty, tz = _normalize3(tx, ty, tz)
    return (tx, ty, tz), (ny * tz - nz * ty, nz * tx - nx * tz, nx * ty - ny * tx), (nx, ny, nz)


def _logsumexp0(a):
    top = jnp.max(a, axis=0)
    safe = jnp.where(jnp.isfinite(top), top, 0.0)
    return safe + jnp.log(jnp.sum(jnp.exp(a - safe[None]), axis=0))


# --------------------------------------------------------------------------------------------
# Weighted (grouped) EM for diagonal Gaussian mixtures, batched over a trailing axis


def _e_step(x0, x1, qn, params, virtual):
    """Responsibilities `G K N` of each group and log sum_k per group `G N`."""
    pi, m0, m1, v0, v1 = params
    log_norm = -0.5 * (jnp.log(2 * jnp.pi * v0) + jnp.log(2 * jnp.pi * v1))
    h0, h1 = 0.5 / v0, 0.5 / v1  # reciprocals on K N: no division per node

    def term(j):  # node j of every group: G K N (the sum over the short node axis written out)
        d0 = x0[:, j, None, :] - m0[None]
        d1 = x1[:, j, None, :] - m1[None]
        return qn[:, j, None, :] * (log_norm[None] - (d0 * d0 * h0[None] + d1 * d1 * h1[None]))

    ell = virtual * sum(term(j) for j in range(x0.shape[1])) + jnp.log(jnp.maximum(pi, _TINY))[None]  # G K N
    lse = _logsumexp0(jnp.moveaxis(ell, 1, 0))                                                    # G N
    return jnp.exp(ell - lse[:, None, :]), lse


def _m_step(x0, x1, w, resp, params, var_floor):
    rw = resp[:, None, :, :] * w[:, :, None, :]                                                  # G Q K N
    # sum_short (written-out adds fused into one pass) measured faster than reductions here and in
    # `_component_lobes` and `_ise_terms`, slower for the node moments in `_texels_kernel`
    n = sum_short(rw, axis=(0, 1))                                                                # K N
    alive = n > _TINY
    safe_n = jnp.where(alive, n, 1.0)
    m0 = sum_short(rw * x0[:, :, None, :], axis=(0, 1)) / safe_n
    m1 = sum_short(rw * x1[:, :, None, :], axis=(0, 1)) / safe_n
    d0 = x0[:, :, None, :] - m0[None, None]
    d1 = x1[:, :, None, :] - m1[None, None]
    v0 = jnp.maximum(sum_short(rw * d0 * d0, axis=(0, 1)) / safe_n, var_floor)
    v1 = jnp.maximum(sum_short(rw * d1 * d1, axis=(0, 1)) / safe_n, var_floor)
    _, om0, om1, ov0, ov1 = params
    keep = lambda new, old: jnp.where(alive, new, old)  # noqa: E731
    pi = n / jnp.maximum(jnp.sum(n, axis=0), _TINY)[None]
    return pi, keep(m0, om0), keep(m1, om1), keep(v0, ov0), keep(v1, ov1)


def _em_core(x0, x1, w, params, *, iterations, tol, var_floor, virtual, run):
    """EM on `N` independent problems: nodes `G Q N`, parameters `K N`, `run` `N` (problems not run
    count as converged).
    Returns (parameters, log-likelihood N, iterations N, converged N, responsibilities G K N)."""
    w = w / jnp.maximum(jnp.sum(w, axis=(0, 1)), _TINY)[None, None]
    mass = sum_short(w, axis=1)                                                                     # G N
    qn = w / jnp.maximum(mass, _TINY)[:, None, :]

    def loglik(lse):
        return jnp.sum(mass * lse, axis=0)

    n = x0.shape[-1]
    inf = jnp.full((n,), jnp.inf, x0.dtype)

    def active(previous, current):
        return run & ~(jnp.abs(current - previous) < tol)

    def cond(state):
        i, _, previous, current, _ = state
        return (i < iterations) & jnp.any(active(previous, current))

    def step(state):
        i, params, previous, current, count = state
        go = active(previous, current) & (i < iterations)
        resp, lse = _e_step(x0, x1, qn, params, virtual)
        new = _m_step(x0, x1, w, resp, params, var_floor)
        params = tuple(jnp.where(go[None], a, b) for a, b in zip(new, params))
        previous, current = jnp.where(go, current, previous), jnp.where(go, loglik(lse), current)
        return i + 1, params, previous, current, count + go.astype(jnp.int32)

    body = step

    state = (jnp.zeros((), jnp.int32), tuple(params), -inf, inf, jnp.zeros((n,), jnp.int32))
    _, params, previous, current, count = jax.lax.while_loop(cond, body, state)
    resp, lse = _e_step(x0, x1, qn, params, virtual)
    return params, loglik(lse), count, ~run | (jnp.abs(current - previous) < tol), resp


def _grouped(x, w):
    x = jnp.asarray(x)
    w = jnp.asarray(w, dtype=x.dtype)
    if x.ndim == 2:  # plain samples: every sample its own group
        return x[:, None, :], w[:, None]
    return x, w


def _to_soa(x, w, gmm: GaussianMixture | None = None):
    x, w = _grouped(x, w)
    out = (x[..., 0][..., None], x[..., 1][..., None], w[..., None])
    if gmm is None:
        return out
    gmm = jax.tree.map(lambda a: jnp.asarray(a, dtype=x.dtype), gmm)
    params = (gmm.weights[:, None], gmm.means[:, 0][:, None], gmm.means[:, 1][:, None],
              gmm.variances[:, 0][:, None], gmm.variances[:, 1][:, None])
    return out, params


def _from_params(params) -> GaussianMixture:
    pi, m0, m1, v0, v1 = (a[..., 0] for a in params)
    return GaussianMixture(pi, jnp.stack([m0, m1], axis=-1), jnp.stack([v0, v1], axis=-1))


def weighted_log_likelihood(x: Float[Array, "S 2"] | Float[Array, "G Q 2"], w: Float[Array, " S"] | Float[Array, "G Q"],
                            gmm: GaussianMixture, *, virtual: float = 1.0) -> Float[Array, ""]:
    """sum_i w_i log sum_k pi_k N(x_i; mu_k, diag var_k) / sum_i w_i for plain samples (`S 2`);
    for grouped samples (`G Q 2`) the per-group terms use the group's weighted mean log-density."""
    (x0, x1, w), params = _to_soa(x, w, gmm)
    w = w / jnp.maximum(jnp.sum(w), _TINY)
    mass = jnp.sum(w, axis=1)
    _, lse = _e_step(x0, x1, w / jnp.maximum(mass, _TINY)[:, None, :], params, virtual)
    return jnp.sum(mass * lse)


def em_fit(x: Float[Array, "S 2"] | Float[Array, "G Q 2"], w: Float[Array, " S"] | Float[Array, "G Q"],
           init: GaussianMixture, *, iterations: int = DEFAULT_ITERATIONS, tol: float | None = None,
           var_floor: float = VAR_FLOOR, run: Bool[Array, ""] | bool = True, virtual: float = 1.0,
           ) -> tuple[GaussianMixture, Float[Array, ""], Int[Array, ""], Bool[Array, ""]]:
    """Weighted EM for a diagonal Gaussian mixture from `init`: at most `iterations` E+M steps,
    stopping once the weighted mean log-likelihood changes by less than `tol` (default 1e-5 in
    float32, 1e-10 in float64); `run=False` returns `init`.

    Plain samples `S 2` (weights `S`): the textbook EM (as scikit-learn's, with weights).
    Grouped samples `G Q 2` (weights `G Q`): the nodes of one group (a child lobe's quadrature
    nodes) share one responsibility, computed from the group's weighted mean log-density, which
    is the expected log-density under the child lobe, multiplied by `virtual` (hierarchical EM
    with `virtual` virtual samples per group): a lobe is never split between components, and EM
    cannot overfit the node lattice.

    Returns (mixture, weighted mean log-likelihood of the returned mixture, iterations, converged).
    Zero-weight samples are ignored; a component that loses all its mass keeps its mean and
    variance with weight 0 (no NaN). The same core runs the texel kernel, batched over texels.
    """
    (x0, x1, w), params = _to_soa(x, w, init)
    if tol is None:
        tol = 1e-5 if x0.dtype == jnp.float32 else 1e-10
    params, loglik, count, converged, _ = _em_core(x0, x1, w, params, iterations=iterations, tol=tol,
                                                   var_floor=var_floor, virtual=virtual,
                                                   run=jnp.reshape(jnp.asarray(run), (1,)))
    return _from_params(params), loglik[0], count[0], converged[0]


def moment_match(x: Float[Array, "S 2"], w: Float[Array, " S"], *, var_floor: float = VAR_FLOOR) -> GaussianMixture:
    """The one-component maximum-likelihood fit: weighted mean and variance (K = 1)."""
    w = w / jnp.maximum(jnp.sum(w), _TINY)
    mean = jnp.sum(w[:, None] * x, axis=0)
    d = x - mean[None, :]
    var = jnp.maximum(jnp.sum(w[:, None] * d * d, axis=0), var_floor)
    return GaussianMixture(jnp.ones((1,), x.dtype), mean[None, :], var[None, :])


# --------------------------------------------------------------------------------------------
# Child lobes -> slope-space nodes (batched, texel axis last)


def _hermite_grid(order: int, dtype) -> tuple[Array, Array, Array]:
    nodes, weights = np.polynomial.hermite.hermgauss(order)
    a, b = np.meshgrid(nodes, nodes, indexing="ij")
    q = np.outer(weights, weights) / math.pi
    return (jnp.asarray(a.ravel(), dtype=dtype), jnp.asarray(b.ravel(), dtype=dtype),
            jnp.asarray(q.ravel(), dtype=dtype))


def _lobe_nodes(normal, sigma_x, sigma_y, order):
    """Nodes of lobes `L N` (normal a 3-tuple): half vectors (3-tuple of `L Q N`), slopes x0, x1, weights q `Q`."""
    a, b, q = _hermite_grid(order, sigma_x.dtype)
    # The barriers materialize the per-lobe frames and the nodes once: left to itself XLA fuses
    # the frame into every consumer of every node (recomputing it 9 times per lobe, per consumer).
    t, bt, n = jax.lax.optimization_barrier(_tangent_frame3(*normal))
    sx = jnp.maximum(sigma_x, SIGMA_FLOOR)[:, None, :]
    sy = jnp.maximum(sigma_y, SIGMA_FLOOR)[:, None, :]
    ua, ub = a[None, :, None] * sx, b[None, :, None] * sy
    # (T, B, N) is orthonormal, so |ua T + ub B + N|^2 = 1 + ua^2 + ub^2: no per-node dot product
    norm = jax.lax.rsqrt(1 + ua * ua + ub * ub)
    h = tuple((ua * tc[:, None, :] + ub * bc[:, None, :] + nc[:, None, :]) * norm for tc, bc, nc in zip(t, bt, n))
    inv = 1 / jnp.maximum(h[2], _HZ_FLOOR)
    h, x0, x1 = jax.lax.optimization_barrier((h, h[0] * inv, h[1] * inv))
    return h, x0, x1, q


def lobe_slope_nodes(lobe: Lobe, *,
                     order: int = DEFAULT_ORDER) -> tuple[Float[Array, "Q 3"], Float[Array, "Q 2"], Float[Array, " Q"]]:
    """Gauss-Hermite nodes of one lobe's D: (half vectors h, sample-frame slopes x, weights summing to 1)."""
    col = lambda a: jnp.reshape(a, (1, 1))  # noqa: E731
    h, x0, x1, q = _lobe_nodes(tuple(col(lobe.normal[i]) for i in range(3)), col(lobe.sigma_x), col(lobe.sigma_y),
                               order)
    return jnp.stack([c[0, :, 0] for c in h], axis=-1), jnp.stack([x0[0, :, 0], x1[0, :, 0]], axis=-1), q


def _ise_terms(a, b):
    """sum_jk ma_j mb_k <N_j, N_k> for sets of diagonal 2-D Gaussians (mass, m0, m1, v0, v1), each `J N`."""
    ma, ma0, ma1, va0, va1 = a
    mb, mb0, mb1, vb0, vb1 = b
    s0 = va0[:, None] + vb0[None]
    s1 = va1[:, None] + vb1[None]
    d0 = ma0[:, None] - mb0[None]
    d1 = ma1[:, None] - mb1[None]
    g = jnp.exp(-0.5 * (d0 * d0 / s0 + d1 * d1 / s1)) / (2 * jnp.pi * jnp.sqrt(s0 * s1))
    return sum_short(ma[:, None] * g * mb[None], axis=(0, 1))


def _relative_ise(p, q) -> Array:
    pp = _ise_terms(p, p)
    ise = pp - 2 * _ise_terms(p, q) + _ise_terms(q, q)
    return jnp.maximum(ise, 0.0) / jnp.maximum(pp, _TINY)


def _component_lobes(h, w, e, resp, m0, m1, mass):
    """Fitted Gaussians -> lobes (see the module docstring), batched over N: nodes `G Q N`,
    their weights w `G Q N`, the child lobes' RGB energies e (3-tuple of `G N`), responsibilities
    `G N`, means and masses `N`. Returns (rho_s 3-tuple, normal 3-tuple, sx, sy)."""
    rw = resp[:, None, :] * w
    total = jnp.maximum(jnp.sum(rw, axis=(0, 1)), _TINY)
    mean = lambda a: sum_short(rw * a, axis=(0, 1)) / total  # noqa: E731

    def frame_slopes(normal):
        t, b, n = _tangent_frame3(*normal)
        dot = lambda u: sum(hc * uc[None, None, :] for hc, uc in zip(h, u))  # noqa: E731
        inv = 1 / jnp.maximum(dot(n), _HZ_FLOOR)
        return t, b, n, dot(t) * inv, dot(b) * inv

    def recentre(_, normal):  # move the normal until the nodes' mean slope in its own frame is 0
        t, b, n, p, q = frame_slopes(normal)
        mp, mq = mean(p), mean(q)
        return _normalize3(*(nc + mp * tc + mq * bc for tc, bc, nc in zip(t, b, n)))

    normal = _normalize3(m0, m1, jnp.ones_like(m0))
    normal = jax.lax.fori_loop(0, _RECENTRE_STEPS, recentre, normal)
    _, _, _, p, q = frame_slopes(normal)
    sx = jnp.maximum(jnp.sqrt(2 * mean(p * p)), SIGMA_FLOOR)
    sy = jnp.maximum(jnp.sqrt(2 * mean(q * q)), SIGMA_FLOOR)
    denom = mass * jnp.pi * sx * sy
    ok = denom > _TINY
    rho_s = tuple(jnp.where(ok, jnp.sum(resp * ec, axis=0) / jnp.where(ok, denom, 1.0), 0.0) for ec in e)
    return rho_s, normal, sx, sy


def _child_lobes_soa(children: BTFTexel, one_lobe_children: bool):
    """Children `4 N ...` (child axis first) -> their lobes in structure-of-arrays layout, texel
    axis last: (normal 3-tuple, rho_s 3-tuple, sigma_x, sigma_y, mass), each `L N` with L = 8
    child lobes (4 with `one_lobe_children`: every child has weight 0, e.g. level 0 of a fit, so
    its lobe 1 would add exact zeros to every sum and is left out: half the nodes, the same
    texels up to the order of the sums)."""
    if one_lobe_children:
        lobes = children.lobe0                                                                           # 4 N ...
        child_mass = jnp.ones_like(children.weight)
    else:
        lobes = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), children.lobe0, children.lobe1)     # 8 N ...
        child_mass = jnp.concatenate([1 - children.weight, children.weight])
    comps = lambda a: tuple(a[..., i] for i in range(3))  # noqa: E731  8 N 3 -> 3 x (8 N)
    return comps(lobes.normal), comps(lobes.rho_s), lobes.sigma_x, lobes.sigma_y, child_mass


def _cut_blocks(tree, size: int):
    """Arrays with the texel axis last (`... N`) -> blocks of `size` texels, block axis first
    (`N/size ... size`), each block contiguous."""
    return jax.tree.map(lambda a: jnp.moveaxis(a.reshape(a.shape[:-1] + (a.shape[-1] // size, size)), -2, 0), tree)


def _no_em(init, groups):
    """`_em_core`'s outputs where no texel runs EM: the initial parameters, nothing iterated."""
    n = init[0].shape[-1]
    dtype = init[0].dtype
    return (tuple(init), jnp.zeros((n,), dtype), jnp.zeros((n,), jnp.int32), jnp.ones((n,), bool),
            jnp.zeros((groups, 2, n), dtype))


def _texels_kernel(lobes_soa, rho_d: Float[Array, "N 3"], order: int, iterations: int, tol: float | None,
                   max_lobes: int):
    """Coarse texels from their children's lobes (`_child_lobes_soa`) and mean `rho_d` ->
    (BTFTexel N, EMInfo N)."""
    normal, rho_s, sigma_x, sigma_y, child_mass = lobes_soa
    dtype = sigma_x.dtype
    if tol is None:
        tol = 1e-5 if dtype == jnp.float32 else 1e-10
    mass_l = 0.25 * child_mass                                                                         # 8 (or 4) N
    h, x0, x1, q = _lobe_nodes(normal, sigma_x, sigma_y, order)                                          # 8 Q N
    area = mass_l * jnp.pi * jnp.maximum(sigma_x, SIGMA_FLOOR) * jnp.maximum(sigma_y, SIGMA_FLOOR)       # 8 N
    # A child lobe's nodes share its energy in the proportions q (which sum to 1), so the per-lobe
    # energies carry everything: RGB e, and the EM weight (their mean, plus a geometric fallback
    # so that a texel without any specular energy still gets a defined lobe).
    e = tuple(area * rc for rc in rho_s)                                                                 # 3 x (8 N)
    mass = (e[0] + e[1] + e[2]) / 3 + 1e-20 * mass_l                                                    # 8 N
    qq = q[None, :, None]
    w = qq * mass[:, None, :]                                                                           # 8 Q N
    # Children's lobes as Gaussians in the common slope space (the density p of the 1-or-2 rule).
    total = jnp.maximum(jnp.sum(mass, axis=0), _TINY)
    mu0, mu1 = jnp.sum(qq * x0, axis=1), jnp.sum(qq * x1, axis=1)
    raw0, raw1 = jnp.sum(qq * (x0 - mu0[:, None]) ** 2, axis=1), jnp.sum(qq * (x1 - mu1[:, None]) ** 2, axis=1)
    var0, var1 = jnp.maximum(raw0, VAR_FLOOR), jnp.maximum(raw1, VAR_FLOOR)
    frac = mass / total[None]
    p = (frac, mu0, mu1, var0, var1)
    # The one-lobe summary: weighted mean and variance of all nodes (from the lobes' moments).
    om0, om1 = jnp.sum(frac * mu0, axis=0), jnp.sum(frac * mu1, axis=0)
    ov0 = jnp.maximum(jnp.sum(frac * (raw0 + (mu0 - om0[None]) ** 2), axis=0), VAR_FLOOR)
    ov1 = jnp.maximum(jnp.sum(frac * (raw1 + (mu1 - om1[None]) ** 2), axis=0), VAR_FLOOR)
    one = jnp.ones_like(total)
    error_one = _relative_ise(p, tuple(a[None] for a in (one, om0, om1, ov0, ov1)))
    n_tex = total.shape[0]
    single_resp = jnp.ones_like(mass)
    if max_lobes == 1:
        rho, nrm, sx, sy = _component_lobes(h, w, e, single_resp, om0, om1, one)
        lobe = Lobe(jnp.stack(rho, -1), jnp.stack(nrm, -1), sx, sy)
        zero = jnp.zeros_like(total)
        info = EMInfo(jnp.zeros((n_tex,), jnp.int32), jnp.ones((n_tex,), bool), jnp.zeros((n_tex,), bool),
                      error_one, zero, zero)
        return BTFTexel(rho_d, lobe, lobe, zero), info
    # Initialization: heaviest child lobe, then the farthest (energy x squared normalized distance).
    index = jnp.arange(mass.shape[0])[:, None]
    hot1 = (index == jnp.argmax(mass, axis=0)[None]).astype(dtype)
    at1 = lambda a: jnp.sum(hot1 * a, axis=0)  # noqa: E731
    d2 = (mu0 - at1(mu0)[None]) ** 2 / (var0 + at1(var0)[None]) + (mu1 - at1(mu1)[None]) ** 2 / (var1 + at1(var1)[None])
    hot2 = (index == jnp.argmax(mass * d2, axis=0)[None]).astype(dtype)
    at2 = lambda a: jnp.sum(hot2 * a, axis=0)  # noqa: E731
    init = (jnp.full((2, n_tex), 0.5, dtype),) + tuple(jnp.stack([at1(a), at2(a)]) for a in (mu0, mu1, var0, var1))
    # EM only where one lobe is not enough (the others stop at once).
    run = error_one > ONE_LOBE_TOLERANCE
    em_loop = functools.partial(_em_core, iterations=iterations, tol=tol, var_floor=VAR_FLOOR, virtual=VIRTUAL)

    def fit():
        if n_tex <= _EM_BLOCK or n_tex % _EM_BLOCK:
            return em_loop(x0, x1, w, init, run=run)
        # The EM loop in blocks of _EM_BLOCK texels one after the other: each block iterates only
        # as long as its own slowest texel, and not at all where none of its texels needs EM.
        out = jax.lax.map(lambda b: jax.lax.cond(jnp.any(b[-1]), lambda: em_loop(*b[:-1], run=b[-1]),
                                                 lambda: _no_em(b[3], b[2].shape[0])),
                          _cut_blocks((x0, x1, w, init, run), _EM_BLOCK))
        return jax.tree.map(lambda a: jnp.moveaxis(a, 0, -2).reshape(a.shape[1:-1] + (n_tex,)), out)

    def fit_and_error():
        out = fit()
        return out + (_relative_ise(p, out[0]),)

    # (no texel of the block needs EM: skipped, as the numpy peer fits only that subset)
    params, loglik, count, converged, resp, error_two = jax.lax.cond(
        jnp.any(run), fit_and_error, lambda: _no_em(init, w.shape[0]) + (error_one,))
    error_two, loglik = jnp.where(run, error_two, error_one), jnp.where(run, loglik, 0.0)
    pi, m0, m1, v0, v1 = params
    two = run & (error_two < TWO_LOBE_GAIN * error_one)
    # Lobe 0 = the heavier component. Two conversions in one batch of 2N problems: lobe 0 (the
    # major component where two lobes are kept, else the single summary) and the minor component.
    swap = pi[1] > pi[0]
    major = lambda a: jnp.where(swap, a[1], a[0])  # noqa: E731
    minor = lambda a: jnp.where(swap, a[0], a[1])  # noqa: E731
    first = lambda a, b: jnp.where(two.reshape((1,) * (a.ndim - 1) + two.shape), a, b)  # noqa: E731
    resp_k = jnp.moveaxis(resp, 1, 0)                                                           # K G N
    as_lobe = lambda rho, nrm, sx, sy: Lobe(jnp.stack(rho, -1), jnp.stack(nrm, -1), sx, sy)  # noqa: E731
    lobe0 = as_lobe(*_component_lobes(h, w, e, first(major(resp_k), single_resp), first(major(m0), om0),
                                      first(major(m1), om1), first(major(pi), one)))
    # The minor component's lobe is converted only where some texel of the block keeps two lobes
    # (elsewhere lobe 1 is a copy of lobe 0): same result, half the conversion work on the many
    # blocks where one lobe is enough everywhere.
    minor_lobe = jax.lax.cond(
        jnp.any(two), lambda: as_lobe(*_component_lobes(h, w, e, minor(resp_k), minor(m0), minor(m1), minor(pi))),
        lambda: lobe0)
    lobe1 = jax.tree.map(lambda u, v: jnp.where(two.reshape(two.shape + (1,) * (u.ndim - 1)), u, v), minor_lobe, lobe0)
    weight = jnp.where(two, minor(pi), 0.0)
    info = EMInfo(count, converged, two, error_one, error_two, loglik)
    return BTFTexel(rho_d, lobe0, lobe1, weight), info


def em_texel(children: BTFTexel, *, order: int = DEFAULT_ORDER, iterations: int = DEFAULT_ITERATIONS,
             tol: float | None = None) -> tuple[BTFTexel, EMInfo]:
    """One coarse texel from its 4 children (fields with a leading axis of 4): EM 1-or-2 lobes."""
    texel, info = _em_batch(jax.tree.map(lambda a: a[None], children), order, iterations, tol, 2)
    return jax.tree.map(lambda a: a[0], (texel, info))


def moment_matched_texel(children: BTFTexel, *, order: int = DEFAULT_ORDER) -> BTFTexel:
    """The one-lobe LEAN/Toksvig-style summary: energy-weighted slope mean and second moments of
    the children's lobes in one lobe (the baseline the two-lobe EM must beat)."""
    texel, _ = _em_batch(jax.tree.map(lambda a: a[None], children), order, 0, None, 1)
    return jax.tree.map(lambda a: a[0], texel)


def mip_texel(children: BTFTexel) -> BTFTexel:
    """The ordinary mip: every parameter averaged over the 4 children (normals renormalized)."""
    avg = jax.tree.map(lambda a: jnp.mean(a, axis=0), children)
    fix = lambda lobe: Lobe(lobe.rho_s, normalize(lobe.normal), lobe.sigma_x, lobe.sigma_y)  # noqa: E731
    return BTFTexel(avg.rho_d, fix(avg.lobe0), fix(avg.lobe1), avg.weight)


# --------------------------------------------------------------------------------------------
# Whole levels


def gather_children(level: BTFTexel) -> BTFTexel:
    """An `H W` level -> `ceil(H/2) ceil(W/2) 4` children (odd sizes edge-padded as
    `jaxrender.textures.downsample2`). Child order: (0,0), (1,0), (0,1), (1,1) offsets (row, col)."""
    return jax.tree.map(lambda a: jnp.moveaxis(a, 0, 2), _children_first(level))


def _children_first(level: BTFTexel) -> BTFTexel:
    """`gather_children` with the child axis first: `4 ceil(H/2) ceil(W/2)`."""
    h, w = level.weight.shape

    def one(a):
        pad = ((0, h % 2), (0, w % 2)) + ((0, 0),) * (a.ndim - 2)
        a = jnp.pad(a, pad, mode="edge")
        return jnp.stack([a[0::2, 0::2], a[1::2, 0::2], a[0::2, 1::2], a[1::2, 1::2]])

    return jax.tree.map(one, level)


_BLOCK = 2048    # texels per block of a batch (the passes outside the EM loop)
_EM_BLOCK = 256  # texels per block of the EM loop, which stops when ITS texels converge


def _em_blocks(lobes, rho_d, order: int, iterations: int, tol: float | None, max_lobes: int):
    """`_texels_kernel` over a batch in structure-of-arrays layout (`_child_lobes_soa`)."""
    n = rho_d.shape[0]
    kernel = lambda b: _texels_kernel(b[0], b[1], order, iterations, tol, max_lobes)  # noqa: E731
    if n <= _BLOCK or n % _BLOCK:
        return kernel((lobes, rho_d))
    # Blocks of _BLOCK texels, small enough to stay in cache; inside a block the EM loop runs in
    # smaller blocks still (`_texels_kernel`). Every texel's result is the same as in one batch.
    # The blocks are cut from the structure-of-arrays layout (block axis first, texels last), so
    # that a block's arrays are contiguous and its elementwise passes vectorize (cutting them
    # inside the kernel left strided transposes in every pass: ~20 % slower on level 1).
    blocks = (_cut_blocks(lobes, _BLOCK), rho_d.reshape((n // _BLOCK, _BLOCK, 3)))
    if n % (2 * _BLOCK):
        out = jax.lax.map(kernel, blocks)   # one after the other
    else:
        # Two blocks per step with no data between them: XLA:CPU's thunk executor runs their
        # passes concurrently, which uses two cores better than splitting each pass (~9 % faster
        # on level 1 of the woven pyramid).
        def two(pair):
            outs = [kernel(jax.tree.map(lambda a: a[i], pair)) for i in range(2)]
            return jax.tree.map(lambda *xs: jnp.stack(xs), *outs)

        pairs = jax.tree.map(lambda a: a.reshape((a.shape[0] // 2, 2) + a.shape[1:]), blocks)
        out = jax.tree.map(lambda a: a.reshape((-1,) + a.shape[2:]), jax.lax.map(two, pairs))
    return jax.tree.map(lambda a: a.reshape((n,) + a.shape[2:]), out)


_em_blocks_jit = jax.jit(_em_blocks, static_argnums=(2, 3, 4, 5))


@functools.partial(jax.jit, static_argnums=(1, 2, 3, 4, 5))
def _em_batch(children: BTFTexel, order: int, iterations: int, tol: float | None, max_lobes: int = 2,
              one_lobe_children: bool = False):
    first = jax.tree.map(lambda a: jnp.moveaxis(a, 1, 0), children)
    return _em_blocks(_child_lobes_soa(first, one_lobe_children), jnp.mean(children.rho_d, axis=1),
                      order, iterations, tol, max_lobes)


def em_texels(children: BTFTexel, *, order: int = DEFAULT_ORDER, iterations: int = DEFAULT_ITERATIONS,
              tol: float | None = None, one_lobe_children: bool = False) -> tuple[BTFTexel, EMInfo]:
    """`em_texel` over a leading texel axis (`N 4` children -> `N` texels), jitted, batched.
    `one_lobe_children=True` promises that every child's weight is 0 (faster; see `_texels_kernel`)."""
    return _em_batch(children, order, iterations, tol, 2, one_lobe_children)


def moment_matched_texels(children: BTFTexel, *, order: int = DEFAULT_ORDER) -> BTFTexel:
    """`moment_matched_texel` over a leading texel axis, jitted, batched."""
    return _em_batch(children, order, 0, None, 1)[0]


_CHUNK_SIZES = (16, 256, 4096, 65536)  # the kernel shapes levels are cut into (a few, shared by all levels)
_CALL_COST = 300  # the fixed cost of one kernel call, in texels of work (~0.15 ms on a 2-core CPU)


def _chunk_size(n: int, chunk: int) -> int:
    """The chunk size (from _CHUNK_SIZES, at most `chunk`) that costs `n` texels the least: every
    chunk is one kernel call of fixed cost _CALL_COST plus its texels, padding included."""
    sizes = [s for s in _CHUNK_SIZES if s <= chunk] or [_CHUNK_SIZES[0]]
    return min(sizes, key=lambda s: (-(-n // s) * (_CALL_COST + s), s))


def _split_level(level: BTFTexel, size: int, one_lobe_children: bool) -> tuple:
    """Children of an `H W` level as the kernel's input (`_child_lobes_soa`, mean rho_d) in chunks
    of `size` texels (the last padded by repeating a texel). Data movement only, in numpy: a
    compiled version would be compiled again for every level's shape (the kernels' chunks share
    a few shapes)."""
    h, w = level.weight.shape
    hh, ww = -(-h // 2), -(-w // 2)
    n = hh * ww
    n_padded = -(-n // size) * size

    def children(a):   # `_children_first` then flat and padded: 4 n_padded ...
        a = np.asarray(a)
        a = np.pad(a, ((0, h % 2), (0, w % 2)) + ((0, 0),) * (a.ndim - 2), mode="edge")
        a = np.stack([a[0::2, 0::2], a[1::2, 0::2], a[0::2, 1::2], a[1::2, 1::2]]).reshape((4, n) + a.shape[2:])
        return np.pad(a, ((0, 0), (0, n_padded - n)) + ((0, 0),) * (a.ndim - 2), mode="edge")

    flat = jax.tree.map(children, level)
    if one_lobe_children:
        lobes, mass = flat.lobe0, np.ones_like(flat.weight)
    else:
        lobes = jax.tree.map(lambda a, b: np.concatenate([a, b]), flat.lobe0, flat.lobe1)
        mass = np.concatenate([1 - flat.weight, flat.weight])
    comps = lambda a: tuple(np.ascontiguousarray(a[..., i]) for i in range(3))  # noqa: E731
    soa = (comps(lobes.normal), comps(lobes.rho_s), lobes.sigma_x, lobes.sigma_y, mass)
    rho_d = np.mean(flat.rho_d, axis=0, dtype=flat.rho_d.dtype)
    return tuple((jax.tree.map(lambda a: a[..., start:start + size], soa), rho_d[start:start + size])
                 for start in range(0, n_padded, size))


def _merge_level(pieces, hh: int, ww: int):
    return jax.tree.map(lambda *xs: np.concatenate([np.asarray(x) for x in xs], axis=0)[:hh * ww].reshape(
        (hh, ww) + xs[0].shape[1:]), *pieces)


_AHEAD: dict[tuple, threading.Thread] = {}   # kernels being compiled ahead (`compile_ahead`), by their key


def _kernel_key(order, iterations, tol, size, dtype) -> tuple:
    return (order, iterations, tol, size, np.dtype(dtype).str)


def compile_ahead(*, order: int = DEFAULT_ORDER, iterations: int = DEFAULT_ITERATIONS, tol: float | None = None,
                  chunk: int = 4096, dtype=np.float32) -> threading.Thread:
    """Start compiling, in a background thread, the one-lobe and two-lobe kernels that
    `em_downsample(..., chunk=chunk, fixed=True)` of `dtype` levels calls, and return the thread
    at once (the same thread for the same kernels while it lives).
    XLA compiles without holding the GIL: a pyramid built after a long computation (a fit, whose
    own compilation and solves leave a core free at times) finds its kernels compiled or waits only
    for the rest. `em_downsample` waits for a pending compilation of its kernels before calling
    them, so they are never compiled twice."""
    key = _kernel_key(order, iterations, tol, chunk, dtype)
    if key in _AHEAD:
        return _AHEAD[key]
    zero = np.zeros((1, 1), dtype)
    lobe = Lobe(np.zeros((1, 1, 3), dtype), np.zeros((1, 1, 3), dtype), zero, zero)
    level = BTFTexel(np.zeros((1, 1, 3), dtype), lobe, lobe, zero)
    shapes = [jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), _split_level(level, chunk, one)[0])
              for one in (True, False)]

    def compile_both():
        try:
            for lobes, rho_d in shapes:
                _em_blocks_jit.lower(lobes, rho_d, order, iterations, tol, 2).compile()
        except Exception:  # noqa: BLE001 - the call itself compiles again and reports what fails
            pass

    # not a daemon: a process that ends (an error, Ctrl-C) waits for the compilation instead of
    # finalizing the interpreter under it
    thread = threading.Thread(target=compile_both, name="em-compile-ahead")
    _AHEAD[key] = thread
    thread.start()
    return thread


def em_downsample(level: BTFTexel, *, order: int = DEFAULT_ORDER, iterations: int = DEFAULT_ITERATIONS,
                  tol: float | None = None, chunk: int = 4096, fixed: bool = False) -> tuple[BTFTexel, EMInfo]:
    """The next pyramid level of an `H W` BTFTexel level: `ceil(H/2) ceil(W/2)`.

    Texels are processed in chunks of a few fixed sizes (16, 256, 4096 texels, at most `chunk`;
    the last chunk padded by repeating a texel), so that a whole pyramid reuses a few compiled
    kernels; each level takes the size that costs it least, counting the fixed cost of a kernel
    call (~300 texels of work) per chunk (e.g. 64 texels: one chunk of 256, not four of 16).
    The Python loop runs over chunks, never over texels, and dispatches them asynchronously.
    Inside a chunk, blocks of 2048 texels are processed two at a time, and inside them blocks of
    256 texels run their EM loops, each until its own slowest texel has converged (`_em_blocks`).
    Splitting into chunks (already in the kernel's structure-of-arrays layout) and merging them
    are numpy (compiled, they would be compiled again for every level's shape); whether any child
    has a second lobe picks the cheaper kernel for one-lobe levels. The level comes back in numpy.
    `fixed`: every chunk of `chunk` texels (a pyramid built once, in a fresh process: two kernels to
    compile, one-lobe and two-lobe, instead of one per chunk size its levels would pick; measured on
    a 231 x 385 level 0 and its 8 levels: 12.4 s CPU with compilation instead of 18.9 s).
    """
    level = jax.tree.map(np.asarray, level)
    h, w = level.weight.shape
    hh, ww = -(-h // 2), -(-w // 2)
    one_lobe = not bool(np.any(level.weight))   # e.g. level 0 of a fit: the cheaper kernel
    size = chunk if fixed else _chunk_size(hh * ww, chunk)
    ahead = _AHEAD.get(_kernel_key(order, iterations, tol, size, level.weight.dtype))
    if ahead is not None:
        ahead.join()
    pieces = [_em_blocks_jit(lobes, rho_d, order, iterations, tol, 2)   # dispatched asynchronously
              for lobes, rho_d in _split_level(level, size, one_lobe)]
    return _merge_level(tuple(pieces), hh, ww)



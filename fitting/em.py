"""EM multi-resolution BTF (paper 004, section 3.2, after Takeda et al., refs. 21-22).

A texel of level l+1 summarizes the specular slope distributions of its 4 children at level l
(each with 1 or 2 lobes) as a mixture of at most 2 anisotropic lobes, fitted by EM; `rho_d` is
averaged. Everything here is written for ONE coarse texel and vmapped over texels.

Slope space
-----------
For a lobe with normal N and frame (T, B, N) (`jaxrender.brdf.tangent_frame`: T = the sample x
axis projected onto N's tangent plane), the slope distribution of eq. 1 is, with the half-vector's
slopes p = h.T / h.N and q = h.B / h.N,

    D = exp(-(p^2 / sigma_x^2 + q^2 / sigma_y^2)) = pi sigma_x sigma_y  N(p; 0, sigma_x^2 / 2) N(q; 0, sigma_y^2 / 2),

an unnormalized Gaussian in (p, q) with standard deviation sigma / sqrt(2) per axis and integral
pi sigma_x sigma_y over slope space. Each child lobe is represented by an `order` x `order`
Gauss-Hermite product rule of that Gaussian: nodes (p, q) = (sigma_x a_i, sigma_y a_j) with
a = the Hermite nodes of weight exp(-a^2), weights w_i w_j / pi (they sum to 1). Every node is
turned into its unit half vector h = normalize(p T + q B + N) and then into the COMMON slope
space of the coarse texel, the sample frame: x = (h.x / h.z, h.y / h.z). A lobe whose normal is
the sample z maps to itself; a tilted normal moves the Gaussian to the normal's slope
(n.x / n.z, n.y / n.z), with the mild projective distortion of the tilt carried by the nodes.

Energy weights: a child lobe contributes to the average of its 4 children's reflectance
rho_s D / cos_r with mass (1/4) m rho_s pi sigma_x sigma_y (m = 1 - weight for lobe 0, weight for
lobe 1), so a node carries e = (1/4) m rho_s pi sigma_x sigma_y w_i w_j (RGB); the EM weight of a
node is the mean of e over R, G, B.

EM and the 1-or-2 rule
----------------------
`em_fit` is weighted EM for a mixture of K Gaussians with diagonal covariances in (x, y) (i.e.
along the sample's x and y axes, which are the lobes' T and B up to the tilt), a variance floor
of SIGMA_FLOOR^2 / 2, a fixed maximum number of iterations and a convergence check (|change of
the weighted mean log-likelihood| < tol). On plain samples it is the textbook EM (checked against
scikit-learn). For a texel the samples are grouped by child lobe: the E-step gives all nodes of
one child lobe the same responsibility, from their weighted mean log-density (the expected
log-density under the child lobe, exact with Gauss-Hermite nodes since log N is quadratic), and
the M-step is the ordinary weighted one over the nodes (whose moments are the child lobes').
This is hierarchical EM (Vasconcelos and Lippman) with VIRTUAL = 16 virtual samples per child
lobe: the group's expected log-density is multiplied by 16 before the softmax over components,
which sharpens the lobe-to-component assignment (with 1 the soft assignment lets both
components collapse onto the moment match where the lobes form two close clusters). Without
grouping, EM overfits the 3x3 node lattice (e.g. a narrow component on the central row of nodes),
a likelihood optimum of the nodes but not a good summary of the lobes. The EM runs only for texels whose one-
lobe summary is not good enough (below), initialized from the most energetic child lobe and the
child lobe maximizing energy x squared normalized distance from it.

Plain EM never drives a weight to 0, so the number of lobes is chosen by an L2 rule. Let p be the
children's slope density (each child lobe as the Gaussian of its transported nodes' moments, with
its energy as mass), q1 the single moment-matched Gaussian (mean and variance of all nodes: the
LEAN/Toksvig-style one-lobe summary, which is also the 1-component maximum-likelihood fit) and q2
the EM mixture. With e_k = ISE(p, q_k) / <p, p> (integrated squared error, closed form for
Gaussians; it is the relative squared error of the rendered specular term over slope space):

    two lobes  iff  e_1 > ONE_LOBE_TOLERANCE (0.01, i.e. one lobe is more than ~10 % RMS off)
               and  e_2 < TWO_LOBE_GAIN * e_1 (0.5: the second lobe must halve the error).

So 4 agreeing children (or children that differ by much less than their widths) give one lobe
with weight 0 and lobe 1 a copy of lobe 0, never two copies. Lobes are ordered by descending
weight: lobe 0 is the heavier one and `weight` (of lobe 1) is <= 1/2.

From a Gaussian back to a lobe
------------------------------
For a fitted component k with mean slope (m_x, m_y) and responsibilities r_ik:
normal = normalize(m_x, m_y, 1), then a few fixed-point steps N <- normalize(N + <p> T + <q> B)
that move N until the responsibility-weighted mean of the nodes' slopes in N's own frame
(p_i = h_i.T / h_i.N, q_i = h_i.B / h_i.N, (T, B) = tangent_frame(N)) is 0 (for a single child
lobe this returns its normal exactly: its nodes are symmetric about it); then
sigma_x^2 = 2 sum_i r_ik w_i p_i^2 / sum_i r_ik w_i (and sigma_y from q), floored at SIGMA_FLOOR
(the second moment about the lobe's own normal: exact for an untilted lobe, and free of the
sample-frame distortion for a tilted one); rho_s (RGB) = E_k / (pi_k pi sigma_x sigma_y), with
E_k = sum_i r_ik e_i the component's energy and pi_k its mixture weight (1 for a single lobe):
the total specular energy of the children is conserved exactly.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jaxrender._math import normalize
from jaxrender.brdf import SIGMA_FLOOR, BTFTexel, Lobe, tangent_frame

__all__ = ["GaussianMixture", "EMInfo", "em_fit", "weighted_log_likelihood", "moment_match", "lobe_slope_nodes",
           "em_texel", "em_texels", "moment_matched_texel", "mip_texel", "gather_children", "em_downsample",
           "ONE_LOBE_TOLERANCE", "TWO_LOBE_GAIN", "DEFAULT_ORDER", "DEFAULT_ITERATIONS"]

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
    error_two: Float[Array, "..."]   # relative ISE of the EM mixture
    log_likelihood: Float[Array, "..."]


# --------------------------------------------------------------------------------------------
# Plain weighted EM for a diagonal Gaussian mixture (one texel's samples)


def _log_components(x: Float[Array, "G Q 2"], gmm: GaussianMixture) -> Float[Array, "G Q K"]:
    d = x[:, :, None, :] - gmm.means[None, None, :, :]
    var = gmm.variances[None, None, :, :]
    return -0.5 * jnp.sum(jnp.log(2 * jnp.pi * var) + d * d / var, axis=-1)


def _group_weights(w: Float[Array, "G Q"]) -> tuple[Array, Array]:
    mass = jnp.sum(w, axis=1)
    return mass, w / jnp.maximum(mass, _TINY)[:, None]


def _e_step(x, w, gmm, virtual=1.0):
    """Responsibilities per group (G K) from the group's mean log-density (times `virtual`), and
    log sum_k per group."""
    _, qn = _group_weights(w)
    expected = virtual * jnp.einsum("gq,gqk->gk", qn, _log_components(x, gmm))
    log_p = expected + jnp.log(jnp.maximum(gmm.weights, _TINY))[None, :]
    lse = jax.scipy.special.logsumexp(log_p, axis=1)
    return jnp.exp(log_p - lse[:, None]), lse


def _m_step(x, w, resp, old: GaussianMixture, var_floor) -> GaussianMixture:
    rw = resp[:, None, :] * w[:, :, None]                    # G Q K
    n = jnp.sum(rw, axis=(0, 1))                             # K
    alive = n > _TINY
    safe_n = jnp.where(alive, n, 1.0)
    means = jnp.einsum("gqk,gqd->kd", rw, x) / safe_n[:, None]
    d = x[:, :, None, :] - means[None, None, :, :]
    var = jnp.einsum("gqk,gqkd->kd", rw, d * d) / safe_n[:, None]
    var = jnp.maximum(var, var_floor)
    means = jnp.where(alive[:, None], means, old.means)
    var = jnp.where(alive[:, None], var, old.variances)
    return GaussianMixture(n / jnp.maximum(jnp.sum(n), _TINY), means, var)


def _grouped(x, w):
    x = jnp.asarray(x)
    w = jnp.asarray(w, dtype=x.dtype)
    if x.ndim == 2:  # plain samples: every sample its own group
        return x[:, None, :], w[:, None]
    return x, w


def weighted_log_likelihood(x: Float[Array, "S 2"] | Float[Array, "G Q 2"], w: Float[Array, " S"] | Float[Array, "G Q"],
                            gmm: GaussianMixture) -> Float[Array, ""]:
    """sum_i w_i log sum_k pi_k N(x_i; mu_k, diag var_k) / sum_i w_i for plain samples (`S 2`);
    for grouped samples (`G Q 2`) the per-group terms use the group's weighted mean log-density."""
    x, w = _grouped(x, w)
    mass, _ = _group_weights(w)
    _, lse = _e_step(x, w, gmm)
    return jnp.sum(mass * lse) / jnp.maximum(jnp.sum(mass), _TINY)


def em_fit(x: Float[Array, "S 2"] | Float[Array, "G Q 2"], w: Float[Array, " S"] | Float[Array, "G Q"],
           init: GaussianMixture, *, iterations: int = DEFAULT_ITERATIONS, tol: float | None = None,
           var_floor: float = VAR_FLOOR, run: Bool[Array, ""] | bool = True, virtual: float = 1.0,
           ) -> tuple[GaussianMixture, Float[Array, ""], Int[Array, ""], Bool[Array, ""]]:
    """Weighted EM for a diagonal Gaussian mixture from `init`: at most `iterations` E+M steps,
    stopping once the weighted mean log-likelihood changes by less than `tol` (default 1e-5 in
    float32, 1e-10 in float64); `run=False` returns `init` (lets a vmapped caller skip texels).

    Plain samples `S 2` (weights `S`): the textbook EM (as scikit-learn's, with weights).
    Grouped samples `G Q 2` (weights `G Q`): the nodes of one group (a child lobe's quadrature
    nodes) share one responsibility, computed from the group's weighted mean log-density, which
    is the expected log-density under the child lobe, multiplied by `virtual` (hierarchical EM with `virtual` virtual samples per group):
    a lobe is never split between components, and EM cannot overfit the node lattice.

    Returns (mixture, weighted mean log-likelihood of the returned mixture, iterations, converged).
    Zero-weight samples are ignored; a component that loses all its mass keeps its mean and
    variance with weight 0 (no NaN). Vmap it over texels.
    """
    x, w = _grouped(x, w)
    w = w / jnp.maximum(jnp.sum(w), _TINY)
    mass, _ = _group_weights(w)
    if tol is None:
        tol = 1e-5 if x.dtype == jnp.float32 else 1e-10
    init = jax.tree.map(lambda a: jnp.asarray(a, dtype=x.dtype), init)
    run = jnp.asarray(run)

    def cond(state):
        i, _, previous, current = state
        return run & (i < iterations) & ~(jnp.abs(current - previous) < tol)

    def body(state):
        i, gmm, _, current = state
        resp, lse = _e_step(x, w, gmm, virtual)
        new = _m_step(x, w, resp, gmm, var_floor)
        return i + 1, new, current, jnp.sum(mass * lse)

    inf = jnp.asarray(jnp.inf, dtype=x.dtype)
    state = (jnp.zeros((), jnp.int32), init, -inf, inf)  # |inf - -inf| is never below tol: at least one step
    i, gmm, previous, current = jax.lax.while_loop(cond, body, state)
    converged = jnp.abs(current - previous) < tol
    return gmm, jnp.sum(mass * _e_step(x, w, gmm, virtual)[1]), i, converged


def moment_match(x: Float[Array, "S 2"], w: Float[Array, " S"], *, var_floor: float = VAR_FLOOR) -> GaussianMixture:
    """The one-component maximum-likelihood fit: weighted mean and variance (K = 1)."""
    w = w / jnp.maximum(jnp.sum(w), _TINY)
    mean = jnp.einsum("s,sd->d", w, x)
    d = x - mean[None, :]
    var = jnp.maximum(jnp.einsum("s,sd->d", w, d * d), var_floor)
    return GaussianMixture(jnp.ones((1,), x.dtype), mean[None, :], var[None, :])


# --------------------------------------------------------------------------------------------
# Child lobes -> slope-space nodes


def _hermite_grid(order: int, dtype) -> tuple[Array, Array, Array]:
    nodes, weights = np.polynomial.hermite.hermgauss(order)
    a, b = np.meshgrid(nodes, nodes, indexing="ij")
    q = np.outer(weights, weights) / math.pi
    return (jnp.asarray(a.ravel(), dtype=dtype), jnp.asarray(b.ravel(), dtype=dtype), jnp.asarray(q.ravel(), dtype=dtype))


def lobe_slope_nodes(lobe: Lobe, *, order: int = DEFAULT_ORDER) -> tuple[Float[Array, "Q 3"], Float[Array, "Q 2"], Float[Array, " Q"]]:
    """Gauss-Hermite nodes of one lobe's D: (half vectors h, sample-frame slopes x, weights summing to 1)."""
    dtype = lobe.sigma_x.dtype
    a, b, q = _hermite_grid(order, dtype)
    t, bt, n = tangent_frame(lobe.normal)
    sx = jnp.maximum(lobe.sigma_x, SIGMA_FLOOR)
    sy = jnp.maximum(lobe.sigma_y, SIGMA_FLOOR)
    h = normalize(a[:, None] * sx * t[None, :] + b[:, None] * sy * bt[None, :] + n[None, :])
    hz = jnp.maximum(h[:, 2], _HZ_FLOOR)
    return h, h[:, :2] / hz[:, None], q


def _lobe_energy(lobe: Lobe, mass) -> Float[Array, "3"]:
    sx = jnp.maximum(lobe.sigma_x, SIGMA_FLOOR)
    sy = jnp.maximum(lobe.sigma_y, SIGMA_FLOOR)
    return (mass * jnp.pi * sx * sy) * lobe.rho_s


def _ise_terms(ma, mua, va, mb, mub, vb):
    """sum_jk ma_j mb_k <N_j, N_k> for diagonal 2-D Gaussians."""
    v = va[:, None, :] + vb[None, :, :]
    d = mua[:, None, :] - mub[None, :, :]
    g = jnp.prod(jnp.exp(-0.5 * d * d / v) / jnp.sqrt(2 * jnp.pi * v), axis=-1)
    return jnp.einsum("j,jk,k->", ma, g, mb)


def _relative_ise(p, q) -> Array:
    pp = _ise_terms(*p, *p)
    ise = pp - 2 * _ise_terms(*p, *q) + _ise_terms(*q, *q)
    return jnp.maximum(ise, 0.0) / jnp.maximum(pp, _TINY)


def _component_lobe(h, w, e, resp_k, mean_k, mass_k) -> Lobe:
    """Fitted Gaussian (mean slope, responsibilities) -> Lobe (see the module docstring)."""
    rw = resp_k * w
    total = jnp.maximum(jnp.sum(rw), _TINY)

    def frame_slopes(normal):
        t, b, n = tangent_frame(normal)
        hn = jnp.maximum(h @ n, _HZ_FLOOR)
        return t, b, n, (h @ t) / hn, (h @ b) / hn

    def recentre(_, normal):  # move the normal until the nodes' mean slope in its own frame is 0
        t, b, n, p, q = frame_slopes(normal)
        return normalize(n + (jnp.sum(rw * p) / total) * t + (jnp.sum(rw * q) / total) * b)

    normal = normalize(jnp.concatenate([mean_k, jnp.ones((1,), mean_k.dtype)]))
    normal = jax.lax.fori_loop(0, _RECENTRE_STEPS, recentre, normal)
    _, _, _, p, q = frame_slopes(normal)
    sx = jnp.maximum(jnp.sqrt(2 * jnp.sum(rw * p * p) / total), SIGMA_FLOOR)
    sy = jnp.maximum(jnp.sqrt(2 * jnp.sum(rw * q * q) / total), SIGMA_FLOOR)
    energy = resp_k @ e                                            # 3
    denom = mass_k * jnp.pi * sx * sy
    rho_s = jnp.where(denom > _TINY, energy / jnp.maximum(denom, _TINY), 0.0)
    return Lobe(rho_s, normal, sx, sy)


def _children_nodes(children: BTFTexel, order: int):
    """The 4 children's (up to 8) lobes as nodes: h (S 3), x (S 2), w (S), e (S 3), lobe id grouping."""
    lobes = jax.tree.map(lambda a, b: jnp.concatenate([a, b], axis=0), children.lobe0, children.lobe1)  # 8 lobes
    mass = 0.25 * jnp.concatenate([1 - children.weight, children.weight])                              # 8
    h, x, q = jax.vmap(lambda lobe: lobe_slope_nodes(lobe, order=order))(lobes)                          # 8 Q ...
    energy = jax.vmap(_lobe_energy)(lobes, mass)                                                       # 8 3
    e = q[:, :, None] * energy[:, None, :]                                                             # 8 Q 3
    # Geometric fallback so that a texel without any specular energy still gets a defined lobe.
    w = jnp.mean(e, axis=-1) + 1e-20 * q * mass[:, None]
    return h, x, w, e


def em_texel(children: BTFTexel, *, order: int = DEFAULT_ORDER, iterations: int = DEFAULT_ITERATIONS,
             tol: float | None = None) -> tuple[BTFTexel, EMInfo]:
    """One coarse texel from its 4 children (fields with a leading axis of 4): EM 1-or-2 lobes."""
    h, x, w, e = _children_nodes(children, order)
    n_lobes, n_nodes = w.shape
    # Children's lobes as Gaussians in the common slope space (the density p of the 1-or-2 rule).
    mass = jnp.sum(w, axis=1)
    total = jnp.maximum(jnp.sum(mass), _TINY)
    qn = w / jnp.maximum(mass, _TINY)[:, None]
    mu = jnp.einsum("jq,jqd->jd", qn, x)
    dev = x - mu[:, None, :]
    var = jnp.maximum(jnp.einsum("jq,jqd->jd", qn, dev * dev), VAR_FLOOR)
    p = (mass / total, mu, var)
    # Initialization: heaviest child lobe, then the farthest (energy x squared normalized distance).
    j1 = jnp.argmax(mass)
    d2 = jnp.sum((mu - mu[j1][None, :]) ** 2 / (var + var[j1][None, :]), axis=-1)
    j2 = jnp.argmax(mass * d2)
    init = GaussianMixture(jnp.full((2,), 0.5, x.dtype), jnp.stack([mu[j1], mu[j2]]), jnp.stack([var[j1], var[j2]]))
    hs, xs, ws, es = (h.reshape(n_lobes * n_nodes, 3), x.reshape(n_lobes * n_nodes, 2),
                      w.reshape(n_lobes * n_nodes), e.reshape(n_lobes * n_nodes, 3))
    one = moment_match(xs, ws)
    error_one = _relative_ise(p, (one.weights, one.means, one.variances))
    # EM only where one lobe is not enough (in a vmapped batch the others stop at once).
    gmm, loglik, n_iter, converged = em_fit(x, w, init, iterations=iterations, tol=tol,
                                            run=error_one > ONE_LOBE_TOLERANCE, virtual=VIRTUAL)
    error_two = _relative_ise(p, (gmm.weights, gmm.means, gmm.variances))
    two = (error_one > ONE_LOBE_TOLERANCE) & (error_two < TWO_LOBE_GAIN * error_one)

    resp = jnp.repeat(_e_step(x, w, gmm, VIRTUAL)[0], n_nodes, axis=0)   # S K: a lobe's nodes share theirs
    k0 = jnp.argmax(gmm.weights)  # lobe 0 = the heavier component
    k1 = 1 - k0
    # The three candidate lobes (major, minor, single) in one vmapped conversion.
    resps = jnp.stack([resp[:, k0], resp[:, k1], jnp.ones_like(ws)])
    means = jnp.stack([gmm.means[k0], gmm.means[k1], one.means[0]])
    masses = jnp.stack([gmm.weights[k0], gmm.weights[k1], jnp.ones((), ws.dtype)])
    lobes = jax.vmap(lambda r, m, a: _component_lobe(hs, ws, es, r, m, a))(resps, means, masses)
    pick = lambda i: jax.tree.map(lambda a: jnp.where(two, a[i], a[2]), lobes)  # noqa: E731
    lobe0, lobe1 = pick(0), pick(1)
    weight = jnp.where(two, gmm.weights[k1], 0.0)
    rho_d = jnp.mean(children.rho_d, axis=0)
    info = EMInfo(n_iter, converged, two, error_one, error_two, loglik)
    return BTFTexel(rho_d, lobe0, lobe1, weight), info


def moment_matched_texel(children: BTFTexel, *, order: int = DEFAULT_ORDER) -> BTFTexel:
    """The one-lobe LEAN/Toksvig-style summary: energy-weighted slope mean and second moments of
    the children's lobes in one lobe (the baseline the two-lobe EM must beat)."""
    h, x, w, e = _children_nodes(children, order)
    hs, xs, ws, es = h.reshape(-1, 3), x.reshape(-1, 2), w.reshape(-1), e.reshape(-1, 3)
    one = moment_match(xs, ws)
    lobe = _component_lobe(hs, ws, es, jnp.ones_like(ws), one.means[0], jnp.ones((), ws.dtype))
    return BTFTexel(jnp.mean(children.rho_d, axis=0), lobe, lobe, jnp.zeros((), ws.dtype))


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
    h, w = level.weight.shape

    def one(a):
        pad = ((0, h % 2), (0, w % 2)) + ((0, 0),) * (a.ndim - 2)
        a = jnp.pad(a, pad, mode="edge")
        return jnp.stack([a[0::2, 0::2], a[1::2, 0::2], a[0::2, 1::2], a[1::2, 1::2]], axis=2)

    return jax.tree.map(one, level)


@eqx.filter_jit
def _em_batch(children: BTFTexel, order: int, iterations: int, tol: float | None):
    return jax.vmap(lambda c: em_texel(c, order=order, iterations=iterations, tol=tol))(children)


def em_texels(children: BTFTexel, *, order: int = DEFAULT_ORDER, iterations: int = DEFAULT_ITERATIONS,
              tol: float | None = None) -> tuple[BTFTexel, EMInfo]:
    """`em_texel` jitted and vmapped over a leading texel axis (`N 4` children -> `N` texels)."""
    return _em_batch(children, order, iterations, tol)


def em_downsample(level: BTFTexel, *, order: int = DEFAULT_ORDER, iterations: int = DEFAULT_ITERATIONS,
                  tol: float | None = None, chunk: int = 4096) -> tuple[BTFTexel, EMInfo]:
    """The next pyramid level of an `H W` BTFTexel level: `ceil(H/2) ceil(W/2)`.

    Texels are processed in fixed-size chunks (buckets of 16, 256, 4096, ... texels up to `chunk`;
    the last chunk padded by repeating a texel) so that a whole pyramid reuses a few compiled
    kernels; the Python loop runs over chunks, never over texels. Splitting into chunks and
    concatenating happen on the host (numpy), the EM itself in `em_texels`.
    """
    children = jax.tree.map(np.asarray, _gather_jit(level))
    hh, ww = children.weight.shape[:2]
    n = hh * ww
    flat = jax.tree.map(lambda a: a.reshape((n,) + a.shape[2:]), children)
    size = 16  # buckets 16, 256, 4096, ... up to `chunk`: a whole pyramid compiles a few kernels
    while size < min(n, chunk):
        size *= 16
    size = min(size, chunk)
    n_padded = -(-n // size) * size
    index = np.minimum(np.arange(n_padded), n - 1)
    padded = jax.tree.map(lambda a: a[index], flat)
    pieces = []
    for start in range(0, n_padded, size):
        batch = jax.tree.map(lambda a: a[start:start + size], padded)
        pieces.append(jax.tree.map(np.asarray, em_texels(batch, order=order, iterations=iterations, tol=tol)))
    out = jax.tree.map(lambda *xs: np.concatenate(xs, axis=0)[:n].reshape((hh, ww) + xs[0].shape[1:]), *pieces)
    return jax.tree.map(jnp.asarray, out)


_gather_jit = jax.jit(gather_children)

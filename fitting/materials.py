"""Materials shared by the texels of a capture: the global pass of a fit (`MaterialTable`).

A sparse capture (tens of lights) sees a sharp highlight at a texel under one or two lights, or
under none; fitted texel by texel, a lobe is then invented or missed. Most surfaces are made of a
few materials, so the lobe is estimated where the data pin it and lent where they do not
(Lensch et al. 2003, clustered BRDFs). From a sample of texels (`sample_texels`):

1. every sampled texel is fitted freely (`fitting.lm.fit_texels`, no prior);
2. texels whose lobe carries a visible share of their light are clustered by lobe (log-slopes and
   log amplitude, k-means from quantile seeds); the others form the lobeless material (rho_s = 0);
3. each material's lobe (slopes and rho_s, shared) is fitted jointly to its texels' observations,
   their normals held and each texel's rho_d projected (alternating least squares over a grid
   of slopes around the cluster's median), then texels are reassigned to the material that
   explains them best and the lobes refitted (k-means in BRDF space);
4. the noise level is the median residual variance of the material fits relative to each
   texel's mean squared observation.

The table (a few rows) is the only global state: every tile of the fit gets it, and each texel
takes the prior of its own material (`fitting.lm.MaterialTable`). Reasoning: docs/fitting.md,
"Real captures: the robust method"; figures: benchmarks/RESULTS.md, "Fitting woven fabric (paper 004)".
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from jaxrender.brdf import SIGMA_FLOOR

from ._varpro import Prior, columns, geometry_to_theta, lights_of

__all__ = ["MaterialTable", "estimate_materials", "material_priors", "no_materials", "MAX_MATERIALS", "COLOUR_EPS"]

MAX_MATERIALS = 6     # rows of a table: the lobeless material and up to 5 with a lobe
LOBE_SHARE = 0.02     # a lobe "carries a visible share" above this fraction of a texel's light
MIN_MEMBERS = 64      # sampled texels per material, at least
COLOUR_SPREAD_FLOOR = 0.05
SPLIT_SPREAD = 0.2    # a cluster whose log-colour spreads more than this is split
_COARSE = np.log(np.geomspace(0.02, 0.64, 11) - SIGMA_FLOOR)   # isotropic log-slopes of the coarse search
_GRID = np.array([-0.17, 0.0, 0.17])   # log-slope offsets of the refinement around the best
_ALS_ROUNDS = 6
_REASSIGN_ROUNDS = 2
_MATTE_S = float(np.log(0.3))
NOISE_FLOOR = 1e-12   # relative noise variance below which data count as exact (noise-free synthetic captures)
COLOUR_EPS = 1e-3     # log(rho_d + eps): the colour a texel's material is recognised by
# The priors a `MaterialTable` gives a texel (one setting for every capture): log-slopes within
# TAU_LOG_SLOPE of the material's (a factor e^0.35 = 1.4 at one standard deviation), rho_s within
# TAU_RHO_REL of the material's plus TAU_RHO_FLOOR of the texel's RMS observation (so a material
# without a lobe still lets a texel's lobe through where its data pin it).
TAU_LOG_SLOPE = 0.35
TAU_RHO_REL = 0.35
TAU_RHO_FLOOR = 0.05
_FIELDS = ("rho_s", "s", "log_share", "colour", "colour_spread", "noise", "sample")


class MaterialTable(eqx.Module):
    """Materials shared by the texels of a capture (`estimate_materials`): per row the centre of a
    Gaussian prior on a texel's lobe, and the capture's noise level. The only global state of a
    robust fit: every chunk (every Dask task) gets it, and it is saved with the checkpoint.

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
    sample: Int[Array, ""]         # texels of the sample the table was estimated from

    @property
    def size(self) -> int:
        return int(self.rho_s.shape[0])

    def to_json(self) -> dict:
        """The table as lists (float32 values round-trip exactly; -inf as -Infinity)."""
        return {k: np.asarray(getattr(self, k)).tolist() for k in _FIELDS}

    @classmethod
    def from_json(cls, data: dict) -> "MaterialTable":
        return cls(*(jnp.asarray(np.asarray(data[k], np.int32 if k == "sample" else np.float32)) for k in _FIELDS))

    def describe(self, level: float = 1.0) -> dict:
        """The table's figures for `btf.json`: rows in use, their shares, slopes, rho_s (in the
        capture's units: the table's divided by the capture's `level`), the noise."""
        used = np.flatnonzero(np.isfinite(np.asarray(self.log_share)))
        return {"materials": int(used.size), "shares": [float(np.exp(self.log_share[j])) for j in used],
                "sigma": [[round(float(x), 4) for x in SIGMA_FLOOR + np.exp(np.asarray(self.s[j]))] for j in used],
                "rho_s": [[round(float(x) / level, 4) for x in np.asarray(self.rho_s[j])] for j in used],
                "noise": float(self.noise), "sample": int(self.sample)}


def material_priors(table: MaterialTable, mean_sq: Float[Array, ""]) -> Prior:
    """The `M` priors of a table for a texel of mean squared observation `mean_sq` (stacked)."""
    var = table.noise * mean_sq
    tau_rho = TAU_RHO_REL * jnp.mean(table.rho_s, axis=-1) + TAU_RHO_FLOOR * jnp.sqrt(mean_sq)
    rho_weight = var / jnp.maximum(tau_rho * tau_rho, jnp.finfo(mean_sq.dtype).tiny)
    s_weight = jnp.broadcast_to(var / TAU_LOG_SLOPE**2, rho_weight.shape)
    return Prior(table.rho_s, rho_weight, table.s, s_weight)


def no_materials(dtype=np.float32, sample: int = 0) -> MaterialTable:
    """A table with only the lobeless material and no noise: priors of weight 0."""
    rho_s = np.zeros((MAX_MATERIALS, 3), dtype)
    s = np.full((MAX_MATERIALS, 2), _MATTE_S, dtype)
    share = np.full(MAX_MATERIALS, -np.inf, dtype)
    share[0] = 0.0
    return MaterialTable(jnp.asarray(rho_s), jnp.asarray(s), jnp.asarray(share), jnp.zeros((MAX_MATERIALS, 3), dtype),
                         jnp.ones(MAX_MATERIALS, dtype), jnp.asarray(0.0, dtype), jnp.asarray(sample, np.int32))


@functools.partial(jax.jit, static_argnames="model")
def _columns_of(normals, s, light_dirs, view_dir, model):
    """(a, b) `T L` for texel normals and one lobe's log-slopes s (2,)."""
    lights = lights_of(light_dirs, view_dir)

    def one(n):
        theta = jnp.concatenate([geometry_to_theta(n, 1.0, 1.0)[:2], s])
        return columns(theta, lights, model)

    return jax.vmap(one)(normals)


def _shared_lobe_fit(ratio, w, a, b):
    """Alternating least squares of one shared rho_s (3) and per-texel rho_d (T 3) >= 0:
    min sum_t sum_l w (R - rho_d_t a - rho_s b)^2. Returns (rho_s, per-texel cost T).

    Every quantity is a per-texel sum over the lights, taken once: the rounds cost T, not T L."""
    wa, wb = w * a, w * b
    saa = np.maximum(np.sum(wa * a, axis=1), 1e-30)
    sab = np.sum(wa * b, axis=1)
    sbb_t = np.sum(wb * b, axis=1)
    sbb = float(np.sum(sbb_t)) + 1e-3 * float(np.sum(saa))   # a ridge: no lobe where b vanishes
    ha = np.einsum("tl,tlc->tc", wa, ratio)
    hb = np.einsum("tl,tlc->tc", wb, ratio)
    srr = np.einsum("tl,tlc->tc", w, ratio * ratio)
    rho_s = np.zeros(3)
    for _ in range(_ALS_ROUNDS):
        rho_d = np.maximum((ha - rho_s * sab[:, None]) / saa[:, None], 0.0)
        rho_s = np.maximum((hb.sum(0) - np.einsum("tc,t->c", rho_d, sab)) / sbb, 0.0)
    rho_d = np.maximum((ha - rho_s * sab[:, None]) / saa[:, None], 0.0)
    cost = (srr - 2 * rho_d * ha - 2 * rho_s * hb + rho_d * rho_d * saa[:, None] + 2 * rho_d * rho_s * sab[:, None]
            + rho_s * rho_s * sbb_t[:, None])
    return rho_s, 0.5 * np.maximum(cost, 0.0).sum(1)


def _spread(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean((x - x.mean(0)) ** 2)))


def _divisive_clusters(features: np.ndarray, max_k: int, min_members: int, split_spread: float) -> np.ndarray:
    """Labels of a deterministic divisive clustering: the widest cluster (RMS spread per feature)
    is split in two (2-means seeded by the sign along its principal axis) while its spread is
    above `split_spread`, both halves keep `min_members` and there are fewer than `max_k`."""
    labels = np.zeros(len(features), int)
    frozen: set[int] = set()
    while labels.max() + 1 < max_k:
        spreads = [(_spread(features[labels == j]) if j not in frozen else -1.0) for j in range(labels.max() + 1)]
        j = int(np.argmax(spreads))
        if spreads[j] <= split_spread:
            break
        idx = np.flatnonzero(labels == j)
        x = features[idx] - features[idx].mean(0)
        axis = np.linalg.svd(x, full_matrices=False)[2][0]
        side = x @ axis > 0
        for _ in range(10):
            if side.all() or not side.any():
                break
            c0, c1 = x[~side].mean(0), x[side].mean(0)
            side = np.sum((x - c1) ** 2, 1) < np.sum((x - c0) ** 2, 1)
        if min(side.sum(), (~side).sum()) < min_members:
            frozen.add(j)
            continue
        labels[idx[side]] = labels.max() + 1
    return labels


def _colour(rho_d):
    return np.log(np.maximum(rho_d, 0.0) + COLOUR_EPS)


def estimate_materials(ratio, weight, light_dirs, view_dir, fits, *, model: str = "reciprocal") -> MaterialTable:
    """The material table of a sample of texels (`ratio` `S L 3`, `weight` `S L`; module docstring)
    from their free fits `fits` (a `fitting.lm.TexelFit` of `S` texels, or a dict of its
    normal, rho_d, rho_s, sigma_x, sigma_y and n_valid)."""
    ratio = np.asarray(ratio, np.float32)
    weight = np.asarray(weight, np.float32)
    dirs = np.asarray(light_dirs, np.float32)
    view = np.asarray(view_dir, np.float32)
    n = ratio.shape[0]
    if n == 0:
        return no_materials()
    fields = ("normal", "rho_d", "rho_s", "sigma_x", "sigma_y", "n_valid")
    fits = {k: np.asarray(fits[k] if isinstance(fits, dict) else getattr(fits, k)) for k in fields}
    keep = (fits["n_valid"] >= 8) & np.all(np.isfinite(fits["normal"]), -1)
    if keep.sum() < MIN_MEMBERS // 2:   # too few for any material (a row needs this many members)
        return no_materials(sample=n)
    ratio, weight = ratio[keep], weight[keep]
    fits = {k: v[keep] for k, v in fits.items()}
    n = ratio.shape[0]
    normals = np.asarray(fits["normal"], np.float32)
    theta_s = np.log(np.maximum(np.stack([fits["sigma_x"], fits["sigma_y"]], -1) - SIGMA_FLOOR, 1e-6))
    valid = weight > 0
    nv = np.maximum(valid.sum(1), 1)
    w = np.where(valid, weight * (nv / np.maximum(weight.sum(1), 1e-30))[:, None], 0.0).astype(np.float64)
    r64 = np.where(valid[..., None], ratio, 0.0).astype(np.float64)
    mean_sq = np.maximum(np.einsum("tl,tlc->t", w, r64 * r64) / (3 * nv), 1e-30)
    colour = _colour(np.asarray(fits["rho_d"], np.float64))

    # texels whose free lobe carries a visible share of their light: their slopes seed the lobes
    ab = np.asarray(_columns_of_each(normals, theta_s.astype(np.float32), dirs, view, model), np.float64)
    spec = np.einsum("tl,tl->t", w, ab[:, 1] ** 2) * np.mean(np.asarray(fits["rho_s"], np.float64) ** 2, -1)
    lobed = spec / (mean_sq * 3 * nv) > LOBE_SHARE

    # clusters of colour
    labels = _divisive_clusters(colour, MAX_MATERIALS, MIN_MEMBERS, SPLIT_SPREAD)
    groups = [np.flatnonzero(labels == j) for j in range(labels.max() + 1)]
    groups = [g for g in groups if g.size >= MIN_MEMBERS] or [np.arange(n)]

    lobe_cols = {}

    def cols(s):
        key = tuple(np.round(np.asarray(s, float), 6))
        if key not in lobe_cols:
            a, b = _columns_of(jnp.asarray(normals), jnp.asarray(np.asarray(s, np.float32)), jnp.asarray(dirs),
                               jnp.asarray(view), model)
            lobe_cols[key] = (np.asarray(a, np.float64), np.asarray(b, np.float64))
        return lobe_cols[key]

    def seed(members):
        seen = members[lobed[members]]
        return np.median(theta_s[seen], axis=0) if seen.size else np.full(2, _MATTE_S)

    seeds = [seed(g) for g in groups]
    assign = labels
    rows = []
    for round_ in range(_REASSIGN_ROUNDS + 1):
        rows = []
        for j, s0 in enumerate(seeds):
            members = np.flatnonzero(assign == j) if round_ else groups[j]
            if members.size < MIN_MEMBERS // 2:
                rows.append(None)
                continue
            def score(s, members=members):
                a, b = cols(s)
                mu, c = _shared_lobe_fit(r64[members], w[members], a[members], b[members])
                return c.sum(), s, mu

            if round_ == 0:   # a coarse isotropic search over every slope first
                s0 = min((score(np.full(2, x)) for x in _COARSE), key=lambda t: t[0])[1]
            best = min((score(s0 + np.array([dx, dy])) for dx in _GRID for dy in _GRID), key=lambda t: t[0])
            centre = colour[members].mean(0)
            spread = max(float(np.sqrt(np.mean((colour[members] - centre) ** 2))), COLOUR_SPREAD_FLOOR)
            rows.append((best[1], best[2], centre, spread, members.size))
        if all(r is None for r in rows):   # every material lost its members: no table
            return no_materials(sample=n)
        seeds = [r[0] if r is not None else None for r in rows]
        # reassign every texel to the material that explains it best (data, colour, share)
        costs = np.full((n, len(rows)), np.inf)
        prior_terms = np.zeros((n, len(rows)))
        for j, row in enumerate(rows):
            if row is None:
                continue
            s, mu, centre, spread, count = row
            a, b = cols(s)
            saa = np.maximum(np.sum(w * a * a, 1), 1e-30)
            rd = np.maximum(np.einsum("tl,tlc->tc", w * a, r64 - mu * b[..., None]) / saa[:, None], 0.0)
            r = r64 - rd[:, None, :] * a[..., None] - mu * b[..., None]
            cost = 0.5 * np.einsum("tl,tlc->t", w, r * r)
            d = (colour - centre) / spread
            costs[:, j] = cost
            prior_terms[:, j] = 0.5 * np.sum(d * d, -1) + 3 * np.log(spread) - np.log(count / n)
        var = max(np.median(np.min(costs, 1) * 2 / (3 * nv) / mean_sq), NOISE_FLOOR) * mean_sq   # noise, as below
        assign = np.argmin(costs / var[:, None] + prior_terms, 1)
        seeds = [s if s is not None else np.full(2, _MATTE_S) for s in seeds]
    data_cost = []
    for j in range(len(rows)):
        if rows[j] is None:
            continue
        members = np.flatnonzero(assign == j)
        a, b = cols(rows[j][0])
        data_cost.append((members, _shared_lobe_fit(r64[members], w[members], a[members], b[members])[1]))
    rel = np.concatenate([2 * c / (3 * nv[m]) / mean_sq[m] for m, c in data_cost])
    noise = float(np.median(rel))

    out = [r for r in rows if r is not None][:MAX_MATERIALS]
    counts = np.array([np.sum(assign == j) for j, r in enumerate(rows) if r is not None], float)[:MAX_MATERIALS]
    rho = np.zeros((MAX_MATERIALS, 3), np.float32)
    srow = np.full((MAX_MATERIALS, 2), _MATTE_S, np.float32)
    log_share = np.full(MAX_MATERIALS, -np.inf, np.float32)
    centres = np.zeros((MAX_MATERIALS, 3), np.float32)
    spreads = np.ones(MAX_MATERIALS, np.float32)
    for j, (s, mu, centre, spread, _) in enumerate(out):
        if counts[j] > 0:
            rho[j], srow[j], log_share[j] = mu, s, np.log(counts[j] / counts.sum())
            centres[j], spreads[j] = centre, spread
    return MaterialTable(jnp.asarray(rho), jnp.asarray(srow), jnp.asarray(log_share), jnp.asarray(centres),
                         jnp.asarray(spreads), jnp.asarray(noise, np.float32), jnp.asarray(n, np.int32))


@functools.partial(jax.jit, static_argnames="model")
def _columns_of_each(normals, s, light_dirs, view_dir, model):
    """(a, b) stacked `T 2 L` for per-texel normals and log-slopes s (`T 2`)."""
    lights = lights_of(light_dirs, view_dir)

    def one(n, si):
        theta = jnp.concatenate([geometry_to_theta(n, 1.0, 1.0)[:2], si])
        return jnp.stack(columns(theta, lights, model))

    return jax.vmap(one)(jnp.asarray(normals), jnp.asarray(s, jnp.float32))

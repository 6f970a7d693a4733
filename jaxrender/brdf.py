"""The Ashikhmin-style anisotropic model of paper 004 (eq. 1): the one BRDF of the toolkit.

All directions are unit vectors in the sample (tangent) frame: x along the texture's columns,
y along its rows toward the top, z the geometric normal. For a lobe with normal N the tangent is
T = x projected onto the plane of N, B = N x T, and with h the half vector of light and view

    D = exp(-((h.T / sigma_x)^2 + (h.B / sigma_y)^2) / (h.N)^2),   0 where h.N <= 0.

`reciprocal` (default):  R = rho_d cos_i + rho_s D / cos_r,       f = R / (pi cos_i)
`paper` (as printed):    R = rho_d cos_i + rho_s D / (cos_i cos_r)

R is what a capture observes (radiance over a white board's radiance at normal incidence, times
the board's reflectance); f is what the renderer shades with. Cosines are taken to each lobe's
normal N; the diffuse term uses the weight-averaged normal normalize((1 - weight) N0 + weight N1),
which is lobe 0's normal for a one-lobe texel (a two-lobe pyramid texel summarizing children with
two directions keeps their mean normal for its diffuse shading). Two-lobe texels mix their specular terms as
(1 - weight) * lobe0 + weight * lobe1.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .maths import dot, normalize, safe_div

__all__ = ["Lobe", "BTFTexel", "MODELS", "SIGMA_FLOOR", "COS_FLOOR", "tangent_frame", "slope_distribution",
           "slope_distribution_from_components", "specular_factor", "lobe_reflectance", "reflectance", "brdf",
           "half_vector", "diffuse_normal"]

MODELS = ("reciprocal", "paper")
SIGMA_FLOOR = 1e-3  # slopes below this are numerically a mirror; the fit floors sigma here
COS_FLOOR = 1e-4    # keeps 1/cos finite at exactly grazing directions; the paper's captures stop at 87 deg


class Lobe(eqx.Module):
    """One specular lobe. Leading batch axes are allowed on every field (e.g. `H W`)."""

    rho_s: Float[Array, "... 3"]
    normal: Float[Array, "... 3"]
    sigma_x: Float[Array, "..."]
    sigma_y: Float[Array, "..."]


class BTFTexel(eqx.Module):
    """A texel of a BTF level: diffuse albedo plus one or two lobes (`weight` = 0: one lobe)."""

    rho_d: Float[Array, "... 3"]
    lobe0: Lobe
    lobe1: Lobe
    weight: Float[Array, "..."]

    @staticmethod
    def single(rho_d, rho_s, normal, sigma_x, sigma_y) -> "BTFTexel":
        """A one-lobe texel (lobe 1 a copy of lobe 0 with weight 0)."""
        lobe = Lobe(jnp.asarray(rho_s), jnp.asarray(normal), jnp.asarray(sigma_x), jnp.asarray(sigma_y))
        return BTFTexel(jnp.asarray(rho_d), lobe, lobe, jnp.zeros_like(jnp.asarray(sigma_x)))

    @staticmethod
    def from_channels(channels: dict) -> "BTFTexel":
        """From a BTF level's channel dict (design.md names: rho_d.R, normal.X, lobe1.sigma_x, ...)."""
        c = {k: jnp.asarray(v) for k, v in channels.items()}
        rgb = lambda p: jnp.stack([c[f"{p}.R"], c[f"{p}.G"], c[f"{p}.B"]], axis=-1)  # noqa: E731
        xyz = lambda p: jnp.stack([c[f"{p}.X"], c[f"{p}.Y"], c[f"{p}.Z"]], axis=-1)  # noqa: E731
        lobe0 = Lobe(rgb("rho_s"), xyz("normal"), c["sigma_x"], c["sigma_y"])
        if "lobe1.sigma_x" in c:
            lobe1 = Lobe(rgb("lobe1.rho_s"), xyz("lobe1.normal"), c["lobe1.sigma_x"], c["lobe1.sigma_y"])
            weight = c.get("weight", jnp.zeros_like(c["sigma_x"]))
        else:
            lobe1, weight = lobe0, jnp.zeros_like(c["sigma_x"])
        return BTFTexel(rgb("rho_d"), lobe0, lobe1, weight)

    def to_channels(self) -> dict:
        """The inverse of `from_channels` (numpy-convertible arrays keyed by channel name)."""
        out = {}
        for prefix, lobe in (("", self.lobe0), ("lobe1.", self.lobe1)):
            for i, ch in enumerate("RGB"):
                out[f"{prefix}rho_s.{ch}"] = lobe.rho_s[..., i]
            for i, ax in enumerate("XYZ"):
                out[f"{prefix}normal.{ax}"] = lobe.normal[..., i]
            out[f"{prefix}sigma_x"] = lobe.sigma_x
            out[f"{prefix}sigma_y"] = lobe.sigma_y
        for i, ch in enumerate("RGB"):
            out[f"rho_d.{ch}"] = self.rho_d[..., i]
        out["weight"] = self.weight
        return out


def tangent_frame(normal: Float[ArrayLike, "... 3"]
                  ) -> tuple[Float[Array, "... 3"], Float[Array, "... 3"], Float[Array, "... 3"]]:
    """(T, B, N): T = the sample x axis projected onto N's tangent plane, B = N x T."""
    n = normalize(normal)
    x = jnp.zeros_like(n).at[..., 0].set(1.0)
    t = x - dot(x, n)[..., None] * n
    # N along +-x (never for upper-hemisphere normals that are not fully grazing): fall back to y.
    y = jnp.zeros_like(n).at[..., 1].set(1.0)
    degenerate = (dot(t, t) < 1e-12)[..., None]
    t = normalize(jnp.where(degenerate, y - dot(y, n)[..., None] * n, t))
    return t, jnp.cross(n, t), n


def half_vector(wi: Float[ArrayLike, "... 3"], wo: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3"]:
    return normalize(jnp.asarray(wi) + jnp.asarray(wo))


def slope_distribution_from_components(ht: Float[ArrayLike, "..."], hb: Float[ArrayLike, "..."],
                                       hn: Float[ArrayLike, "..."], sigma_x: Float[ArrayLike, "..."],
                                       sigma_y: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """D of eq. 1 from the half vector's components in the lobe frame (h.T, h.B, h.N).

    The one implementation of D: `slope_distribution` projects a half vector and calls it; the
    fit evaluates it on structure-of-arrays components of all light directions at once.
    """
    sx = jnp.maximum(sigma_x, SIGMA_FLOOR)
    sy = jnp.maximum(sigma_y, SIGMA_FLOOR)
    front = hn > 1e-6
    safe_hn = jnp.where(front, hn, 1.0)
    exponent = ((ht / sx) ** 2 + (hb / sy) ** 2) / safe_hn**2
    return jnp.where(front, jnp.exp(-jnp.minimum(exponent, 80.0)), 0.0)


def slope_distribution(h: Float[ArrayLike, "... 3"], lobe: Lobe) -> Float[Array, "..."]:
    """D of eq. 1 for the half vector `h` (sample frame)."""
    t, b, n = tangent_frame(lobe.normal)
    return slope_distribution_from_components(dot(h, t), dot(h, b), dot(h, n), lobe.sigma_x, lobe.sigma_y)


def specular_factor(d: Float[ArrayLike, "..."], cos_i: Float[ArrayLike, "..."], cos_r: Float[ArrayLike, "..."], *,
                    model: str = "reciprocal") -> Float[Array, "..."]:
    """The specular part of R per unit rho_s: D / cos_r (reciprocal) or D / (cos_i cos_r) (paper),
    0 unless both directions are above the lobe's tangent plane."""
    if model not in MODELS:
        raise ValueError(f"unknown model {model!r}: use one of {MODELS}")
    lit = (cos_i > 0) & (cos_r > 0)
    denom = jnp.maximum(cos_r, COS_FLOOR)
    if model == "paper":
        denom = denom * jnp.maximum(cos_i, COS_FLOOR)
    return jnp.where(lit, safe_div(d, denom), 0.0)


def lobe_reflectance(lobe: Lobe, wi: Float[ArrayLike, "... 3"], wo: Float[ArrayLike, "... 3"], *,
                     model: str = "reciprocal") -> Float[Array, "... 3"]:
    """The specular part of R for one lobe: rho_s D / cos_r (reciprocal) or / (cos_i cos_r) (paper)."""
    n = normalize(lobe.normal)
    d = slope_distribution(half_vector(wi, wo), lobe)
    return specular_factor(d, dot(wi, n), dot(wo, n), model=model)[..., None] * lobe.rho_s


def diffuse_normal(texel: BTFTexel) -> Float[Array, "... 3"]:
    """normalize((1 - weight) N0 + weight N1): lobe 0's normal where the texel has one lobe."""
    w = texel.weight[..., None]
    return normalize((1 - w) * normalize(texel.lobe0.normal) + w * normalize(texel.lobe1.normal))


def reflectance(texel: BTFTexel, wi: Float[ArrayLike, "... 3"], wo: Float[ArrayLike, "... 3"], *,
                model: str = "reciprocal") -> Float[Array, "... 3"]:
    """R of eq. 1 (what a capture observes) for light direction `wi` and view direction `wo`."""
    wi, wo = jnp.asarray(wi), jnp.asarray(wo)
    n0 = diffuse_normal(texel)
    geometric = (wi[..., 2] > 0) & (wo[..., 2] > 0)
    cos_i = jnp.maximum(dot(wi, n0), 0.0)
    w = texel.weight[..., None]
    specular = (1 - w) * lobe_reflectance(texel.lobe0, wi, wo, model=model)
    specular = specular + w * lobe_reflectance(texel.lobe1, wi, wo, model=model)
    return jnp.where(geometric[..., None], texel.rho_d * cos_i[..., None] + specular, 0.0)


def brdf(texel: BTFTexel, wi: Float[ArrayLike, "... 3"], wo: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3"]:
    """f (1/sr) of the reciprocal model: rho_d/pi + sum of rho_s D / (pi cos_i cos_r).

    Radiance leaving toward `wo` under irradiance E from `wi` is f * E_normal * cos(wi, z)
    in the renderer; here f is given with respect to lobe normals as in `reflectance`.
    """
    wi, wo = jnp.asarray(wi), jnp.asarray(wo)
    n0 = diffuse_normal(texel)
    cos_i = jnp.maximum(dot(wi, n0), COS_FLOOR)
    return reflectance(texel, wi, wo) / (jnp.pi * cos_i[..., None])

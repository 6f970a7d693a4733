"""Textured emitting quads (bonfires, paper 004 eq. 4), sampled over their areas by emitted power.

Quad f has centre c, half-extent vectors u (toward the texture's right edge) and v (toward its
top edge): the point at texture coordinates (s, t) (s along columns, t along rows, t = 0 at the
top, as `jaxrender.textures`) is c + (2s - 1) u + (1 - 2t) v. Emission is two-sided with radiance
`emission[f, row, col]` (linear RGB) on both faces.

Sampling: a texel (f, row, col) is drawn with probability proportional to its luminance times
its area (4 |u x v| / (H W)), then a point uniformly inside it, so the area pdf is
    p_A(y) = lum(texel(y)) / sum_texels lum * area,
and the radiance at x from sample y is estimated by L_e(y) |cos_y| / |x - y|^2 / p_A(y).
All-black emission gives zero-power samples (radiance 0, pdf 1).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int, PRNGKeyArray

from ..io import luminance
from ..maths import normalize

__all__ = ["QuadLights", "QuadLightSamples", "sample_quad_lights", "quad_light_radiance_at"]

class QuadLights(eqx.Module):
    center: Float[Array, "F 3"]
    u: Float[Array, "F 3"]
    v: Float[Array, "F 3"]
    emission: Float[Array, "F H W 3"]

    @property
    def normal(self) -> Float[Array, "F 3"]:
        return normalize(jnp.cross(self.u, self.v))

    @property
    def area(self) -> Float[Array, " F"]:
        c = jnp.cross(self.u, self.v)
        return 4 * jnp.sqrt(jnp.sum(c * c, axis=-1))


class QuadLightSamples(eqx.Module):
    position: Float[Array, "K 3"]
    normal: Float[Array, "K 3"]
    radiance: Float[Array, "K 3"]
    pdf_area: Float[Array, " K"]
    light: Int[Array, " K"]


def sample_quad_lights(lights: QuadLights, key: PRNGKeyArray, k: int = 20) -> QuadLightSamples:
    """Draw `k` points over all quads by emitted power (module docstring)."""
    f, h, w = lights.emission.shape[0], lights.emission.shape[1], lights.emission.shape[2]
    e = lights.emission
    lum = jnp.maximum(luminance(e), 0.0)                                                  # F H W
    texel_area = lights.area / (h * w)                                                    # F
    power = (lum * texel_area[:, None, None]).reshape(-1)
    total = jnp.sum(power)
    safe_total = jnp.where(total > 0, total, 1.0)
    cdf = jnp.cumsum(power) / safe_total
    xi = jax.random.uniform(key, (k, 3), dtype=e.dtype)
    idx = jnp.clip(jnp.searchsorted(cdf, xi[:, 0], side="right"), 0, f * h * w - 1)
    fi, rem = idx // (h * w), idx % (h * w)
    row, col = rem // w, rem % w
    s = (col.astype(e.dtype) + xi[:, 1]) / w
    t = (row.astype(e.dtype) + xi[:, 2]) / h
    pos = lights.center[fi] + (2 * s - 1)[:, None] * lights.u[fi] + (1 - 2 * t)[:, None] * lights.v[fi]
    rad = e[fi, row, col]
    pdf = jnp.where(total > 0, lum[fi, row, col] / safe_total, 1.0)
    rad = jnp.where(total > 0, rad, 0.0)
    return QuadLightSamples(pos, lights.normal[fi], rad, pdf, fi.astype(jnp.int32))


def quad_light_radiance_at(samples: QuadLightSamples, points: Float[Array, "N 3"]
                           ) -> tuple[Float[Array, "N K 3"], Float[Array, "N K 3"]]:
    """Per point and sample: the unit direction toward the sample and L_e |cos_y| / (r^2 p_A K)
    (the weight of the sample in the K-sample estimator, before the BRDF and visibility)."""
    d = samples.position[None, :, :] - points[:, None, :]
    r2 = jnp.maximum(jnp.sum(d * d, axis=-1), 1e-8)
    wi = d / jnp.sqrt(r2)[..., None]
    cos_y = jnp.abs(jnp.sum(wi * samples.normal[None, :, :], axis=-1))
    k = samples.pdf_area.shape[0]
    g = cos_y / (r2 * samples.pdf_area[None, :] * k)
    return wi, samples.radiance[None, :, :] * g[..., None]

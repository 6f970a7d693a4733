"""One Noh frame (paper 004, eqs. 2-4): I = I_static + I_dynamic. I_dynamic: K_f points drawn over
all four flame quads by emitted power for the frame (`jaxrender.lights.sample_quad_lights`),
shared by all shading points; flames are volumes, so each flame quad is treated as facing the
shading point (|cos_y| = 1) while its texture gives the radiance; each fire's visibility is the
sequence's PCSS. Visible flames are added to the image (additive, in front of whatever lies
behind them)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from jaxrender.lights import QuadLightSamples, sample_quad_lights
from jaxrender.textures import bilinear

from .prepare import NohPrepared
from .scene import NohScene
from .shading import SurfaceLight, shade_floor, shade_garment


def fire_light(samples: QuadLightSamples, points: Float[Array, "N 3"], vis: Float[Array, "N Q"],
               n_fires: int) -> SurfaceLight:
    """The K flame samples seen from each point, weighted by that fire's visibility there."""
    k = samples.position.shape[0]
    onehot = (samples.light[:, None] == jnp.arange(n_fires, dtype=jnp.int32)[None, :]).astype(points.dtype)   # K Q
    d = samples.position[None, :, :] - points[:, None, :]
    r2 = jnp.maximum(jnp.sum(d * d, -1), 1e-8)
    g = (vis @ onehot.T) / (r2 * samples.pdf_area[None, :] * k)          # billboard flames: |cos_y| = 1
    return SurfaceLight(d / jnp.sqrt(r2)[..., None], samples.radiance[None, :, :] * g[..., None])


def noh_frame(scene: NohScene, prep: NohPrepared, emission: Float[Array, "Q H W 3"], key: PRNGKeyArray, *,
              k_fire: int = 20, blend: str = "shading") -> Float[Array, "H W 3"]:
    """One frame (linear radiance): I_static + firelight with PCSS + visible flames over the sky."""
    fires = eqx.tree_at(lambda f: f.emission, scene.fires, emission)
    samples = sample_quad_lights(fires, key, k_fire)
    n_fires = fires.center.shape[0]
    g = shade_garment(scene.mats, prep.garment, fire_light(samples, prep.garment.position, prep.garment_vis, n_fires),
                      blend=blend)
    f = shade_floor(prep.floor, fire_light(samples, prep.floor.position, prep.floor_vis, n_fires))
    h, w = prep.background.shape[0], prep.background.shape[1]
    img = prep.background.reshape(h * w, 3)
    img = img.at[prep.garment.index].set(g + prep.garment_static)
    img = img.at[prep.floor.index].set(f + prep.floor_static)
    img = img.reshape(h, w, 3)
    for i in range(n_fires):  # four fires: unrolled
        img = img + prep.flames.hit[i][..., None] * bilinear(emission[i], prep.flames.uv[i], wrap="clamp")
    return img


noh_frame_jit = eqx.filter_jit(noh_frame)  # one compile per scene size and k_fire

"""The surface points a Noh frame shades, and their shading under K light samples (paper 004,
eqs. 2-4): the garment by its BTF pyramid (`jaxrender.fabric.shade_fabric`), the floor by one lobe."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from jaxrender.brdf import BTFTexel
from jaxrender.fabric import MaterialSet, shade_fabric, shade_single_lobe


class GarmentPoints(eqx.Module):
    """The garment's visible pixels (`index` into the flattened image) and their surface data."""

    index: Int[Array, " G"]
    position: Float[Array, "G 3"]
    frame: Float[Array, "G 3 3"]        # tangent, bitangent, normal (facing the viewer)
    wo: Float[Array, "G 3"]
    uv: Float[Array, "G 2"]             # BTF texture coordinates (mask uv x tiles) and their footprint
    duv_dx: Float[Array, "G 2"]
    duv_dy: Float[Array, "G 2"]
    material: Int[Array, " G"]           # index into LABELS
    colour: Float[Array, "G 3"]         # the mask's colour, rho_d of the plain weave
    use_colour: Float[Array, " G"]       # 1 where the plain weave takes the mask's colour


class FloorPoints(eqx.Module):
    """The floor's visible pixels and its texels there."""

    index: Int[Array, " P"]
    position: Float[Array, "P 3"]
    wo: Float[Array, "P 3"]
    texel: BTFTexel


class SurfaceLight(eqx.Module):
    """K light samples per point: directions toward the light and radiance x geometry / pdf."""

    direction: Float[Array, "N K 3"]
    weight: Float[Array, "N K 3"]


def shared_light(directions: Float[Array, "K 3"], weights: Float[Array, "K 3"], n: int) -> SurfaceLight:
    """The same K distant samples for all n points (the environment)."""
    k = directions.shape[0]
    return SurfaceLight(jnp.broadcast_to(directions[None], (n, k, 3)), jnp.broadcast_to(weights[None], (n, k, 3)))


def shade_garment(mats: MaterialSet, garment: GarmentPoints, light: SurfaceLight, *,
                  blend: str = "shading") -> Float[Array, "G 3"]:
    return shade_fabric(mats, garment.material, garment.uv, garment.duv_dx, garment.duv_dy, garment.frame, garment.wo,
                        light.direction, light.weight, diffuse_override=garment.colour,
                        use_override=garment.use_colour, blend=blend)


def shade_floor(floor: FloorPoints, light: SurfaceLight) -> Float[Array, "P 3"]:
    n = floor.position.shape[0]
    up = jnp.asarray([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]], dtype=floor.position.dtype)
    return shade_single_lobe(floor.texel, jnp.broadcast_to(up, (n, 3, 3)), floor.wo, light.direction, light.weight)

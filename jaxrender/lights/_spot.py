"""Spot light per design.md's contract (the same light as Mitsuba 3's `spot` emitter).

Radiant intensity toward a point P at distance s from the light, in the light's local frame
(Mitsuba's look-at frame: z toward `target`, x = normalize(up x z), y = z x x):

    I(P) = intensity * falloff(theta) * light_map(uv),     irradiance-like factor 1 / s^2 applied by the caller

- theta = angle between the local direction w and z; falloff = 1 for theta <= beam_width, linear
  in angle down to 0 at `cutoff`, 0 beyond (and behind the light).
- uv = 0.5 + 0.5 * (w.x, w.y) / (w.z * tan(cutoff)); u along the map's columns, v along its rows
  (v = 0 at the top of row 0); bilinear lookup clamped at the border (`jaxrender.textures.bilinear`).
- No light map = a 1x1 white map.
- `mips`: the light map's mip pyramid (`jaxrender.textures.pack_mips`), built once when the light
  is made, for lookups at the level a footprint needs (the fast shaft methods' fog samples);
  None for a 1 x 1 map. Replace a light map with `with_light_map` (it rebuilds the pyramid), not
  with `eqx.tree_at` on `light_map` alone.

Gradient-safe: theta uses atan2(safe_norm(w.xy), w.z), finite (zero) gradient on the cone axis; the
division by w.z is guarded behind the light. A batch of lights is either a Python list of
`SpotLight`s or one `SpotLight` whose leaves carry a leading axis (`stack_spotlights`); every
method works on one light, `jax.vmap` it over a stacked batch.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ..camera import look_at_frame
from ..maths import atan_nonneg, normalize, safe_norm
from ..textures import PackedMips, bilinear, pack_mips, quantize

__all__ = ["SpotLight", "stack_spotlights", "unstack_spotlights", "cone_angle"]


def _dot(a: Array, b: Array) -> Array:
    """a . b over the last axis, b a single 3-vector (broadcast without rank promotion)."""
    return a[..., 0] * b[0] + a[..., 1] * b[1] + a[..., 2] * b[2]


def cone_angle(local: Float[ArrayLike, "*B 3"]) -> Float[Array, "*B"]:
    """Angle between a local vector and the +z axis, in [0, pi]; gradient-safe on the axis."""
    local = jnp.asarray(local)
    rxy = safe_norm(local[..., :2])
    z = local[..., 2]
    near_axis = z >= rxy  # theta <= 45 deg: atan(rxy / z); else pi/2 - atan(z / rxy)
    safe_z = jnp.where(near_axis & (z > 0), z, 1.0)
    side_ok = ~near_axis & (rxy > 0)
    safe_r = jnp.where(side_ok, rxy, 1.0)
    t_axis = atan_nonneg(jnp.where(near_axis, rxy / safe_z, 0.0))
    tan_side = jnp.where(side_ok, jnp.abs(z) / safe_r, jnp.where(near_axis, 0.0, 1e30))
    t_side = 0.5 * jnp.pi - jnp.sign(z) * atan_nonneg(tan_side)
    theta = jnp.where(near_axis, t_axis, t_side)
    return theta


class SpotLight(eqx.Module):
    """One spot light (or a stacked batch: every leaf with a leading axis).

    Fields: `position`, `target`, `up` (3,), `cutoff_deg`, `beam_width_deg` (scalars, degrees),
    `intensity` (3,) linear RGB radiant intensity (W/sr per channel), `light_map` (H, W, 3) linear RGB;
    `mips` is derived from `light_map` (module docstring).
    """

    position: Float[Array, "3"]
    target: Float[Array, "3"]
    up: Float[Array, "3"]
    cutoff_deg: Float[Array, ""]
    beam_width_deg: Float[Array, ""]
    intensity: Float[Array, "3"]
    light_map: Float[Array, "H W 3"]
    mips: PackedMips | None

    def __init__(self, position, target, up=(0.0, 0.0, 1.0), cutoff_deg=20.0, beam_width_deg=None,
                 intensity=(1.0, 1.0, 1.0), light_map=None):
        self.position = jnp.asarray(position, dtype=float)
        self.target = jnp.asarray(target, dtype=float)
        self.up = jnp.asarray(up, dtype=float)
        self.cutoff_deg = jnp.asarray(cutoff_deg, dtype=float)
        self.beam_width_deg = (0.75 * self.cutoff_deg if beam_width_deg is None
                               else jnp.asarray(beam_width_deg, dtype=float))
        intensity = jnp.asarray(intensity, dtype=float)
        self.intensity = (jnp.broadcast_to(intensity, self.position.shape[:-1] + (3,)) if intensity.ndim == 0
                          else intensity)
        self.light_map = jnp.ones((1, 1, 3)) if light_map is None else jnp.asarray(light_map, dtype=float)
        textured = self.light_map.shape[-3] * self.light_map.shape[-2] > 1 and self.light_map.ndim == 3
        self.mips = pack_mips(self.light_map) if textured else None

    def with_light_map(self, light_map) -> "SpotLight":
        """The same light projecting another light map (its mip pyramid rebuilt)."""
        return SpotLight(self.position, self.target, self.up, self.cutoff_deg, self.beam_width_deg, self.intensity,
                         light_map)

    # -- frame ---------------------------------------------------------------------------------
    def frame(self) -> tuple[Float[Array, "3"], Float[Array, "3"], Float[Array, "3"]]:
        """(x, y, z) of Mitsuba 3's look-at frame at the light."""
        return look_at_frame(self.position, self.target, self.up)

    def rotation(self) -> Float[Array, "3 3"]:
        """Rows x, y, z: local = rotation @ (P - position)."""
        return jnp.stack(self.frame(), axis=0)

    def to_local(self, points: Float[ArrayLike, "*B 3"]) -> Float[Array, "*B 3"]:
        """Points in the light's frame (not normalized: its length is the distance s)."""
        points = jnp.asarray(points)
        rel = points - jnp.broadcast_to(self.position, points.shape)
        x, y, z = self.frame()
        # component arithmetic: XLA's CPU matmul is slow for a K = 3 contraction over many points
        return jnp.stack([_dot(rel, x), _dot(rel, y), _dot(rel, z)], axis=-1)

    @property
    def cutoff(self) -> Float[Array, ""]:
        return jnp.deg2rad(self.cutoff_deg)

    @property
    def beam_width(self) -> Float[Array, ""]:
        return jnp.deg2rad(self.beam_width_deg)

    # -- angular terms (all take local vectors, any length) --------------------------------------
    def falloff(self, local: Float[ArrayLike, "*B 3"]) -> Float[Array, "*B"]:
        """1 inside the beam width, linear in angle to 0 at the cutoff, 0 outside (and behind)."""
        local = jnp.asarray(local)
        z = local[..., 2]
        front = z > 0
        theta = atan_nonneg(safe_norm(local[..., :2]) / jnp.where(front, z, 1.0))
        cut, beam = self.cutoff, jnp.minimum(self.beam_width, self.cutoff)
        width = cut - beam
        safe_width = jnp.where(width > 1e-9, width, 1.0)
        ramp = jnp.where(width > 1e-9, (cut - theta) / safe_width, 1.0)
        value = jnp.where(theta <= beam, 1.0, ramp)
        return jnp.where(front & (theta < cut), value, 0.0).astype(local.dtype)

    def uv(self, local: Float[ArrayLike, "*B 3"]) -> Float[Array, "*B 2"]:
        """Light-map coordinates uv = 0.5 + 0.5 * xy / (z tan(cutoff)); (0.5, 0.5) behind the light."""
        local = jnp.asarray(local)
        z = local[..., 2]
        front = z > 1e-12
        scale = 0.5 / (jnp.where(front, z, 1.0) * jnp.tan(self.cutoff))
        uv = 0.5 + local[..., :2] * scale[..., None]
        return jnp.where(front[..., None], uv, 0.5)

    def map_value(self, uv: Float[ArrayLike, "*B 2"], *, quantize_bits: int = 0,
                  footprint: Float[ArrayLike, "*B"] | None = None) -> Float[Array, "*B 3"]:
        """Bilinear, clamped light-map lookup; with `quantize_bits` the map is first rounded to
        2^B - 1 levels of its maximum (8-bit textures). A 1 x 1 map (no light map) is its texel
        everywhere, read without gathers (the five-spot stage's surface pass: ~6 % less CPU).
        `footprint` (radians seen from the light): instead, the nearest texel of the mip level
        whose texels are no larger than it (`mips`; one gather, whatever the map's size). No
        gradient through uv."""
        texture = self.quantized_map(quantize_bits)
        uv = jnp.asarray(uv)
        if texture.shape[:2] == (1, 1):
            return jnp.broadcast_to(texture[0, 0], uv.shape[:-1] + texture.shape[2:])
        if footprint is None:
            return bilinear(texture, uv, wrap="clamp")
        if quantize_bits:
            raise ValueError("light-map lookups by footprint read the unquantized mip pyramid")
        mips = self.mips
        level = mips.level_for(jnp.asarray(footprint) * (mips.side / (2.0 * jnp.tan(self.cutoff))))
        uv = jax.lax.stop_gradient(uv)
        texel = mips.index(uv[..., 0], uv[..., 1], jax.lax.stop_gradient(level))
        return jnp.broadcast_to(mips.fetch(texel), texel.shape + self.light_map.shape[-1:])

    def quantized_map(self, quantize_bits: int = 0) -> Float[Array, "H W 3"]:
        if quantize_bits == 0:
            return self.light_map
        return quantize(self.light_map, quantize_bits, scale=jnp.max(self.light_map))

    def radiant_intensity(self, points: Float[ArrayLike, "*B 3"], *, quantize_bits: int = 0,
                          footprint: Float[ArrayLike, "*B"] | None = None
                          ) -> tuple[Float[Array, "*B 3"], Float[Array, "*B"], Float[Array, "*B 3"]]:
        """(I, s, w): RGB radiant intensity toward each point, its distance s from the light, and
        the unit propagation direction w (world frame) from the light to the point. `footprint`:
        the size (a length across the direction from the light, at the point) the light-map
        lookup covers (`map_value`); None: bilinear."""
        points = jnp.asarray(points)
        local = self.to_local(points)
        s = safe_norm(local)
        fall = self.falloff(local)
        angle = None if footprint is None else jnp.asarray(footprint) / jnp.maximum(s, 1e-9)
        value = self.map_value(self.uv(local), quantize_bits=quantize_bits, footprint=angle)
        rel = points - jnp.broadcast_to(self.position, points.shape)
        return value * (fall[..., None] * jnp.broadcast_to(self.intensity, value.shape)), s, normalize(rel)

    def cone_bound(self, reach: Float[ArrayLike, ""]) -> tuple[Float[Array, "3"], Float[Array, "3"], Float[Array, ""]]:
        """(apex, disk centre, disk radius): the lit cone cut at distance `reach` from the apex lies
        in the convex hull of the apex and this disk (perpendicular to the axis)."""
        _, _, z = self.frame()
        reach = jnp.asarray(reach)
        return self.position, self.position + reach * z, reach * jnp.tan(self.cutoff)


def stack_spotlights(lights: Sequence[SpotLight]) -> SpotLight:
    """One SpotLight whose leaves have a leading batch axis (light maps must share a shape)."""
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *lights)


def unstack_spotlights(lights: SpotLight | Sequence[SpotLight]) -> list[SpotLight]:
    """A list of single lights from a stacked batch (or the list itself)."""
    if isinstance(lights, SpotLight):
        if lights.position.ndim == 1:
            return [lights]
        n = lights.position.shape[0]
        return [jax.tree_util.tree_map(lambda x, i=i: x[i], lights) for i in range(n)]
    return list(lights)

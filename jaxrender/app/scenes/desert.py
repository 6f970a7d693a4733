"""The showcase desert of paper 001: 64 x 64 dunes (barchans grown by the dune automaton), wind
ripples (ripple automaton) bump-mapped onto every quad at up to 64 x 64 texels, a low sun, a
physically based clear sky, dune and ripple shadows, and sand dust.

World frame: z up, the dune grid in the xy plane (x along the grid's columns and the wind, y
along its rows), one dune cell = 1 length unit. The sky module works y up; `_to_sky` rotates.
"""

from __future__ import annotations

import functools
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxrender.camera import Camera
from jaxrender.io import tonemap
from jaxrender.lights import Sun, sun_direction_z_up
from jaxrender.shadows import heightfield_shadow
from jaxrender.sky import Atmosphere, optical_depth, sky_radiance
from jaxrender.terrain import (
    DustParticles,
    TerrainMaps,
    build_terrain_maps,
    composite_billboards,
    plan_quads,
    quad_capacities,
    render_terrain,
    shadow_steps,
    with_detail,
)
from jaxrender.textures import bilinear
from sims import (
    DuneParams,
    DustParams,
    RippleParams,
    init_dunes,
    init_ripples,
    simulate_dunes,
    simulate_dust,
    simulate_ripples,
)

from .footprints import footprint_detail

__all__ = ["DesertScene", "desert_scene", "default_camera", "render_desert", "desert_frame",
           "sky_for_sun", "to_display"]

SAND_ALBEDO = (0.60, 0.36, 0.18)  # linear RGB of desert sand (reddish ochre)
EXPOSURE = 0.55


def _to_sky(v: Array) -> Array:
    """z-up world -> the sky module's y-up frame (x stays, z -> y, y -> -z)."""
    return jnp.stack([v[..., 0], v[..., 2], -v[..., 1]], axis=-1)


class DesertScene(eqx.Module):
    """Precomputed scene: terrain maps plus the raw fields (for dust sizes and previews)."""

    maps: TerrainMaps
    ripple_height: Float[Array, "R R"]  # world units, mean 0
    dune_height: Float[Array, "N N"]  # world units


def _scale_to_slope(h: np.ndarray, max_slope: float, texel: float) -> np.ndarray:
    gx = (np.roll(h, -1, 1) - np.roll(h, 1, 1)) / (2 * texel)
    gy = (np.roll(h, -1, 0) - np.roll(h, 1, 0)) / (2 * texel)
    g = float(np.max(np.hypot(gx, gy)))
    return h * (max_slope / g if g > 0 else 1.0)


@functools.lru_cache(maxsize=8)
def _fields(dune_size: int, ripple_size: int, seed: int, dune_steps: int,
            ripple_steps: int) -> tuple[np.ndarray, np.ndarray]:
    """Grow the dune and ripple fields with the automata of `sims` (cached per process)."""
    k_dune, k_ripple = jax.random.split(jax.random.key(seed))
    dunes = simulate_dunes(init_dunes(k_dune, (dune_size, dune_size)), DuneParams(), steps=dune_steps)
    ripples = simulate_ripples(init_ripples(k_ripple, (ripple_size, ripple_size)), RippleParams(), steps=ripple_steps)
    return np.asarray(dunes, np.float64), np.asarray(ripples, np.float64)


def desert_scene(*, dune_size: int = 64, ripple_size: int = 64, texels: int = 64, seed: int = 0,
                 dune_steps: int = 800, ripple_steps: int = 2000, dune_slope: float = 0.7,
                 ripple_slope: float = 0.35, directions: int = 8, dune_field: np.ndarray | None = None,
                 ripple_field: np.ndarray | None = None, footprints: bool = False) -> DesertScene:
    """Build the scene: fields from the automata (or given), scaled to world units so that the
    steepest dune slope is `dune_slope` (sand's angle of repose ~35 deg) and the steepest ripple
    slope `ripple_slope`; then the terrain maps (normal pyramid, grain, horizon maps). With
    `footprints`, a trail of footprints crosses the foreground (`.footprints`, Fig. 18)."""
    if dune_field is None or ripple_field is None:
        d, r = _fields(dune_size, ripple_size, seed, dune_steps, ripple_steps)
        dune_field = d if dune_field is None else dune_field
        ripple_field = r if ripple_field is None else ripple_field
    dune_field = np.asarray(dune_field, np.float64)
    ripple_field = np.asarray(ripple_field, np.float64)
    dune_z = _scale_to_slope(dune_field - dune_field.min(), dune_slope, 1.0)
    ripple_z = _scale_to_slope(ripple_field - ripple_field.mean(), ripple_slope, 1.0 / texels)
    dtype = jnp.result_type(float)
    dune_j = jnp.asarray(dune_z, dtype)
    ripple_j = jnp.asarray(ripple_z, dtype)
    maps = _build_maps(dune_j, ripple_j, key=jax.random.key(seed + 7), spacing=1.0, texels=texels,
                       directions=directions)
    if footprints:
        detail, _ = footprint_detail(ripple_j, maps.quads[0], texels=texels, levels=maps.levels, directions=directions)
        maps = with_detail(maps, detail)
    return DesertScene(maps, ripple_j, dune_j)


_build_maps = jax.jit(build_terrain_maps,
                      static_argnames=("spacing", "texels", "levels", "directions", "grain_contrast"))


def default_camera(scene: DesertScene, *, width: int = 720, height: int = 480) -> Camera:
    """Looking across the wind (+y) from the field's southern edge, a little above the dunes, so
    that the barchans' lee faces (downwind, +x) and their shadows are seen from the side."""
    n = scene.maps.quads[0]
    top = float(jnp.max(scene.maps.z))
    eye = (0.47 * n, 0.016 * n, top + 0.0625 * n)
    target = (0.53 * n, 0.625 * n, 0.0)
    return Camera(eye, target, (0.0, 0.0, 1.0), 40.0, width=width, height=height)


def sky_for_sun(sun_elevation: float, sun_azimuth: float, *, sun_intensity: float = 20.0,
                env_size: tuple[int, int] = (128, 64)) -> tuple[Sun, Array, Array]:
    """(sun with the atmosphere's transmittance, a sky lat-long map H x W x 3 over the z-up
    world (rows: zenith -> nadir, columns: azimuth 0 -> 360 from +x toward +y), and the sky
    irradiance on a horizontal surface)."""
    direction = jnp.asarray(sun_direction_z_up(sun_elevation, sun_azimuth), dtype=jnp.result_type(float))
    return _sky_jit(direction, sun_intensity, env_size)


@functools.partial(jax.jit, static_argnames=("sun_intensity", "env_size"))
def _sky_jit(direction: Array, sun_intensity: float, env_size: tuple[int, int]) -> tuple[Sun, Array, Array]:
    atm = Atmosphere()
    tau_r, tau_m = optical_depth(_to_sky(direction)[None])
    beta = jnp.asarray(atm.rayleigh_scattering, direction.dtype)
    trans = jnp.exp(-(beta * tau_r[0] + atm.mie_extinction * tau_m[0]))
    sun = Sun(direction, sun_intensity * trans)
    w, h = env_size
    theta = (jnp.arange(h, dtype=direction.dtype) + 0.5) / h * jnp.pi  # from the zenith
    phi = (jnp.arange(w, dtype=direction.dtype) + 0.5) / w * 2 * jnp.pi
    st, ct = jnp.sin(theta)[:, None], jnp.cos(theta)[:, None]
    dirs = jnp.stack([st * jnp.cos(phi)[None, :], st * jnp.sin(phi)[None, :], ct * jnp.ones((1, w), direction.dtype)],
                     axis=-1)
    # below the horizon the sky map holds the horizon's radiance (the ground is drawn by the dunes)
    dirs_up = dirs.at[..., 2].set(jnp.maximum(dirs[..., 2], 0.02))
    env = sky_radiance(_to_sky(dirs_up / jnp.linalg.norm(dirs_up, axis=-1, keepdims=True)), _to_sky(direction),
                       sun_intensity=sun_intensity)
    solid = (jnp.pi / h) * (2 * jnp.pi / w) * st
    up = jnp.maximum(ct, 0.0)
    irradiance = jnp.sum(env * (solid * up)[..., None], axis=(0, 1))
    return sun, env, irradiance


def _sky_lookup(env: Array, dirs: Array) -> Array:
    phi = jnp.mod(jnp.arctan2(dirs[..., 1], dirs[..., 0]), 2 * jnp.pi)
    theta = jnp.arccos(jnp.clip(dirs[..., 2], -1.0, 1.0))
    uv = jnp.stack([phi / (2 * jnp.pi), theta / jnp.pi], axis=-1)
    return bilinear(env, uv, wrap="clamp")


@functools.partial(jax.jit, static_argnames=("capacities", "ripples", "dune_shadows", "ripple_shadows", "steps",
                                             "dust", "ray_steps"))
def _frame(maps, camera, sun, env, sky_irr, visible, level, particles, haze, *, capacities, ripples, dune_shadows,
           ripple_shadows, steps, dust, ray_steps):
    albedo = jnp.asarray(SAND_ALBEDO, maps.z.dtype)
    color, t, hit = render_terrain(maps, camera, sun, albedo=albedo, sky_irradiance=sky_irr, visible=visible,
                                   level=level, capacities=capacities, ripples=ripples, dune_shadows=dune_shadows,
                                   ripple_shadows=ripple_shadows, shadow_steps=steps, ray_steps=ray_steps)
    dirs = camera.primary_rays().astype(maps.z.dtype)
    sky = _sky_lookup(env, dirs)
    # aerial perspective: the far dunes fade toward the sky's colour near the horizon
    horizon = _sky_lookup(env, dirs.at[..., 2].set(0.0))
    fade = jnp.exp(-jnp.where(hit, t, 0.0) / haze)[..., None]
    image = jnp.where(hit[..., None], color * fade + horizon * (1 - fade), sky)
    if dust:
        in_shadow = heightfield_shadow(maps.z, particles.position, sun.direction.astype(maps.z.dtype),
                                       spacing=maps.spacing, n_steps=steps)
        image = composite_billboards(image, jnp.where(hit, t, jnp.inf), camera, particles, sun, sky_irr,
                                     sunlit=jnp.where(in_shadow, 0.0, 1.0))
    return image


def desert_frame(scene: DesertScene, camera: Camera, *, sun_elevation: float = 18.0, sun_azimuth: float = 165.0,
                 ripples: bool = True, lod: bool = True, culling: bool = True, dune_shadows: bool = True,
                 ripple_shadows: bool = True, dust: bool = True, dust_count: int = 1200, dust_steps: int = 20,
                 lod_bias: float = 0.0, haze: float = 600.0, ray_steps: int = 96, seed: int = 0,
                 timing: dict | None = None) -> Array:
    """Render one linear-RGB frame (H x W x 3). The per-level buffer capacities are taken from the
    plan of this camera (host side), so a repeated call with the same camera reuses the compiled
    frame. `timing`, if given, receives 'plan_s' and 'frame_s'."""
    t0 = time.perf_counter()
    visible, level = _plan(scene.maps, camera, lod=lod, culling=culling, lod_bias=lod_bias)
    caps = quad_capacities(visible, level, scene.maps.levels)
    sun, env, sky_irr = _sky(sun_elevation, sun_azimuth)
    steps = shadow_steps(scene.maps, sun_elevation)
    particles = _dust(scene, dust_count, dust_steps, seed) if dust else None
    t1 = time.perf_counter()
    image = _frame(scene.maps, camera, sun, env, sky_irr, visible, level, particles,
                   jnp.asarray(haze, scene.maps.z.dtype), capacities=caps, ripples=ripples,
                   dune_shadows=dune_shadows, ripple_shadows=ripple_shadows,
                   steps=steps, dust=dust, ray_steps=ray_steps)
    image.block_until_ready()
    if timing is not None:
        timing["plan_s"] = t1 - t0
        timing["frame_s"] = time.perf_counter() - t1
        timing["capacities"] = caps
    return image


@functools.lru_cache(maxsize=4)
def _cached_scene(dune_size: int, ripple_size: int, texels: int, seed: int, footprints: bool) -> DesertScene:
    return desert_scene(dune_size=dune_size, ripple_size=ripple_size, texels=texels, seed=seed, footprints=footprints)


_plan = jax.jit(plan_quads, static_argnames=("lod", "culling"))


@functools.lru_cache(maxsize=16)
def _sky(sun_elevation: float, sun_azimuth: float):
    return sky_for_sun(sun_elevation, sun_azimuth)


@functools.partial(jax.jit, static_argnames=("count", "steps", "tiling"))
def _dust_jit(key: Array, dune_height: Array, ripple_height: Array, *, count: int, steps: int,
              tiling: float) -> DustParticles:
    params = DustParams(drift=0.35, lift=0.05, jitter=(0.1, 0.1, 0.03), size_scale=0.5)
    positions, sizes = simulate_dust(key, dune_height, ripple_height, n_particles=count, steps=steps, params=params,
                                     ripple_tiling=tiling)
    n_rows, n_cols = dune_height.shape
    last = positions[-1]
    xy = jnp.stack([jnp.mod(last[:, 0], n_cols), jnp.mod(last[:, 1], n_rows)], axis=-1)  # the dunes are periodic
    radius = jnp.maximum(sizes[-1], 0.1 * params.size_scale)
    centre = jnp.concatenate([xy, (last[:, 2] + radius)[:, None]], axis=-1)  # the cloud sits on the surface
    return DustParticles(centre, radius, jnp.full(radius.shape, 0.1, radius.dtype))


def _dust(scene: DesertScene, count: int, steps: int, seed: int) -> DustParticles:
    """Eq. 7 particles from `sims.dust` (the last step of each track), as billboard clouds."""
    tiling = scene.maps.texels / scene.ripple_height.shape[0]
    return _dust_jit(jax.random.key(seed + 11), scene.dune_height, scene.ripple_height, count=count, steps=steps,
                     tiling=float(tiling))


def render_desert(*, width: int = 720, height: int = 480, ripples: bool = True, lod: bool = True,
                  culling: bool = True, dune_shadows: bool = True, ripple_shadows: bool = True, dust: bool = True,
                  sun_elevation: float = 18.0, sun_azimuth: float = 165.0, dune_size: int = 64,
                  ripple_size: int = 64, texels: int = 64, seed: int = 0, camera: Camera | None = None,
                  footprints: bool = False, timing: dict | None = None, **frame_kwargs) -> Array:
    """The showcase desert with the paper's switches (`footprints`: a trail of footprints, Fig. 18);
    returns linear RGB (H x W x 3)."""
    scene = _cached_scene(dune_size, ripple_size, texels, seed, footprints)
    camera = camera or default_camera(scene, width=width, height=height)
    return desert_frame(scene, camera, sun_elevation=sun_elevation, sun_azimuth=sun_azimuth, ripples=ripples, lod=lod,
                        culling=culling, dune_shadows=dune_shadows, ripple_shadows=ripple_shadows, dust=dust,
                        seed=seed, timing=timing, **frame_kwargs)


def to_display(image: Array) -> np.ndarray:
    """Tone-mapped sRGB values in [0, 1] (what the PNGs show)."""
    return np.asarray(tonemap(np.asarray(image), exposure=EXPOSURE))

"""Fast single scattering: equiangular quadrature seen from each light (the default shafts method).

Along a view ray E + t d, let L be the light, t_p the parameter of the ray's closest approach to L
and h that distance. Parametrize the ray by the angle phi it subtends at the light:
t = t_p + h tan(phi), so s = h / cos(phi), dt = h / cos^2(phi) dphi and

    dt / s^2 = dphi / h,    cos(alpha) = -sin(phi),    s + t = t_p + h (1 + sin(phi)) / cos(phi).

In phi the 1/s^2 peak of eq. 2 is gone: the unshadowed integrand rho F(alpha) exp(-rho kappa (s+t))
/ h is smooth and bounded (this is equiangular sampling, Kulla & Fajardo 2012, used here as a
deterministic midpoint rule). What remains is piecewise constant along *light* rays: the falloff,
the light map and the shadow-map visibility depend only on the direction w from the light (and
the depth s), and equal steps in phi are equal angular steps from the light, the way shadow-map
and light-map texels are laid out. So `samples` midpoints in phi between the ray's cone entry and
exit (cut at the visible surface and the light's reach, `cone_intervals`) cover the lit stretch of
every view ray with steps of equal angle as seen from the light, wherever the light is (near the
apex, where a ray march needs many uniform samples in t, phi steps are automatically short in t).

Per sample: the local light direction w = cos(phi) m + sin(phi) d (m the unit vector from L to the
closest point, both in the light's frame; cos/sin by a polynomial, no libm call), the falloff
(polynomial arctan), ONE nearest-texel fetch of the shadow-map depth and, for a textured light,
ONE nearest-texel fetch of the light map pre-filtered onto a grid `bake` times finer than the map
(bilinear at the finer texel centres: one bilinear evaluation per fine texel per frame, not four
fetches per sample). Cost per pixel and light: `samples` x (about 60 flops, one exp, one or two
gathers); only the rays that enter a light's cone are evaluated for it (`active_rays_map`).

Fog with a density grid (issue 24): each sample also needs d(P) (a trilinear lookup of the
grid), the optical depth toward the light (the light's `DepthVolume`, indexed by the same uv as
the shadow map and the sample's distance) and toward the eye: the eye's volume gives it at the
ends of the ray's interval and a trapezoid rule over the samples' own d fills in between,
anchored at both ends (so it costs no lookup per sample). The interval itself is cut to the
grid's box. Its weight rho d F I exp(-rho kappa (tau_l + tau_v)) dphi / h replaces the uniform
fog's; a grid of ones reproduces it to rounding. See docs/fog.md.

Surfaces: two-sided Lambert with extinction (`surface_term`), shadowed by the same shadow maps
(`shadow_map_visibility`, the plane method's slope-scaled lookup) or, on request, by exact shadow
rays. Gradients flow to rho, kappa, K, intensity, the light's pose (geometry, falloff,
interval ends) and the light-map values; not through the shadow map (no gradient by design) nor
through the light map's uv (nearest fetch of the baked map).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..fusion import materialize
from ..geometry import cast_rays, hit_point
from ..lights import SpotLight
from ..maths import atan_nonneg, outer
from ..textures import bilinear
from ._density import DepthVolume
from ._fog import FogVolumes, RayFog, fog_volumes
from ._model import FAR, cone_intervals, light_reach, surface_term
from ._raymarch import surface_visibility
from ._scene import ShaftsScene, shadow_maps

__all__ = ["render_equiangular", "equiangular_scattering", "equiangular_ladder", "bake_light_map", "active_rays_map"]


_H_MIN = 1e-6  # floor of the ray-to-light distance h (a ray through the light itself)
_BAKE = 8  # baked light-map texels per light-map texel along each axis
_BAKE_MAX = 1024  # cap on the baked map's side


def _cos_sin(x: Array) -> tuple[Array, Array]:
    """(cos x, sin x) for |x| <= pi/2 by Taylor polynomials (|error| < 1e-7): a few fused flops
    where XLA's CPU sin/cos are scalar libm calls (~20 ns each)."""
    z = x * x
    c = 1.0 + z * (-1 / 2 + z * (1 / 24 + z * (-1 / 720 + z * (1 / 40320 + z * (-1 / 3628800 + z / 479001600.0)))))
    s = 1.0 + z * (-1 / 6 + z * (1 / 120 + z * (-1 / 5040 + z * (1 / 362880 + z * (-1 / 39916800 + z / 6227020800.0)))))
    s = x * s
    return c, s


def _signed_atan(y: Array, h: Array) -> Array:
    """atan(y / h) for h > 0 (polynomial arctan with arctan's derivative)."""
    return jnp.sign(y) * atan_nonneg(jnp.abs(y) / h)


def bake_light_map(light: SpotLight, *, bake: int = _BAKE, max_size: int = _BAKE_MAX) -> Float[Array, "N N 3"] | None:
    """The light map sampled bilinearly (clamped) at the texel centres of a grid `bake` times
    finer (at most `max_size` texels a side); None for a uniform (1 x 1) map. A nearest fetch of it
    differs from the bilinear lookup by at most the map's slope over half a fine texel."""
    lmap = light.light_map
    if lmap.shape[0] * lmap.shape[1] == 1:
        return None
    n = int(min(bake * max(lmap.shape[0], lmap.shape[1]), max_size))
    c = (jnp.arange(n, dtype=lmap.dtype) + 0.5) / n
    v, u = jnp.meshgrid(c, c, indexing="ij")
    return bilinear(lmap, jnp.stack([u, v], axis=-1), wrap="clamp")


def _view_depth_along(view: DepthVolume, eye: Array, dirs: Array, t: Array) -> Array:
    return view.lookup_points(jnp.broadcast_to(eye, dirs.shape) + t[..., None] * dirs)


def _anchored_view_depth(dens: Array, left: Array, right: Array, t_s: Array, e0: Array, e1: Array, tau0: Array,
                         tau1: Array) -> Array:
    """Optical depth from the eye at the samples t_s (*B, S) of a view ray: each sample stands for
    the cell [left, right] of view ray between its neighbours' angle midpoints (the cells tile
    [e0, e1]); tau0 = tau(e0) plus d times the cells before it and the part of its own cell up to
    t_s, then corrected linearly in t so that it ends at tau1 = tau(e1) (tau0, tau1 from the
    eye's volume). For d = 1 this is t_s exactly (the cells telescope), so a grid of ones gives
    the uniform fog's exp(-rho kappa t) to rounding."""
    mass = dens * (right - left)  # 0 in unused slots (dens masked by the caller)
    n = dens.shape[-1]
    # prefix sums as a product with a triangular matrix: XLA's CPU cumsum over a short minor axis
    # costs ~25 ns per element, the matrix product ~1 ns
    before = mass @ jnp.triu(jnp.ones((n, n), dens.dtype), 1)
    total = jnp.sum(mass, axis=-1)
    span = e1 - e0
    ok = span > 0
    frac = (t_s - e0[..., None]) / jnp.where(ok, span, 1.0)[..., None]
    return tau0[..., None] + before + dens * (t_s - left) + frac * jnp.where(ok, tau1 - tau0 - total, 0.0)[..., None]


def equiangular_scattering(light: SpotLight, depth: Float[Array, "R R"], baked: Float[Array, "N N 3"] | None,
                           eye: Float[Array, "3"], dirs: Float[Array, "*B 3"], t0: Float[Array, "*B"],
                           t1: Float[Array, "*B"], rho, kappa, K, bias, *, samples: int,
                           fog: RayFog | None = None, count=None) -> Float[Array, "*B 3"]:
    """In-scattered radiance of one spot light along view rays eye + t dirs, t in [t0, t1]
    (eq. 2, `samples` midpoints equally spaced in the angle seen from the light; see the module
    docstring). `depth`: the light's shadow map (distances, nearest texel + `bias`); `baked`: the
    light map from `bake_light_map` (None: uniform); `fog`: the density grid's lookups (None:
    uniform fog). `count` (a traced integer <= samples): use only the first `count` of `samples`
    slots, spaced for `count` (one compiled function for many counts, as `choose_counts` needs)."""
    x_ax, y_ax, z_ax = light.frame()
    rel = eye - light.position
    le = jnp.stack([jnp.dot(rel, x_ax), jnp.dot(rel, y_ax), jnp.dot(rel, z_ax)])
    ld = [dirs[..., 0] * a[0] + dirs[..., 1] * a[1] + dirs[..., 2] * a[2] for a in (x_ax, y_ax, z_ax)]
    t_p = -(le[0] * ld[0] + le[1] * ld[1] + le[2] * ld[2])  # closest approach to the light
    m = [le[i] + t_p * ld[i] for i in range(3)]  # light -> closest point, light frame
    h2 = m[0] * m[0] + m[1] * m[1] + m[2] * m[2]
    big = h2 > _H_MIN * _H_MIN
    h = jnp.where(big, jnp.sqrt(jnp.where(big, h2, 1.0)), _H_MIN)
    m = [mi / h for mi in m]
    active = t1 > t0
    phi0 = _signed_atan(t0 - t_p, h)
    phi1 = _signed_atan(jnp.where(active, t1, t0) - t_p, h)
    step = (phi1 - phi0) / (samples if count is None else count)
    frac = (jnp.arange(samples, dtype=dirs.dtype) + 0.5).reshape((1,) * phi0.ndim + (samples,))
    active_s = active[..., None] if count is None else active[..., None] & (frac < count)  # slots in use
    phi = phi0[..., None] + step[..., None] * frac  # (*B, S)
    c, s = _cos_sin(phi)
    c = jnp.maximum(c, 1e-7)
    wx = c * m[0][..., None] + s * ld[0][..., None]
    wy = c * m[1][..., None] + s * ld[1][..., None]
    wz = c * m[2][..., None] + s * ld[2][..., None]
    # falloff: 1 inside the beam, linear in angle to 0 at the cutoff (as SpotLight.falloff)
    front = wz > 1e-6
    safe_z = jnp.where(front, wz, 1.0)
    rxy2 = wx * wx + wy * wy
    rxy_ok = rxy2 > 1e-30
    rxy = jnp.where(rxy_ok, jnp.sqrt(jnp.where(rxy_ok, rxy2, 1.0)), 0.0)
    theta = atan_nonneg(rxy / safe_z)
    cut = light.cutoff
    beam = jnp.minimum(light.beam_width, cut)
    ramp = cut - beam
    inv_ramp = jnp.where(ramp > 1e-9, 1.0 / jnp.where(ramp > 1e-9, ramp, 1.0), 0.0)
    fall = jnp.where(theta <= beam, 1.0, (cut - theta) * inv_ramp)
    # shadow-map and light-map coordinates: the same uv (design.md)
    inv = 0.5 / (safe_z * jnp.tan(cut))
    u_raw, v_raw = 0.5 + wx * inv, 0.5 + wy * inv
    u = jax.lax.stop_gradient(u_raw)
    v = jax.lax.stop_gradient(v_raw)
    res = depth.shape[0]
    col = jnp.clip(jnp.floor(u * res).astype(jnp.int32), 0, res - 1)
    row = jnp.clip(jnp.floor(v * res).astype(jnp.int32), 0, res - 1)
    occ = depth.reshape((-1,))[row * res + col]
    dist = h[..., None] / c
    lit = front & (theta < cut) & (jax.lax.stop_gradient(dist) <= occ + bias) & active_s
    # smooth part: rho F(alpha) exp(-sigma (s + t)) dphi / h, cos(alpha) = -sin(phi)
    c2 = 0.5 * (1.0 - s)
    c4 = c2 * c2
    c8 = c4 * c4
    phase = K * (1.0 + 9.0 * c8 * c8)
    if fog is None:
        path = t_p[..., None] + h[..., None] * (1.0 + s) / c  # s + t
        weight = jnp.where(lit, fall * phase * jnp.exp(-rho * kappa * path), 0.0)
    else:  # d(P) and the optical depths toward the light and the eye replace the lengths s and t
        t_s = t_p[..., None] + h[..., None] * s / c  # the samples' t (tan phi = s / c)
        # stored once: the density feeds both the view depth's matrix product and the weight, and
        # XLA's CPU fusion would otherwise redo its eight gathers in each
        dens = materialize(lambda g, ts: g.at_xyz(*(eye[i] + ts * dirs[..., i:i + 1] for i in range(3))), fog.grid, t_s)
        if count is not None:
            dens = jnp.where(active_s, dens, 0.0)
        tau_l = fog.light.lookup(2.0 * u_raw - 1.0, 2.0 * v_raw - 1.0, dist)
        # the sample's cell of view ray: t at its angle -+ step/2 (tan of a sum)
        ch, sh = _cos_sin(0.5 * step)
        ch, sh = ch[..., None], sh[..., None]
        hh, tp = h[..., None], t_p[..., None]
        left = tp + hh * (s * ch - c * sh) / jnp.maximum(c * ch + s * sh, 1e-7)
        right = tp + hh * (s * ch + c * sh) / jnp.maximum(c * ch - s * sh, 1e-7)
        c0, s0 = _cos_sin(phi0)
        c1, s1 = _cos_sin(phi1)
        e0 = t_p + h * s0 / jnp.maximum(c0, 1e-7)
        e1 = t_p + h * s1 / jnp.maximum(c1, 1e-7)
        ends = _view_depth_along(fog.view, eye, jnp.stack([dirs, dirs]), jnp.stack([e0, e1]))  # one lookup
        tau_v = _anchored_view_depth(dens, left, right, t_s, e0, e1, ends[0], ends[1])
        weight = jnp.where(lit, fall * phase * dens * jnp.exp(-rho * kappa * (tau_l + tau_v)), 0.0)
    scale = rho * step / h
    if baked is None:
        return outer(jnp.sum(weight, axis=-1) * scale, light.intensity)
    n = baked.shape[0]
    bcol = jnp.clip(jnp.floor(u * n).astype(jnp.int32), 0, n - 1)
    brow = jnp.clip(jnp.floor(v * n).astype(jnp.int32), 0, n - 1)
    texel = brow * n + bcol
    # one scalar gather per channel: gathering (S, 3) colours and summing over the middle S axis
    # cost XLA on CPU ~3x as much (a copy after the gather, a strided reduction)
    summed = jnp.stack([jnp.sum(baked[..., c].reshape((-1,))[texel] * weight, axis=-1) for c in range(3)], axis=-1)
    return summed * outer(scale, light.intensity)


def active_rays_map(scatter, dirs: Float[Array, "*B 3"], t0: Float[Array, "*B"], t1: Float[Array, "*B"], *,
                    chunk: int = 8192, block: int = 32, into: Float[Array, "*B 3"] | None = None
                    ) -> Float[Array, "*B 3"]:
    """scatter(dirs, t0, t1) (-> (*B, 3), zero where t1 <= t0) evaluated only where needed: the
    rays are cut into runs of `block` consecutive pixels, the runs holding a ray with t1 > t0 are
    compacted to the front (`jnp.nonzero` with a static size), evaluated `chunk` rays at a time
    under `lax.map` (a chunk past the active count is skipped by `lax.cond`) and scattered back.
    Same values as scatter on every ray, at the cost of the active runs only. Runs, not single rays:
    compacting and scattering back whole runs moves contiguous memory (around an empty kernel at
    720 x 480, CPU: per-ray compaction 13 ms per light, runs of 32 6 ms), and at most a run's worth of rays is
    evaluated in vain where a cone's edge crosses it. The earlier tiles of 24 x 40 pixels, each its
    own loop iteration of ~30 small kernels, cost 0.1 s per light of loop overhead on the five-spot
    stage; <= 43 chunks of 8192 rays at 720 x 480 make it vanish. Reverse mode recomputes each chunk
    instead of stacking its intermediates. `into`: add the result to this image instead of zeros
    (the frame accumulates its lights in one buffer)."""
    shape = t0.shape
    n = t0.size
    block = int(min(block, n))
    n_runs = -(-n // block)
    per_chunk = max(1, int(chunk) // block)
    n_chunks = -(-n_runs // per_chunk)
    pad = n_runs * block - n
    d = jnp.pad(dirs.reshape((-1, 3)), ((0, pad), (0, 0))).reshape((n_runs, block, 3))
    a = jnp.pad(t0.reshape((-1,)), (0, pad)).reshape((n_runs, block))
    b = jnp.pad(t1.reshape((-1,)), (0, pad)).reshape((n_runs, block))
    active = jnp.max(b - a, axis=1) > 0
    count = jnp.sum(active)
    runs = jnp.nonzero(active, size=n_chunks * per_chunk, fill_value=0)[0].reshape((n_chunks, per_chunk))
    first = jnp.arange(n_chunks) * per_chunk

    def one_chunk(args):
        start, ids = args
        valid = (start + jnp.arange(per_chunk) < count)[:, None]  # runs past the active count: empty
        zero = jnp.zeros((per_chunk, block), a.dtype)
        args = (d[ids].reshape((-1, 3)), jnp.where(valid, a[ids], zero).reshape((-1,)),
                jnp.where(valid, b[ids], zero).reshape((-1,)))
        empty = jnp.zeros((per_chunk * block, 3), a.dtype)
        out = jax.lax.cond(start < count, lambda x: scatter(*x), lambda x: empty, args)
        return out.reshape((per_chunk, block, 3))

    one_chunk = jax.checkpoint(one_chunk, policy=jax.checkpoint_policies.nothing_saveable)
    out = jax.lax.map(one_chunk, (first, runs))
    valid = (jnp.arange(n_chunks * per_chunk) < count).reshape((n_chunks, per_chunk))
    target = jnp.where(valid, runs, n_runs).reshape((-1,))  # index n_runs: dropped
    base = (jnp.zeros((n_runs, block, 3), out.dtype) if into is None
            else jnp.pad(into.reshape((-1, 3)), ((0, pad), (0, 0))).reshape((n_runs, block, 3)))
    image = base.at[target].add(out.reshape((-1, block, 3)), mode="drop")
    return image.reshape((-1, 3))[:n].reshape(shape + (3,))


def primary_hits(scene: ShaftsScene):
    """(dirs, t, normals, albedo, points) of the camera's primary rays (t = inf on a miss)."""
    eye = scene.camera.eye
    dirs = scene.camera.primary_rays()
    t_hit, normals, albedo = cast_rays(eye, dirs, scene.prims)
    return dirs, t_hit, normals, albedo, hit_point(eye, dirs, t_hit, far=FAR)


class _Frame(eqx.Module):
    """What every light's in-scattering shares: primary rays and hits, shadow maps, a density
    grid's volumes, the surfaces' shading."""

    dirs: Array
    surface_t: Array
    maps: tuple
    fog: FogVolumes | None
    surface: Array


def _frame(scene: ShaftsScene, *, shadow_map: int | None, surface_shadows: str, fog_nodes) -> _Frame:
    # stored once: XLA on CPU otherwise recasts the primary rays inside each of their consumers
    dirs, t_hit, normals, albedo, points = materialize(primary_hits, scene)
    res = scene.render.shadow_map if shadow_map is None else int(shadow_map)
    # stored too: else each surface lookup recasts its texel's ray (XLA fuses the map into the gather)
    maps = materialize(functools.partial(shadow_maps, resolution=res), scene)
    visibility = surface_visibility(scene, maps, surface_shadows)
    # the density grid's optical-depth volumes (stored once, like the maps)
    fog = None if scene.medium.density is None else materialize(
        functools.partial(fog_volumes, nodes=fog_nodes), scene)
    if fog is None:
        surface = surface_term(scene, points, normals, albedo, t_hit, visibility)
    else:
        surface = surface_term(scene, points, normals, albedo, t_hit, visibility, light_depth=fog.light_depth,
                               view_depth=fog.view_depth(scene, dirs, jnp.where(jnp.isfinite(t_hit), t_hit, 0.0)))
    surface_t = jnp.where(jnp.isfinite(t_hit), t_hit, FAR)
    return _Frame(dirs, surface_t, maps, fog, surface)


def _light_scatters(scene: ShaftsScene, frame: _Frame, *, samples: int, bake: int):
    """(scatter(dirs, t0, t1), t0, t1) of every light: its `equiangular_scattering` and cone intervals."""
    rho, kappa, K = scene.medium.rho, scene.medium.kappa, scene.medium.K
    for index, (light, sm) in enumerate(zip(scene.lights, frame.maps)):
        depth = jax.lax.stop_gradient(sm.depth)
        baked = bake_light_map(light, bake=bake)
        reach = light_reach(scene, light)
        t0, t1 = materialize(functools.partial(cone_intervals, scene, light), frame.dirs, frame.surface_t, reach)
        ray_fog = None if frame.fog is None else frame.fog.for_light(index)
        yield (functools.partial(equiangular_scattering, light, depth, baked, scene.camera.eye, rho=rho, kappa=kappa,
                                 K=K, bias=scene.render.shadow_bias, samples=samples, fog=ray_fog), t0, t1)


def equiangular_ladder(scene: ShaftsScene, groups: tuple[tuple[int, ...], ...], reference: int, *,
                       shadow_map: int | None = 512, bake: int = _BAKE,
                       fog_nodes: int | tuple[int, int] | None = None, **_unused
                       ) -> tuple[list[Float[Array, "H W 3"]], Float[Array, "H W 3"]]:
    """The in-scattered light of `scene` at each sample count of `groups` and at `reference`
    samples, as `render_equiangular` renders it, sharing the rays, maps and volumes: what
    `choose_counts` measures on its proxy. The counts of a group share one compiled kernel of
    `max(group)` slots (the first n used, under `lax.map`); every ray is evaluated (no pruning:
    proxies are small). Returns (images in the order of the groups' counts, the reference)."""
    frame = _frame(scene, shadow_map=shadow_map, surface_shadows="map", fog_nodes=fog_nodes)
    images = []
    for group in groups:
        capacity = max(group)

        def at_count(n, capacity=capacity):
            return sum(scatter(frame.dirs, t0, t1, count=n)
                       for scatter, t0, t1 in _light_scatters(scene, frame, samples=capacity, bake=bake))

        images += list(jax.lax.map(at_count, jnp.asarray(group, dtype=frame.dirs.dtype)))
    ref = sum(scatter(frame.dirs, t0, t1) for scatter, t0, t1 in _light_scatters(scene, frame, samples=reference,
                                                                                bake=bake))
    return images, ref


def render_equiangular(scene: ShaftsScene, *, samples: int = 24, shadow_map: int | None = 512,
                       surface_shadows: str = "map", chunk: int = 8192, prune: bool = True,
                       bake: int = _BAKE, fog_nodes: int | tuple[int, int] | None = None,
                       return_parts: bool = False
                       ) -> Float[Array, "H W 3"]:
    """Render `scene` (H, W, 3 linear RGB): surfaces (shadow rays, two-sided Lambert, extinction)
    plus every light's in-scattering by `equiangular_scattering` with `samples` per pixel and light
    (24: about 1 % relative RMS on the five-spot stage; 16: about 2.4 %).

    shadow_map: shadow-map resolution, default 512 (None: the scene's `render.shadow_map`, the
    plane method's setting, 1024 by default). On the five-spot stage the in-scattering error is the
    same at 512 and 1024 (1.17 %: the 24 steps along each ray, not the texels, set it) while the
    maps cost a quarter, and at 720 x 480 a 512 map still has about two texels per pixel across a
    spot's footprint. surface_shadows:
    "map" (shadow-map lookups with a slope-scaled bias, `shadow_map_visibility`) or "rays" (exact
    shadow rays, as the ray march; ~5x the cost of the surface pass).
    prune: evaluate each light only on the rays that pass through its cone in front of the visible
    surface (`active_rays_map`, in chunks of `chunk` rays); prune=False evaluates every pixel in one
    vectorized pass (same image; a smaller graph for tiny images and tests). bake:
    light-map refinement factor (`bake_light_map`). fog_nodes: (directions across, distances) of
    a density grid's optical-depth volumes, or one number for both (default `volume_nodes`). return_parts: also return
    (surface, per-light in-scattering list). Jittable, differentiable; no retrace when light or medium values change.
    """
    frame = _frame(scene, shadow_map=shadow_map, surface_shadows=surface_shadows, fog_nodes=fog_nodes)
    per_light, image = [], frame.surface
    for scatter, t0, t1 in _light_scatters(scene, frame, samples=samples, bake=bake):
        if not prune:
            per_light.append(scatter(frame.dirs, t0, t1))
        elif return_parts:
            per_light.append(active_rays_map(scatter, frame.dirs, t0, t1, chunk=chunk))
        else:  # one buffer for all lights (no per-light image to add up)
            image = active_rays_map(scatter, frame.dirs, t0, t1, chunk=chunk, into=image)
    surface = frame.surface

    if per_light:
        image = surface + sum(per_light)
    if return_parts:
        return image, (surface, per_light)
    return image

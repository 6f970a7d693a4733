"""Fast single scattering: equiangular quadrature seen from each light (the default method,
`render_adaptive`, evaluates it where the image needs it; `render_equiangular` at every pixel).

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
`map_taps` nearest-texel fetches of the light map's mip pyramid (`light.mips`, built once when the
light is made) at the level of the pixel's footprint seen from the light (so a 1024^2 map costs a
frame what a 64^2 one does: the gathers, not the map, cost). Cost per pixel and light: `samples` x
(about 60 flops, one exp, 1 + map_taps gathers); only the rays that enter a light's cone are
evaluated for it (`active_rays_map`).

Fog with a density grid: each sample also needs d(P) (a trilinear lookup of the
grid), the optical depth toward the light (the light's `DepthVolume`, indexed by the same uv as
the shadow map and the sample's distance) and toward the eye: the eye's volume gives it at the
ends of the ray's interval and a trapezoid rule over the samples' own d fills in between,
anchored at both ends (so it costs no lookup per sample). The interval itself is cut to the
grid's box. Its weight rho d F I exp(-rho kappa (tau_l + tau_v)) dphi / h replaces the uniform
fog's; a grid of ones reproduces it to rounding. See docs/fog.md.

Surfaces: two-sided Lambert with extinction (`surface_term`), shadowed by the same shadow maps
(`shadow_map_visibility`, the plane method's slope-scaled lookup) or, on request, by exact shadow
rays. Gradients flow to rho, kappa, K, intensity and the light's pose (geometry, falloff,
interval ends); not through the shadow map (no gradient by design), the light map's uv (nearest
fetches); to the light map's texels only through a light made inside the differentiated function
(its pyramid is built when the light is made: `SpotLight.with_light_map`).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero
from jaxtyping import Array, Bool, Float

from ..fusion import materialize
from ..geometry import cast_rays, hit_point
from ..lights import SpotLight
from ..maths import atan_nonneg, outer, sum_last
from ._density import DepthVolume
from ._fog import FogVolumes, RayFog, fog_volumes
from ._model import FAR, cone_intervals, light_reach, surface_light, surface_radiance
from ._raymarch import surface_visibility
from ._scene import ShaftsScene, shadow_maps

__all__ = ["render_equiangular", "equiangular_scattering", "equiangular_ladder", "active_rays_map",
           "map_active_runs"]


_H_MIN = 1e-6  # floor of the ray-to-light distance h (a ray through the light itself)
# light-map texels per pixel footprint (seen from the light) that the nearest fetch keeps: its
# half-texel displacement then stays within 1/16 of a pixel. Each level coarser doubles the light
# map's part of the error against point-sampled rays (textured spot, 360 x 240, 128 samples x 4
# taps: 1.7 % at one texel per footprint, 0.9 % at 2, 0.6 % at 4, 0.3 % at 8)
MAP_DETAIL = 8.0


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


def equiangular_scattering(light: SpotLight, depth: Float[Array, "R R"], eye: Float[Array, "3"],
                           dirs: Float[Array, "*B 3"], t0: Float[Array, "*B"], t1: Float[Array, "*B"], rho, kappa, K,
                           bias, *, samples: int, pixel_angle, map_taps: int = 1, fog: RayFog | None = None,
                           count=None) -> Float[Array, "*B 3"]:
    """In-scattered radiance of one spot light along view rays eye + t dirs, t in [t0, t1]
    (eq. 2, `samples` midpoints equally spaced in the angle seen from the light; see the module
    docstring). `depth`: the light's shadow map (distances, nearest texel + `bias`); the light
    map is read from its pyramid (`light.mips`) at the level of the pixel's footprint seen from
    the light (`pixel_angle`: the angle between neighbouring pixels' rays, radians), averaged over
    `map_taps` points spread evenly over the sample's cell of angle (the light map's sharp edges
    set the error of a point-sampled midpoint rule; see the module docstring); `fog`: the
    density grid's lookups (None: uniform fog). `count` (a traced integer <= samples): use only
    the first `count` of `samples` slots, spaced for `count` (one compiled function for many
    counts, as `choose_counts` needs)."""
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
    # rho multiplies in here, not after the sum over the samples: with a K near float32's limit and
    # a rho that rounds to 0 the sum overflows and inf x 0 is NaN; rho K is a float32 number (checked
    # where a scene file is read)
    phase = (rho * K) * (1.0 + 9.0 * c8 * c8)
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
    scale = step / h
    mips = light.mips
    if mips is None:
        return outer(sum_last(weight) * scale, light.intensity)
    # one level per ray: the pixel's footprint seen from the light at the middle of the interval
    # (the angle pixel_angle at distance t from the eye spans pixel_angle t / s from the light), in
    # level-0 texels, over MAP_DETAIL; a large map is read at the level the pixel needs, so its
    # size does not matter beyond that
    t_mid = 0.5 * (t0 + t1)
    s_mid = jnp.sqrt(h * h + (t_mid - t_p) ** 2)
    footprint = pixel_angle * t_mid / jnp.maximum(s_mid, _H_MIN) * (mips.side / (2.0 * jnp.tan(cut)))
    level = jax.lax.stop_gradient(mips.level_for(footprint / MAP_DETAIL))
    base = mips.offset(level)[..., None]
    level = level[..., None]
    if map_taps == 1:
        mapv = mips.fetch(mips.index(u, v, level, base))
    else:  # the map averaged over the sample's cell of angle: taps at phi + step ((j + 1/2) / taps - 1/2)
        mapv = 0.0
        tan_c = jnp.tan(cut)
        for j in range(map_taps):
            cd, sd = _cos_sin(step * ((j + 0.5) / map_taps - 0.5))
            cd, sd = cd[..., None], sd[..., None]
            cj, sj = c * cd - s * sd, s * cd + c * sd  # cos, sin of phi + delta
            wxj, wyj, wzj = (cj * m[i][..., None] + sj * ld[i][..., None] for i in range(3))
            invj = jax.lax.stop_gradient(0.5 / (jnp.where(wzj > 1e-6, wzj, 1.0) * tan_c))
            uj, vj = jax.lax.stop_gradient(0.5 + wxj * invj), jax.lax.stop_gradient(0.5 + wyj * invj)
            mapv = mapv + mips.fetch(mips.index(uj, vj, level, base))
        mapv = mapv * (1.0 / map_taps)
    if mips.channels == 1:  # a gray map: one scalar gather per tap
        return outer(sum_last(mapv[..., 0] * weight) * scale, light.intensity)
    summed = jnp.stack([sum_last(mapv[..., k] * weight) for k in range(mapv.shape[-1])], axis=-1)
    return summed * outer(scale, light.intensity)


def map_active_runs(fn, active: Bool[Array, " R"], args, *, chunk_runs: int, into: Array) -> Array:
    """`into` plus fn(...) on the active runs: every leaf of `args` and `into` has a leading axis
    of R runs; the active runs are compacted to the front (`jnp.nonzero` with a static size) and
    handed to `fn` `chunk_runs` at a time by a `lax.scan` that adds each chunk's result into
    `into` at the chunk's runs; a chunk past the active count is skipped (`lax.cond`), so the cost
    follows the active runs. fn(valid (chunk,), *leaves (chunk, ...)) -> (chunk, ...) like `into`'s
    rows; runs with `valid` False (past the count, inside the last chunk) must give zeros.

    Reverse mode is written out (`_chunks`): a second scan over the same chunks recomputes each one
    and pulls its cotangent back (`jax.vjp`), adding into the cotangents of `args` and of the
    values `fn` closes over, of those being differentiated only (symbolic zeros tell which).
    Differentiating the scan itself would store, per chunk, a copy of everything `fn` reads (JAX
    forwards the inputs of a skippable chunk through the `cond` as per-iteration residuals): 43
    copies of the frame's rays and maps per light at 720 x 480."""
    n_runs = active.shape[0]
    per_chunk = int(max(1, min(chunk_runs, n_runs)))
    n_chunks = -(-n_runs // per_chunk)
    active = jax.lax.stop_gradient(active)
    count = jnp.sum(active)
    runs = jnp.nonzero(active, size=n_chunks * per_chunk, fill_value=0)[0].reshape((n_chunks, per_chunk))
    first = jnp.arange(n_chunks) * per_chunk
    example = jax.tree_util.tree_map(lambda a: a[:per_chunk], args)
    converted, consts = jax.closure_convert(fn, jnp.ones((per_chunk,), bool), *example)
    return _chunks(converted, n_runs, (count, runs, first), args, tuple(consts), into)


def _chunk_valid(start, count, per_chunk):
    return start + jnp.arange(per_chunk) < count  # runs past the active count: empty


@functools.partial(jax.custom_vjp, nondiff_argnums=(0, 1))
def _chunks(fn, n_runs, plan, args, consts, into):
    count, runs, first = plan
    per_chunk = runs.shape[1]

    def step(acc, xs):
        start, ids = xs

        def add(acc):
            valid = _chunk_valid(start, count, per_chunk)
            out = fn(valid, *jax.tree_util.tree_map(lambda a: a[ids], args), *consts)
            return acc.at[jnp.where(valid, ids, n_runs)].add(out, mode="drop")  # index n_runs: dropped

        return jax.lax.cond(start < count, add, lambda acc: acc, acc), None

    return jax.lax.scan(step, into, (first, runs))[0]


class _Perturbed(eqx.Module):
    """Which leaves of (args, consts) are differentiated (static: carried through the residuals)."""

    mask: tuple[bool, ...] = eqx.field(static=True)


def _chunks_fwd(fn, n_runs, plan, args, consts, into):
    def value(tree):
        return jax.tree_util.tree_map(lambda p: p.value, tree)

    perturbed = _Perturbed(tuple(p.perturbed for p in jax.tree_util.tree_leaves((args, consts))))
    plan, args, consts = value(plan), value(args), value(consts)
    return _chunks(fn, n_runs, plan, args, consts, value(into)), (plan, args, consts, perturbed)


def _chunks_bwd(fn, n_runs, res, g):
    """Pulls back only the differentiated leaves of (args, consts): a constant's cotangent (a light
    map's texels, the rays' directions) would cost a scatter per chunk, for nothing."""
    plan, args, consts, perturbed = res
    count, runs, first = plan
    per_chunk = runs.shape[1]
    leaves, tree = jax.tree_util.tree_flatten((args, consts))
    n_args = len(jax.tree_util.tree_leaves(args))
    wrt = [i for i, p in enumerate(perturbed.mask) if p]
    if isinstance(g, SymbolicZero):
        g = None
    if g is None or not wrt:  # nothing to pull back through the chunks (`into`'s cotangent is g)
        return None, jax.tree_util.tree_map(lambda _: None, args), jax.tree_util.tree_map(lambda _: None, consts), g

    def step(carry, xs):
        start, ids = xs

        def pull(carry):
            valid = _chunk_valid(start, count, per_chunk)
            target = jnp.where(valid, ids, n_runs)
            sub = [x[ids] if i < n_args else x for i, x in enumerate(leaves)]

            def chunk_fn(*diff):
                both = list(sub)
                for i, x in zip(wrt, diff):
                    both[i] = x
                chunk_args, chunk_consts = jax.tree_util.tree_unflatten(tree, both)
                return fn(valid, *chunk_args, *chunk_consts)

            _, vjp = jax.vjp(chunk_fn, *(sub[i] for i in wrt))
            pulled = vjp(g.at[target].get(mode="fill", fill_value=0))
            return tuple(c.at[target].add(d, mode="drop") if i < n_args else c + d
                         for i, c, d in zip(wrt, carry, pulled))

        return jax.lax.cond(start < count, pull, lambda carry: carry, carry), None

    zeros = tuple(jnp.zeros_like(leaves[i]) for i in wrt)
    pulled, _ = jax.lax.scan(step, zeros, (first, runs))
    out = [None] * len(leaves)
    for i, d in zip(wrt, pulled):
        out[i] = d
    d_args, d_consts = jax.tree_util.tree_unflatten(tree, out)
    return None, d_args, d_consts, g


_chunks.defvjp(_chunks_fwd, _chunks_bwd, symbolic_zeros=True)


def _as_runs(x: Array, size: int, block: int, trailing: tuple[int, ...] = ()) -> Array:
    """The first `size` entries of x (any batch shape, then `trailing`), flat, zero-padded to whole
    runs of `block`: (runs, block, *trailing)."""
    n_runs = -(-size // block)
    pad = n_runs * block - size
    flat = x.reshape((-1,) + trailing)
    return jnp.pad(flat, ((0, pad),) + ((0, 0),) * len(trailing)).reshape((n_runs, block) + trailing)


def active_rays_map(scatter, dirs: Float[Array, "*B 3"], t0: Float[Array, "*B"], t1: Float[Array, "*B"], *,
                    chunk: int = 8192, block: int = 32, into: Float[Array, "*B 3"] | None = None
                    ) -> Float[Array, "*B 3"]:
    """scatter(dirs, t0, t1) (-> (*B, 3), zero where t1 <= t0) evaluated only where needed: the
    rays are cut into runs of `block` consecutive pixels and the runs holding a ray with t1 > t0
    are evaluated, `chunk` rays at a time (`map_active_runs`). Same values as scatter on every ray,
    at the cost of the active runs only. Runs, not single rays: compacting and scattering back
    whole runs moves contiguous memory (around an empty kernel at 720 x 480, CPU: per-ray
    compaction 13 ms per light, runs of 32 6 ms), and at most a run's worth of rays is evaluated
    in vain where a cone's edge crosses it. `into`: add the result to this image instead of zeros
    (the frame accumulates its lights in one buffer)."""
    shape = t0.shape
    n = t0.size
    block = int(min(block, n))
    d, a, b = _as_runs(dirs, n, block, (3,)), _as_runs(t0, n, block), _as_runs(t1, n, block)
    base = jnp.zeros_like(d) if into is None else _as_runs(into, n, block, (3,))

    def evaluate(valid, d, a, b):
        a = jnp.where(valid[:, None], a, 0.0)
        b = jnp.where(valid[:, None], b, 0.0)
        return scatter(d.reshape((-1, 3)), a.reshape((-1,)), b.reshape((-1,))).reshape(d.shape)

    image = map_active_runs(evaluate, jnp.max(b - a, axis=1) > 0, (d, a, b), chunk_runs=max(1, int(chunk) // block),
                            into=base)
    return image.reshape((-1, 3))[:n].reshape(shape + (3,))


def primary_hits(scene: ShaftsScene, dirs: Float[Array, "*B 3"] | None = None):
    """(dirs, t, normals, albedo, points) of the camera's primary rays, or of the rays from the eye
    along `dirs` (t = inf on a miss)."""
    eye = scene.camera.eye
    dirs = scene.camera.primary_rays() if dirs is None else dirs
    t_hit, normals, albedo = cast_rays(eye, dirs, scene.prims)
    return dirs, t_hit, normals, albedo, hit_point(eye, dirs, t_hit, far=FAR)


class Frame(eqx.Module):
    """What every light's in-scattering shares: primary rays and hits, shadow maps, a density
    grid's volumes, the surfaces' shading."""

    dirs: Array
    surface_t: Array
    maps: tuple
    fog: FogVolumes | None
    surface: Array


def shade_frame(scene: ShaftsScene, *, shadow_map: int | None, surface_shadows: str, fog_nodes,
                dirs: Float[Array, "*B 3"] | None = None) -> Frame:
    """The shared part of a frame (`Frame`) for the camera's primary rays (H, W), or for the rays
    along `dirs` (any layout: the adaptive method orders its pixels cell by cell)."""
    # stored once: XLA on CPU otherwise recasts the primary rays inside each of their consumers
    dirs, t_hit, normals, albedo, points = materialize(primary_hits, scene, dirs)
    res = scene.render.shadow_map if shadow_map is None else int(shadow_map)
    # stored too: else each surface lookup recasts its texel's ray (XLA fuses the map into the gather)
    maps = materialize(functools.partial(shadow_maps, resolution=res), scene)
    visibility = surface_visibility(scene, maps, surface_shadows)
    # the density grid's optical-depth volumes (stored once, like the maps)
    fog = None if scene.medium.density is None else materialize(
        functools.partial(fog_volumes, nodes=fog_nodes), scene)
    surface_t = jnp.where(jnp.isfinite(t_hit), t_hit, FAR)
    footprint = pixel_angle(scene) * surface_t / MAP_DETAIL  # light maps at the level the pixel needs
    light_depth = None if fog is None else fog.light_depth
    lit = lit_surfaces(scene, points, normals, jnp.isfinite(t_hit), footprint,
                       functools.partial(surface_light, scene, visibility=visibility, light_depth=light_depth))
    view_depth = None if fog is None else fog.view_depth(scene, dirs, jnp.where(jnp.isfinite(t_hit), t_hit, 0.0))
    surface = surface_radiance(scene, albedo, t_hit, lit, view_depth=view_depth)
    return Frame(dirs, surface_t, maps, fog, surface)


def lit_surfaces(scene: ShaftsScene, points: Float[Array, "*B 3"], normals: Float[Array, "*B 3"],
                 hit: Bool[Array, "*B"], footprint: Float[Array, "*B"], light_term, *, chunk: int = 8192,
                 block: int = 32) -> Float[Array, "*B 3"]:
    """The lights' sum of light_term(index, points, normals, footprint=...) (`surface_light`, zero
    outside each light's cone), each light evaluated only on the runs of `block` consecutive
    points holding a hit inside its cone widened by 1 mrad (`map_active_runs`, `chunk` points at a
    time): a spot lights a tenth of the benchmark frames' pixels, and its light-map fetch and
    shadow-map test are most of a pixel's surface cost. Same values as evaluating every point."""
    shape = hit.shape
    n = hit.size
    block = int(min(block, n))
    p, nrm = _as_runs(points, n, block, (3,)), _as_runs(normals, n, block, (3,))
    fp, h = _as_runs(footprint, n, block), _as_runs(hit, n, block)
    total = jnp.zeros_like(p)
    for index, light in enumerate(scene.lights):
        local = jax.lax.stop_gradient(light.to_local(p))
        tan_c = jnp.tan(jnp.minimum(light.cutoff + 1e-3, 0.5 * jnp.pi - 1e-3))
        lateral = jnp.sqrt(local[..., 0] * local[..., 0] + local[..., 1] * local[..., 1])
        inside = h & (local[..., 2] > 0) & (lateral <= local[..., 2] * tan_c)

        def term(valid, p, nrm, fp, index=index):
            out = light_term(index, p.reshape((-1, 3)), nrm.reshape((-1, 3)), footprint=fp.reshape((-1,)))
            return jnp.where(valid[:, None, None], out.reshape(p.shape), 0.0)

        total = map_active_runs(term, jnp.any(inside, axis=1), (p, nrm, fp), chunk_runs=max(1, int(chunk) // block),
                                into=total)
    return total.reshape((-1, 3))[:n].reshape(shape + (3,))


def pixel_angle(scene: ShaftsScene) -> Float[Array, ""]:
    """The angle between neighbouring pixels' rays at the image's centre (radians)."""
    return 2.0 * scene.camera.tan_half_fov / scene.camera.height


def light_scatter_fns(scene: ShaftsScene, frame: Frame, *, samples: int, map_taps: int = 1):
    """(scatter(dirs, t0, t1), reach) of every light: its `equiangular_scattering` with the frame's
    shadow map and fog lookups bound, and the reach of its cone (`cone_intervals`)."""
    rho, kappa, K = scene.medium.rho, scene.medium.kappa, scene.medium.K
    for index, (light, sm) in enumerate(zip(scene.lights, frame.maps)):
        depth = jax.lax.stop_gradient(sm.depth)
        ray_fog = None if frame.fog is None else frame.fog.for_light(index)
        yield (functools.partial(equiangular_scattering, light, depth, scene.camera.eye, rho=rho, kappa=kappa, K=K,
                                 bias=scene.render.shadow_bias, samples=samples, pixel_angle=pixel_angle(scene),
                                 map_taps=map_taps, fog=ray_fog), light_reach(scene, light))


def _light_scatters(scene: ShaftsScene, frame: Frame, *, samples: int, map_taps: int = 1):
    """(scatter(dirs, t0, t1), t0, t1) of every light: its `equiangular_scattering` and cone intervals."""
    for light, (scatter, reach) in zip(scene.lights, light_scatter_fns(scene, frame, samples=samples,
                                                                      map_taps=map_taps)):
        t0, t1 = materialize(functools.partial(cone_intervals, scene, light), frame.dirs, frame.surface_t, reach)
        yield scatter, t0, t1


def equiangular_ladder(scene: ShaftsScene, groups: tuple[tuple[int, ...], ...], reference: int, *,
                       shadow_map: int | None = 512, map_taps: int = 1,
                       fog_nodes: int | tuple[int, int] | None = None, **_unused
                       ) -> tuple[list[Float[Array, "H W 3"]], Float[Array, "H W 3"]]:
    """The in-scattered light of `scene` at each sample count of `groups` and at `reference`
    samples, as `render_equiangular` renders it (`map_taps` light-map taps a sample), sharing the
    rays, maps and volumes: what `choose_counts` measures on its proxy. The counts of a group share
    one compiled kernel of `max(group)` slots (the first n used, under `lax.map`); every ray is
    evaluated (no pruning: proxies are small). Returns (images in the order of the groups' counts,
    the reference)."""
    frame = shade_frame(scene, shadow_map=shadow_map, surface_shadows="map", fog_nodes=fog_nodes)
    images = []
    for group in groups:
        capacity = max(group)

        def at_count(n, capacity=capacity):
            return sum(scatter(frame.dirs, t0, t1, count=n)
                       for scatter, t0, t1 in _light_scatters(scene, frame, samples=capacity, map_taps=map_taps))

        images += list(jax.lax.map(at_count, jnp.asarray(group, dtype=frame.dirs.dtype)))
    ref = sum(scatter(frame.dirs, t0, t1) for scatter, t0, t1 in _light_scatters(scene, frame, samples=reference,
                                                                                map_taps=map_taps))
    return images, ref


def render_equiangular(scene: ShaftsScene, *, samples: int = 24, map_taps: int = 1, shadow_map: int | None = 512,
                       surface_shadows: str = "map", chunk: int = 8192, prune: bool = True,
                       fog_nodes: int | tuple[int, int] | None = None,
                       return_parts: bool = False
                       ) -> Float[Array, "H W 3"]:
    """Render `scene` (H, W, 3 linear RGB): surfaces (shadow rays, two-sided Lambert, extinction)
    plus every light's in-scattering by `equiangular_scattering` with `samples` per pixel and light
    and `map_taps` light-map taps a sample, at every pixel (`render_adaptive`, the default method,
    evaluates it at the pixels that need it).

    shadow_map: shadow-map resolution, default 512 (None: the scene's `render.shadow_map`, the
    plane method's setting, 1024 by default). On the five-spot stage the in-scattering error is the
    same at 512 and 1024 (1.17 %: the 24 steps along each ray, not the texels, set it) while the
    maps cost a quarter, and at 720 x 480 a 512 map still has about two texels per pixel across a
    spot's footprint. surface_shadows:
    "map" (shadow-map lookups with a slope-scaled bias, `shadow_map_visibility`) or "rays" (exact
    shadow rays, as the ray march; ~5x the cost of the surface pass).
    prune: evaluate each light only on the rays that pass through its cone in front of the visible
    surface (`active_rays_map`, in chunks of `chunk` rays); prune=False evaluates every pixel in one
    vectorized pass (same image; a smaller graph for tiny images and tests). fog_nodes: (directions
    across, distances) of a density grid's optical-depth volumes, or one number for both (default
    `volume_nodes`). return_parts: also return (surface, per-light in-scattering list). Jittable,
    differentiable; no retrace when light or medium values change.
    """
    frame = shade_frame(scene, shadow_map=shadow_map, surface_shadows=surface_shadows, fog_nodes=fog_nodes)
    per_light, image = [], frame.surface
    for scatter, t0, t1 in _light_scatters(scene, frame, samples=samples, map_taps=map_taps):
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

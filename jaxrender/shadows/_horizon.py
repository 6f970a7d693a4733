"""Horizon maps (Max 1988; paper 001 section 3.5): per texel of a periodic heightfield, the largest
slope along each of D directions (an exact search, or the sweep of `_horizon_sweep.py` for large
lattice maps), and the shadow test between the two nearest directions. Paths, sampling and which
method runs when: docs/desert.md.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float

from ._horizon_sweep import lattice_sweep

__all__ = ["horizon_band", "horizon_directions", "horizon_light", "horizon_map", "horizon_shadow"]

# From this side on, the sweep is faster than the dense search on the project's 2-core CPU (CPU
# seconds on one core: 256^2 search 0.010-0.011, sweep 0.009 (crests) to 0.012 (white noise);
# 1024^2 search 0.83, sweep 0.31; the search also uses the second core, the sweep barely).
SWEEP_MIN_SIZE = 512


def horizon_directions(directions: int = 8) -> list[tuple[float, float]]:
    """Step vectors e_d (x, y) of the D search directions (static Python floats)."""
    steps = []
    for d in range(directions):
        phi = 2.0 * math.pi * d / directions
        c, s = math.cos(phi), math.sin(phi)
        m = max(abs(c), abs(s))
        ex, ey = c / m, s / m
        ex = float(round(ex)) if abs(ex - round(ex)) < 1e-9 else ex
        ey = float(round(ey)) if abs(ey - round(ey)) < 1e-9 else ey
        steps.append((ex, ey))
    return steps


def _shifted(tiled: Array, oy: Array, ox: Array, rows: int, cols: int) -> Array:
    """h(y + oy, x + ox) for every texel (integer offsets, periodic) from the 2x2-tiled field."""
    return jax.lax.dynamic_slice(tiled, (jnp.mod(oy, rows), jnp.mod(ox, cols)), (rows, cols))


def _lattice_horizons(tiled: Array, height: Array, steps: list[tuple[int, int]], lengths: list[float],
                      n_path: int) -> Array:
    """Full search of lattice directions: per direction, max over k = 1 .. n_path of
    (h(P + k e) - h(P)) / (k |e|), clamped at 0. Every step is one periodic whole-field shift (a
    slice of the 2x2-tiled field): a dense, gather-free pass. One loop over k updates every
    direction (independent fused passes XLA can overlap), unrolled by 16: ~20 % faster than one
    loop per direction."""
    rows, cols = height.shape

    def body(k, best):
        inv_k = 1.0 / k.astype(height.dtype)
        return tuple(jnp.maximum(b, (_shifted(tiled, k * iy, k * ix, rows, cols) - height) * (inv_k / length))
                     for b, (ix, iy), length in zip(best, steps, lengths))

    zeros = tuple(jnp.zeros_like(height) for _ in steps)
    return jnp.stack(jax.lax.fori_loop(1, n_path + 1, body, zeros, unroll=16))


def _sample(tiled: Array, k: Array, ex: float, ey: float, rows: int, cols: int) -> Array:
    """h(P + k e) for every texel P; bilinear (periodic) unless e is a lattice vector."""
    if ex == round(ex) and ey == round(ey):
        return _shifted(tiled, k * int(ey), k * int(ex), rows, cols)
    kf = k.astype(tiled.dtype)
    ox, oy = kf * ex, kf * ey
    x0, y0 = jnp.floor(ox), jnp.floor(oy)
    fx, fy = ox - x0, oy - y0
    x0i, y0i = x0.astype(jnp.int32), y0.astype(jnp.int32)
    s00 = _shifted(tiled, y0i, x0i, rows, cols)
    s01 = _shifted(tiled, y0i, x0i + 1, rows, cols)
    s10 = _shifted(tiled, y0i + 1, x0i, rows, cols)
    s11 = _shifted(tiled, y0i + 1, x0i + 1, rows, cols)
    return (s00 * (1 - fx) + s01 * fx) * (1 - fy) + (s10 * (1 - fx) + s11 * fx) * fy


def _gather(height: Array, y: Array, x: Array, k: Array, ex: Array, ey: Array) -> Array:
    """h(P + k e) at per-lane texels P = (y, x) and steps e (periodic bilinear gather)."""
    rows, cols = height.shape
    kf = k.astype(height.dtype)
    oy = y.astype(height.dtype) + kf * ey
    ox = x.astype(height.dtype) + kf * ex
    y0, x0 = jnp.floor(oy), jnp.floor(ox)
    fy, fx = oy - y0, ox - x0
    y0i = jnp.mod(y0.astype(jnp.int32), rows)
    x0i = jnp.mod(x0.astype(jnp.int32), cols)
    y1i, x1i = jnp.mod(y0i + 1, rows), jnp.mod(x0i + 1, cols)
    top = height[y0i, x0i] * (1 - fx) + height[y0i, x1i] * fx
    bottom = height[y1i, x0i] * (1 - fx) + height[y1i, x1i] * fx
    return top * (1 - fy) + bottom * fy


def _band_max(height: Array, ex: float, ey: float, n_bands: int) -> list[Array]:
    """M_j(P) >= h(P + k e) for every k in [2^j, 2^(j+1)), j < n_bands: exact range maxima along
    lattice paths (sparse table of doubling windows), the global maximum otherwise."""
    if not (ex == round(ex) and ey == round(ey)):
        return [jnp.full_like(height, jnp.max(height))] * n_bands
    ix, iy = int(ex), int(ey)

    def shift(a: Array, k: int) -> Array:  # a(P + k e), periodic
        return jnp.roll(a, (-k * iy, -k * ix), axis=(0, 1))

    window = height  # W_j(P) = max over k in [0, 2^j) of h(P + k e)
    bands = []
    for j in range(n_bands):
        bands.append(shift(window, 2**j))
        window = jnp.maximum(window, shift(window, 2**j))
    return bands


def horizon_map(height: Float[ArrayLike, "H W"], *, directions: int = 8, texel_size: float = 1.0,
                near: int = 31, capacity: int | None = None, method: str = "auto") -> Float[Array, "D H W"]:
    """Horizon slopes (see `_horizon_map`), jitted with the keywords static.

    `method`: "search" (the exact search below), "sweep" (the convex-hull sweep, D = 4 or 8 and a
    square field only; equal to the search up to float rounding) or "auto": the sweep for lattice
    directions on square fields of at least `SWEEP_MIN_SIZE` texels a side, else the search.

    On the CPU backend the kernel is compiled preferring 512-bit vectors: the dense search is
    bound by vector arithmetic, and on a CPU with AVX-512 this made the 256x256 x 8 map ~15 %
    faster (0.0077 -> 0.0065 s on the project's 2-core Xeon, identical values); elsewhere the
    preference changes nothing. Traced inside another transformation (`jax.jit`, `vmap`, ...)
    it is inlined there, under the outer compilation's options.
    """
    kwargs = dict(directions=directions, texel_size=texel_size, near=near, capacity=capacity, method=method)
    if isinstance(height, jax.core.Tracer):
        return _horizon_map(height, **kwargs)
    compiled = _horizon_jit_cpu if jax.default_backend() == "cpu" else _horizon_jit
    return compiled(height, **kwargs)


def _horizon_map(height: Float[ArrayLike, "H W"], *, directions: int = 8, texel_size: float = 1.0,
                 near: int = 31, capacity: int | None = None, method: str = "auto") -> Float[Array, "D H W"]:
    """Horizon slopes (tan of the horizon elevation) of a periodic heightfield in D directions.

    `height` is in the same length unit as `texel_size` (scale ripple heights before calling).
    Exact (equal to the full search of every path). D = 4 or 8 (all steps on the lattice): every
    step k = 1 .. S - 1 is a whole-field periodic shift, searched densely (no gathers; `near` and
    `capacity` are not used). Other D: all texels search the first steps
    k <= `near` (rounded up to 2^j - 1) with whole-field shifts. Farther steps are split into
    dyadic bands [2^j, 2^(j+1)); a band can only matter to a (texel, direction) lane when the
    band's maximum height M_j (a sparse-table range maximum along the path) gives
    (M_j - h) / (2^j |e|) above the lane's best slope so far. Those lanes are compacted into
    batches of `capacity` (default: 1/8 of all lanes) and search the band with gathers.
    Jit-compatible; the keywords are static.
    """
    height = jnp.asarray(height)
    rows, cols = height.shape
    sweepable = directions in (4, 8) and rows == cols
    if method not in ("auto", "search", "sweep"):
        raise ValueError(f"horizon_map: method must be 'auto', 'search' or 'sweep', got {method!r}")
    if method == "sweep" and not sweepable:
        raise ValueError(f"horizon_map: the sweep needs 4 or 8 directions and a square field, got {directions} "
                         f"directions and {rows}x{cols}")
    if method == "sweep" or (method == "auto" and sweepable and rows >= SWEEP_MIN_SIZE):
        steps = [(round(ex), round(ey)) for ex, ey in horizon_directions(directions)]
        return lattice_sweep(height, steps, [math.hypot(ex, ey) * texel_size for ex, ey in steps])
    n_path = max(rows, cols) - 1
    tiled = jnp.tile(height, (2, 2))
    steps = horizon_directions(directions)
    lengths = [math.hypot(ex, ey) * texel_size for ex, ey in steps]
    j0 = max(1, math.ceil(math.log2(min(near, n_path) + 1)))
    n_bands = max(j0, math.ceil(math.log2(n_path + 1)))

    # phase 1: every texel, steps 1 .. 2^j0 - 1, whole-field (periodic) shifts
    def step(k, best):
        slopes = jnp.stack([(_sample(tiled, k, ex, ey, rows, cols) - height) / (k.astype(height.dtype) * lk)
                            for (ex, ey), lk in zip(steps, lengths)])
        return jnp.maximum(best, slopes)

    lattice = all(ex == round(ex) and ey == round(ey) for ex, ey in steps)
    if lattice:
        return _lattice_horizons(tiled, height, [(int(ex), int(ey)) for ex, ey in steps], lengths, n_path)
    k_end = min(2**j0, n_path + 1)
    best = jax.lax.fori_loop(1, k_end, step, jnp.zeros((directions, rows, cols), height.dtype))
    if 2**j0 > n_path:
        return best

    # phase 2: dyadic bands, only for the lanes whose band bound beats their best slope
    bands = [_band_max(height, ex, ey, n_bands) for ex, ey in steps]
    n_lanes = directions * rows * cols
    cap = capacity or max(1, n_lanes // 8)
    length_flat = jnp.broadcast_to(jnp.asarray(lengths, dtype=height.dtype)[:, None, None],
                                   (directions, rows, cols)).ravel()
    ex_all = jnp.asarray([e[0] for e in steps], dtype=height.dtype)
    ey_all = jnp.asarray([e[1] for e in steps], dtype=height.dtype)
    h_flat = height.ravel()
    best_flat = best.ravel()
    for j in range(j0, n_bands):
        k_lo, k_hi = 2**j, min(2 ** (j + 1) - 1, n_path)
        band = jnp.stack([b[j] for b in bands]).ravel()
        pending = ((band - jnp.tile(h_flat, directions)) > best_flat * (k_lo * length_flat)).astype(jnp.int32)

        def round_body(state, k_lo=k_lo, k_hi=k_hi):
            best_flat, pending = state
            count = jnp.sum(pending)
            idx = jnp.nonzero(pending, size=cap, fill_value=0)[0].astype(jnp.int32)
            valid = jnp.arange(cap) < count
            d = idx // (rows * cols)
            y = (idx // cols) % rows
            x = idx % cols
            h0 = h_flat[y * cols + x]
            lane_len = length_flat[idx]
            ex, ey = ex_all[d], ey_all[d]

            def inner(k, b):
                sample = _gather(height, y, x, k, ex, ey)
                return jnp.maximum(b, (sample - h0) / (k.astype(height.dtype) * lane_len))

            b = jax.lax.fori_loop(k_lo, k_hi + 1, inner, best_flat[idx])
            best_flat = best_flat.at[idx].max(jnp.where(valid, b, 0.0))
            pending = pending.at[idx].min(jnp.where(valid, 0, 1))
            return best_flat, pending

        best_flat, _ = jax.lax.while_loop(lambda s: jnp.any(s[1] > 0), round_body, (best_flat, pending))
    return best_flat.reshape(directions, rows, cols)


_STATIC = ("directions", "texel_size", "near", "capacity", "method")
_horizon_jit = jax.jit(_horizon_map, static_argnames=_STATIC)
_horizon_jit_cpu = jax.jit(_horizon_map, static_argnames=_STATIC,
                           compiler_options={"xla_cpu_prefer_vector_width": "512"})


def _toward_light(maps: Array, light_local: Array) -> tuple[Array, Array, Array]:
    """`maps` (D ...) interpolated linearly in azimuth toward the light, with the light's lz and
    horizontal length |(lx, ly)|."""
    n_dir = maps.shape[0]
    lx, ly, lz = light_local[..., 0], light_local[..., 1], light_local[..., 2]
    phi = jnp.mod(jnp.arctan2(ly, lx), 2 * jnp.pi)
    pos = phi * (n_dir / (2 * jnp.pi))
    d0 = jnp.floor(pos)
    w = pos - d0
    d0i = jnp.mod(d0.astype(jnp.int32), n_dir)
    d1i = jnp.mod(d0i + 1, n_dir)
    m0 = jnp.take_along_axis(maps, d0i[None], axis=0)[0]
    m1 = jnp.take_along_axis(maps, d1i[None], axis=0)[0]
    return (1 - w) * m0 + w * m1, lz, jnp.sqrt(lx * lx + ly * ly)


def horizon_shadow(horizon: Float[ArrayLike, "D ..."], light_local: Float[ArrayLike, "... 3"]) -> Bool[Array, "..."]:
    """True where the light is blocked: the light's slope lz / |(lx, ly)| is below the horizon
    slope interpolated linearly in azimuth between the two neighbouring directions.

    `horizon[d]` holds the slopes of direction d at each shading point (already looked up);
    `light_local` is the unit light vector in the heightfield's frame (x, y along the texture
    axes, z along the un-bumped normal)."""
    h, lz, flat = _toward_light(jnp.asarray(horizon), jnp.asarray(light_local))
    # light slope > horizon slope <=> lz > h * flat (no division; overhead light is never blocked)
    return ~(lz > h * flat)


def horizon_band(horizon: Float[ArrayLike, "D H W"]) -> Float[Array, "D H W"]:
    """How much each direction's horizon slope changes across one texel: the magnitude of its
    gradient per texel (central differences, periodic). `horizon_light` spreads the shadow
    edge over this band of slopes."""
    horizon = jnp.asarray(horizon)
    dx = 0.5 * (jnp.roll(horizon, -1, axis=-1) - jnp.roll(horizon, 1, axis=-1))
    dy = 0.5 * (jnp.roll(horizon, -1, axis=-2) - jnp.roll(horizon, 1, axis=-2))
    return jnp.sqrt(dx * dx + dy * dy)


def horizon_light(horizon: Float[ArrayLike, "D ..."], band: Float[ArrayLike, "D ..."],
                  light_local: Float[ArrayLike, "... 3"]) -> Float[Array, "..."]:
    """Lit fraction of each shading texel, the antialiased `horizon_shadow`: the horizon slope h
    varies across the texel by about `band` (`horizon_band`, looked up like `horizon`), so the
    part of the texel whose horizon lies below the light's slope s is
    clip(1/2 + (s - h) / band, 0, 1); with band 0 it is the binary test. Against the lit fraction
    of 4x4 brute-force rays per texel its mean error is 6-26 % below the binary test's
    (tests/test_desert_shadows.py), and it softens the speckle of single shadowed texels in the
    ripple troughs at grazing sun."""
    h, lz, flat = _toward_light(jnp.asarray(horizon), jnp.asarray(light_local))
    b, _, _ = _toward_light(jnp.asarray(band), jnp.asarray(light_local))
    # (s - h) / band with s = lz / flat, written without dividing by flat (overhead light: lit)
    margin = lz - h * flat
    width = b * flat
    soft = jnp.clip(0.5 + margin / jnp.where(width > 0, width, 1.0), 0.0, 1.0)
    return jnp.where(width > 0, soft, (margin > 0).astype(margin.dtype))

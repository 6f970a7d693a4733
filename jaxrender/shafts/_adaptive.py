"""In-scattering at the resolution it needs (the default shafts method, "adaptive"): every light's
equiangular single scattering (`equiangular_scattering`) evaluated on a coarse grid of rays,
interpolated to the pixels, and evaluated at the pixels themselves in the cells where the
interpolation would be wrong; surfaces at full resolution.

The image is cut into cells of `cell` x `cell` pixels (4 x 4 by default); the coarse rays
("nodes") pass through the pixels at the cells' corners (pixel (cell i, cell j), one row and
column past the image's last cells). Each light's in-scattering v is evaluated at the nodes (only
where its cone is: `active_rays_map`) and the pixels of a cell get the bilinear interpolation of
its four corners. A cell is refined for a light, every pixel of it evaluated, where

- the interpolation's error, estimated as a quarter of the largest second difference of v along
  the node rows and columns at the cell's corners (bilinear interpolation between nodes a cell
  apart errs by about that at a kink, by half that on a smooth curve), exceeds `tolerance` times
  the RMS of the in-scattered light over the nodes: at shadow and light-map edges, the cone's
  rim, where a beam meets a surface;
- or the surfaces' depth jumps inside the cell (a pixel's depth is off the bilinear interpolation
  of the corners' depths by more than `DEPTH_JUMP`, relative) and the light is seen around the
  cell (some node of the cell's 4 x 4 neighbourhood has in-scattered light of it): at a
  silhouette the in-scattering jumps with the depth, and interpolating across the jump would
  bleed light from one side onto the other (a halo). Depth-aware by construction: no cell whose
  pixels straddle a silhouette is interpolated.

Node and refined pixel values are the equiangular method's own, so the image is that method's
wherever it is not interpolated (tests/test_shafts_adaptive.py checks it to rounding), and its
error against the converged integral is the equiangular rays' plus the interpolation's, which the
tolerance holds to a fraction of it (benchmarks/RESULTS.md, "Light shafts at interactive rates").

The light maps are read with `MAP_TAPS` taps a sample, spread over the sample's angle: on
sharp-edged maps (a polka-dot gobo of 256^2 texels) the point-sampled midpoint rule's error is
the light map's, not the falloff's or the fog's (24 samples: 3.2 % with one tap, 1.8 % with two,
on the textured spot), and a tap costs less than a sample (a gather and a dozen flops).

Refinement is a fixed-capacity compaction (`map_active_runs`): the pixels are ordered cell by
cell, so a refined cell is one contiguous run of cell^2 rays, and chunks of runs past the refined
count are skipped under `lax.cond`. The interpolation and the refinement are linear in the node
and pixel values, so gradients reach every parameter the equiangular method's do; the choice of
cells carries none (a selection, like a shadow test).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..fusion import materialize
from ..geometry import nearest_distance
from ._equiangular import active_rays_map, light_scatter_fns, map_active_runs, render_equiangular, shade_frame
from ._model import FAR, cone_intervals
from ._scene import ShaftsScene

__all__ = ["render_adaptive", "MAP_TAPS"]

MAP_TAPS = 2  # light-map taps a sample (module docstring)
# a pixel whose depth is off the bilinear interpolation of its cell's corners by more than this
# fraction is across a silhouette: a smooth surface's depth is off by far less over a 4-pixel cell
# (second order in the cell's angle: 1 % only at ~86 degrees of incidence at 720 x 480)
DEPTH_JUMP = 0.01


def _pixel_layout(height: int, width: int, cell: int):
    """Continuous pixel coordinates (column, row) of the pixel centres, ordered cell by cell:
    (cells, cell^2, 2) for ceil(H / cell) x ceil(W / cell) cells (pixels past the image's edge
    included: they are cropped at the end)."""
    hc, wc = -(-height // cell), -(-width // cell)
    a = np.arange(cell)
    rows = np.broadcast_to(np.arange(hc)[:, None, None, None] * cell + a[None, None, :, None], (hc, wc, cell, cell))
    cols = np.broadcast_to(np.arange(wc)[None, :, None, None] * cell + a[None, None, None, :], (hc, wc, cell, cell))
    xy = np.stack([cols, rows], axis=-1) + 0.5
    return xy.reshape((hc * wc, cell * cell, 2)), (hc, wc)


def _to_image(x: Array, hc: int, wc: int, cell: int, height: int, width: int) -> Array:
    """(cells, cell^2, C) in cell order -> (H, W, C)."""
    img = x.reshape((hc, wc, cell, cell) + x.shape[2:]).transpose((0, 2, 1, 3) + tuple(range(4, x.ndim + 2)))
    return img.reshape((hc * cell, wc * cell) + x.shape[2:])[:height, :width]


def _interp_weights(cell: int) -> np.ndarray:
    """(cell^2, 4) bilinear weights of the corners (top-left, top-right, bottom-left, bottom-right)."""
    f = np.arange(cell) / cell
    fy, fx = (g.reshape((-1,)) for g in np.meshgrid(f, f, indexing="ij"))
    return np.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], axis=-1)


def _corners(nodes: Array) -> Array:
    """(hc + 1, wc + 1, ...) node values -> (hc * wc, 4, ...) of each cell's corners."""
    c = jnp.stack([nodes[:-1, :-1], nodes[:-1, 1:], nodes[1:, :-1], nodes[1:, 1:]], axis=2)
    return c.reshape((-1,) + c.shape[2:])


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _lerp(cell: int, corners: Array) -> Array:
    """Bilinear interpolation inside each cell of `cell` x `cell` pixels: (cells, 4, ...) corner
    values -> (cells, cell^2, ...); written out (a dot product over 4 corners is slow on XLA's
    CPU), and so is its transpose (`_lerp_bwd`)."""
    weights = _interp_weights(cell)
    extra = (1,) * (corners.ndim - 2)
    return sum(jnp.asarray(weights[None, :, k].reshape((1, -1) + extra), corners.dtype) * corners[:, k:k + 1]
               for k in range(4))


def _lerp_fwd(cell, corners):
    return _lerp(cell, corners), None


def _lerp_bwd(cell, _, g):
    """Each corner's cotangent, the weighted sum over the cell's pixels as cell^2 terms: XLA's
    transpose of the broadcast reduces over the pixel axis, ~6x slower on CPU (a gradient of the
    adaptive frame spent a tenth of its time there)."""
    weights = _interp_weights(cell)
    return (jnp.stack([sum(float(weights[p, k]) * g[:, p] for p in range(weights.shape[0]) if weights[p, k] != 0)
                       for k in range(4)], axis=1),)


_lerp.defvjp(_lerp_fwd, _lerp_bwd)


def _bends(v: Array) -> Array:
    """Per node, the largest second difference of v (..., 3) along rows or columns (edge nodes:
    their neighbour repeated), the largest channel."""
    p = jnp.pad(v, ((1, 1), (1, 1), (0, 0)), mode="edge")
    dx = jnp.abs(p[1:-1, :-2] - 2.0 * v + p[1:-1, 2:])
    dy = jnp.abs(p[:-2, 1:-1] - 2.0 * v + p[2:, 1:-1])
    return jnp.max(jnp.maximum(dx, dy), axis=-1)


def _dilate(x: Array) -> Array:
    """Each node's flag or its 3 x 3 neighbourhood's."""
    p = jnp.pad(x, 1, mode="edge")
    h, w = x.shape
    return functools.reduce(jnp.logical_or, [p[i:i + h, j:j + w] for i in range(3) for j in range(3)])


def render_adaptive(scene: ShaftsScene, *, samples: int = 24, map_taps: int = MAP_TAPS, cell: int = 4,
                    tolerance: float = 0.05,
                    shadow_map: int | None = 512, surface_shadows: str = "map", chunk: int = 8192,
                    fog_nodes: int | tuple[int, int] | None = None, return_parts: bool = False,
                    return_refined: bool = False) -> Float[Array, "H W 3"]:
    """Render `scene` (H, W, 3 linear RGB): surfaces per pixel as `render_equiangular`, the
    in-scattering of every light (`samples` per ray, equiangular) at the corners of `cell` x `cell`
    pixel cells, interpolated, and exact in the cells where the interpolation's estimated error
    exceeds `tolerance` x the RMS of the in-scattered light, or where a silhouette crosses a lit
    cell (module docstring). `cell=1` is `render_equiangular`. shadow_map, surface_shadows, chunk, fog_nodes: as
    `render_equiangular`. return_parts: also return (surface, per-light in-scattering list);
    return_refined: also return which cells were refined, (cells down, cells across, lights) booleans.
    Jittable, differentiable; no retrace when light or medium values change."""
    if int(cell) == 1:
        if return_refined:
            raise ValueError("cell=1 refines nothing: it is render_equiangular")
        return render_equiangular(scene, samples=samples, map_taps=map_taps, shadow_map=shadow_map,
                                  surface_shadows=surface_shadows, chunk=chunk, fog_nodes=fog_nodes,
                                  return_parts=return_parts)
    cam = scene.camera
    height, width, cell = cam.height, cam.width, int(cell)
    xy, (hc, wc) = _pixel_layout(height, width, cell)
    dtype = cam.eye.dtype
    frame = shade_frame(scene, shadow_map=shadow_map, surface_shadows=surface_shadows, fog_nodes=fog_nodes,
                        dirs=cam.ray_direction(jnp.asarray(xy, dtype)))
    # the nodes: pixels (cell i, cell j) for i <= hc, j <= wc
    ny, nx = jnp.meshgrid(jnp.arange(hc + 1, dtype=dtype) * cell, jnp.arange(wc + 1, dtype=dtype) * cell,
                          indexing="ij")
    node_dirs = cam.ray_direction(jnp.stack([nx, ny], axis=-1) + 0.5)
    node_t = materialize(lambda s, d: nearest_distance(s.camera.eye, d, s.prims), scene, node_dirs)
    node_t = jnp.where(jnp.isfinite(node_t), node_t, FAR)

    # silhouettes: a pixel's depth off the bilinear interpolation of its cell's corners' depths
    lerp_t = _lerp(cell, _corners(jax.lax.stop_gradient(node_t)))
    pixel_t = jax.lax.stop_gradient(frame.surface_t)
    jump = jnp.any(jnp.abs(pixel_t - lerp_t) > DEPTH_JUMP * jnp.minimum(pixel_t, lerp_t), axis=1)

    scatters = list(light_scatter_fns(scene, frame, samples=samples, map_taps=map_taps))
    node_v = []
    for light, (scatter, reach) in zip(scene.lights, scatters):
        # stored: else XLA computes them inside `active_rays_map`'s pads, element by element (unvectorized)
        t0, t1 = materialize(cone_intervals, scene, light, node_dirs, node_t, reach)
        node_v.append(active_rays_map(scatter, node_dirs, t0, t1, chunk=chunk))
    total = sum(node_v)
    threshold = tolerance * jax.lax.stop_gradient(jnp.sqrt(jnp.mean(total * total)))

    chunk_runs = max(1, chunk // (cell * cell))
    image = frame.surface + _lerp(cell, _corners(total))
    parts, refined = [], []
    for light, (scatter, reach), v in zip(scene.lights, scatters, node_v):
        v_fixed = jax.lax.stop_gradient(v)
        bend_error = 0.25 * jnp.max(_corners(_bends(v_fixed)), axis=1)
        # seen around the cell: a node behind a silhouette's near side sees none of the light
        lit = jnp.any(_corners(_dilate(jnp.max(v_fixed, axis=-1) > 0)), axis=1)
        flag = (bend_error > threshold) | (jump & lit)
        refined.append(flag.reshape((hc, wc)))

        def correction(valid, dirs, surface_t, corners, light=light, scatter=scatter, reach=reach):
            n = dirs.shape[0]
            t0, t1 = cone_intervals(scene, light, dirs.reshape((-1, 3)), surface_t.reshape((-1,)), reach)
            live = jnp.repeat(valid, cell * cell)
            t0, t1 = jnp.where(live, t0, 0.0), jnp.where(live, t1, 0.0)
            exact = scatter(dirs.reshape((-1, 3)), t0, t1).reshape((n, cell * cell, 3))
            return jnp.where(valid[:, None, None], exact - _lerp(cell, corners), 0.0)

        args = (frame.dirs, frame.surface_t, _corners(v))
        if return_parts:
            own = map_active_runs(correction, flag, args, chunk_runs=chunk_runs, into=_lerp(cell, _corners(v)))
            parts.append(_to_image(own, hc, wc, cell, height, width))
        else:
            image = map_active_runs(correction, flag, args, chunk_runs=chunk_runs, into=image)
    out = _to_image(image, hc, wc, cell, height, width)
    surface = _to_image(frame.surface, hc, wc, cell, height, width) if return_parts else None
    if return_parts:
        out = surface + sum(parts)
    extra = ()
    if return_parts:
        extra += ((surface, parts),)
    if return_refined:
        extra += (jnp.stack(refined, axis=-1),)
    return (out,) + extra if extra else out

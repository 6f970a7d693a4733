"""In-scattering at the resolution it needs (the default shafts method, "adaptive"): every light's
equiangular single scattering (`equiangular_scattering`) evaluated on a coarse grid of rays,
interpolated to the pixels, and evaluated exactly at the pixels of the cells where the
interpolation would be wrong; surfaces at full resolution.

The image is cut into cells of `cell` x `cell` pixels; the coarse rays ("nodes") pass through
the pixels at the cells' corners (pixel (cell i, cell j), one more row and column past the image's
last cells). Each light's in-scattering v is evaluated at the nodes (only where its cone is:
`active_rays_map`) and the pixels of a cell get the bilinear interpolation of its four corners.
A cell is refined for a light, all its pixels evaluated exactly, where the interpolation's error
is estimated above `tolerance` times the RMS of the in-scattered light over the nodes:

- the light's in-scattering bends within the cell: the second differences of v along the node
  rows and columns at the cell's corners (bilinear interpolation between nodes a cell apart errs
  by about a quarter of them at a kink, an eighth on a smooth curve), at shadow and light-map
  edges and the cone's rim;
- the surfaces' depth jumps inside the cell (the depth of a pixel is off the bilinear
  interpolation of the corners' depths by more than `tolerance` relative) and the light's cone
  crosses a corner's ray: at silhouettes the in-scattering jumps with the depth, and
  interpolating across the jump would bleed light from one side onto the other (a halo).

Refinement is a fixed-capacity compaction (`map_active_runs`): the pixels are ordered cell by cell,
so a refined cell is one contiguous run of cell^2 rays; runs past the refined count are skipped
under `lax.cond`. The interpolation and the refinement are linear in the node and pixel values,
so gradients flow to every parameter the equiangular method's do; the choice of cells carries
none (it is a selection, like a shadow test).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..fusion import materialize
from ..geometry import nearest_distance
from ._equiangular import active_rays_map, light_scatter_fns, map_active_runs, shade_frame
from ._model import FAR, cone_intervals
from ._scene import ShaftsScene

__all__ = ["render_adaptive"]


def _pixel_layout(height: int, width: int, cell: int):
    """Continuous pixel coordinates (column, row) of the pixel centres, ordered cell by cell:
    (cells, cell^2, 2) for ceil(H / cell) x ceil(W / cell) cells (pixels past the image's edge
    included: they are cropped at the end)."""
    hc, wc = -(-height // cell), -(-width // cell)
    a = jnp.arange(cell)
    rows = (jnp.arange(hc)[:, None, None, None] * cell + a[None, None, :, None]) + jnp.zeros((1, wc, 1, cell))
    cols = (jnp.arange(wc)[None, :, None, None] * cell + a[None, None, None, :]) + jnp.zeros((hc, 1, cell, 1))
    xy = jnp.stack([cols, rows], axis=-1) + 0.5
    return xy.reshape((hc * wc, cell * cell, 2)), (hc, wc)


def _to_image(x: Array, hc: int, wc: int, cell: int, height: int, width: int) -> Array:
    """(cells, cell^2, C) in cell order -> (H, W, C)."""
    img = x.reshape((hc, wc, cell, cell) + x.shape[2:]).transpose((0, 2, 1, 3) + tuple(range(4, x.ndim + 2)))
    return img.reshape((hc * cell, wc * cell) + x.shape[2:])[:height, :width]


def _interp_weights(cell: int, dtype) -> Array:
    """(cell^2, 4) bilinear weights of the corners (top-left, top-right, bottom-left, bottom-right)."""
    f = jnp.arange(cell, dtype=dtype) / cell
    fy, fx = jnp.meshgrid(f, f, indexing="ij")
    fy, fx = fy.reshape((-1,)), fx.reshape((-1,))
    return jnp.stack([(1 - fy) * (1 - fx), (1 - fy) * fx, fy * (1 - fx), fy * fx], axis=-1)


def _corners(nodes: Array) -> Array:
    """(hc + 1, wc + 1, ...) node values -> (hc * wc, 4, ...) of each cell's corners."""
    c = jnp.stack([nodes[:-1, :-1], nodes[:-1, 1:], nodes[1:, :-1], nodes[1:, 1:]], axis=2)
    return c.reshape((-1,) + c.shape[2:])


def _lerp(weights: Array, corners: Array) -> Array:
    """Bilinear interpolation inside each cell: (cell^2, 4) weights, (cells, 4, ...) corner values
    -> (cells, cell^2, ...); written out (a dot product over 4 corners is slow on XLA's CPU)."""
    extra = (1,) * (corners.ndim - 2)
    return sum(weights[None, :, k].reshape((1, -1) + extra) * corners[:, k:k + 1] for k in range(4))


def _bends(v: Array) -> Array:
    """Per node, the largest second difference of v (..., 3) along rows or columns (edge nodes:
    their neighbour repeated), the largest channel."""
    p = jnp.pad(v, ((1, 1), (1, 1), (0, 0)), mode="edge")
    dx = jnp.abs(p[1:-1, :-2] - 2.0 * v + p[1:-1, 2:])
    dy = jnp.abs(p[:-2, 1:-1] - 2.0 * v + p[2:, 1:-1])
    return jnp.max(jnp.maximum(dx, dy), axis=-1)


def render_adaptive(scene: ShaftsScene, *, samples: int = 24, map_taps: int = 2, cell: int = 4,
                    tolerance: float = 0.1,
                    shadow_map: int | None = 512, surface_shadows: str = "map", chunk: int = 8192,
                    fog_nodes: int | tuple[int, int] | None = None, return_parts: bool = False,
                    return_refined: bool = False) -> Float[Array, "H W 3"]:
    """Render `scene` (H, W, 3 linear RGB): surfaces per pixel as `render_equiangular`, the
    in-scattering of every light (`samples` per ray, equiangular) at the corners of `cell` x `cell`
    pixel cells, interpolated, and exact in the cells where the interpolation's estimated error
    exceeds `tolerance` x the RMS of the in-scattered light (module docstring). `cell=1` is the
    equiangular method itself. shadow_map, surface_shadows, chunk, fog_nodes: as
    `render_equiangular`. return_parts: also return (surface, per-light in-scattering list);
    return_refined: also return the fraction of cells refined per light (a diagnostic).
    Jittable, differentiable; no retrace when light or medium values change."""
    cam = scene.camera
    height, width, cell = cam.height, cam.width, int(cell)
    xy, (hc, wc) = _pixel_layout(height, width, cell)
    dtype = cam.eye.dtype
    frame = shade_frame(scene, shadow_map=shadow_map, surface_shadows=surface_shadows, fog_nodes=fog_nodes,
                        dirs=cam.ray_direction(xy.astype(dtype)))
    # the nodes: pixels (cell i, cell j) for i <= hc, j <= wc
    ny, nx = jnp.meshgrid(jnp.arange(hc + 1, dtype=dtype) * cell, jnp.arange(wc + 1, dtype=dtype) * cell,
                          indexing="ij")
    node_dirs = cam.ray_direction(jnp.stack([nx, ny], axis=-1) + 0.5)
    node_t = materialize(lambda s, d: nearest_distance(s.camera.eye, d, s.prims), scene, node_dirs)
    node_t = jnp.where(jnp.isfinite(node_t), node_t, FAR)

    weights = _interp_weights(cell, dtype)
    # depth jumps inside a cell: a pixel's depth off the bilinear interpolation of its corners'
    # (relative), or a corner or pixel seeing nothing while another sees a surface
    pixel_t = jax.lax.stop_gradient(frame.surface_t)
    lerp_t = _lerp(weights, _corners(jax.lax.stop_gradient(node_t)))
    jump = jnp.any(jnp.abs(pixel_t - lerp_t) > tolerance * jnp.minimum(pixel_t, lerp_t), axis=1)

    scatters = list(light_scatter_fns(scene, frame, samples=samples, map_taps=map_taps))
    node_v, node_in_cone = [], []
    for light, (scatter, reach) in zip(scene.lights, scatters):
        t0, t1 = cone_intervals(scene, light, node_dirs, jnp.full_like(node_t, FAR), reach)
        node_in_cone.append(t1 > t0)  # the ray crosses the cone, whatever surface it meets
        t1 = jnp.maximum(jnp.minimum(t1, node_t), t0)
        node_v.append(active_rays_map(scatter, node_dirs, t0, t1, chunk=chunk))
    total = sum(node_v)
    threshold = tolerance * jax.lax.stop_gradient(jnp.sqrt(jnp.mean(total * total)))

    chunk_runs = max(1, chunk // (cell * cell))
    image = frame.surface + _lerp(weights, _corners(total))
    parts, refined = [], []
    for light, (scatter, reach), v, in_cone in zip(scene.lights, scatters, node_v, node_in_cone):
        bends = _corners(_bends(jax.lax.stop_gradient(v)))  # (cells, 4)
        crossed = jnp.any(_corners(in_cone), axis=1)
        flag = (jnp.max(bends, axis=1) > 4.0 * threshold) | (jump & crossed)
        refined.append(jnp.mean(flag.astype(dtype)))

        def correction(valid, dirs, surface_t, corners, light=light, scatter=scatter, reach=reach):
            n = dirs.shape[0]
            t0, t1 = cone_intervals(scene, light, dirs.reshape((-1, 3)), surface_t.reshape((-1,)), reach)
            live = jnp.repeat(valid, cell * cell)
            t0, t1 = jnp.where(live, t0, 0.0), jnp.where(live, t1, 0.0)
            exact = scatter(dirs.reshape((-1, 3)), t0, t1).reshape((n, cell * cell, 3))
            return jnp.where(valid[:, None, None], exact - _lerp(weights, corners), 0.0)

        args = (frame.dirs, frame.surface_t, _corners(v))
        if return_parts:
            own = map_active_runs(correction, flag, args, chunk_runs=chunk_runs, into=_lerp(weights, _corners(v)))
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
        extra += (jnp.stack(refined),)
    return (out,) + extra if extra else out

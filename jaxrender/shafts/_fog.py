"""The transmittance lookups of the fast methods in fog with a density grid: one optical-depth
volume seen from the eye (over the camera's frustum) and one from each spot light (over its
cone), built once per frame (`fog_volumes`) from the scene's `DensityGrid`.

A sample P on a view ray then needs d(P) (the grid itself), tau_l(P) (the light's volume at P's
direction from the light and distance) and tau_v(P) (the eye's volume); its in-scattering weight
is rho d(P) F(a) I exp(-rho kappa (tau_l + tau_v)) / s^2. Volume sizes follow the grid's
resolution (`volume_nodes`): with n voxels along the grid's longest axis, 2n directions across
(24 to 96) and n distances (24 to 64); directions matter more (a layer of fog seen from above
makes neighbouring rays' optical depths differ fast, along each ray it is smooth).
Why optical-depth volumes in light space and not the anchors' transmittance or froxel volumes,
and what they cost: docs/fog.md.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ..lights import SpotLight
from ._density import DensityGrid, DepthVolume, depth_volume
from ._scene import ShaftsScene

__all__ = ["FogVolumes", "RayFog", "fog_volumes", "volume_nodes", "light_volume", "view_volume"]

def volume_nodes(grid: DensityGrid) -> tuple[int, int]:
    """(directions across, distances) of the optical-depth volumes for `grid`."""
    n = max(grid.shape)
    return int(min(max(2 * n, 24), 96)), int(min(max(n, 24), 64))


def _nodes(grid: DensityGrid, nodes) -> tuple[int, int]:
    if nodes is None:
        return volume_nodes(grid)
    return (int(nodes), int(nodes)) if isinstance(nodes, int) else (int(nodes[0]), int(nodes[1]))


def light_volume(grid: DensityGrid, light: SpotLight, nodes: tuple[int, int]) -> DepthVolume:
    """Optical depth from the light over its cone; frustum coordinates (a, b) = 2 uv - 1 of the
    light map / shadow map. `nodes`: (directions across, distances)."""
    tan_c = jnp.tan(light.cutoff)
    across, along = nodes
    return depth_volume(grid, light.position, light.rotation(), tan_c, tan_c, n_u=across, n_v=across, n_s=along)


def view_volume(grid: DensityGrid, scene: ShaftsScene, nodes: tuple[int, int]) -> DepthVolume:
    """Optical depth from the eye over the camera's frustum (rows right, up, forward); `nodes`
    across the frustum's shorter side and along the rays."""
    cam = scene.camera
    right, up, forward = cam.frame()
    aspect = cam.width / cam.height
    tan_y = cam.tan_half_fov
    across, along = nodes
    n_u = max(across, int(round(across * aspect))) if aspect >= 1 else across
    n_v = across if aspect >= 1 else max(across, int(round(across / aspect)))
    return depth_volume(grid, cam.eye, jnp.stack([right, up, forward]), tan_y * aspect, tan_y,
                        n_u=n_u, n_v=n_v, n_s=along)


class RayFog(eqx.Module):
    """What one light's samples need of a density grid: the grid, the light's optical-depth
    volume and the eye's."""

    grid: DensityGrid
    light: DepthVolume
    view: DepthVolume


class FogVolumes(eqx.Module):
    """The grid and its optical-depth volumes from the eye and from each light."""

    grid: DensityGrid
    view: DepthVolume
    lights: tuple[DepthVolume, ...]

    def view_depth(self, scene: ShaftsScene, dirs, t):
        """tau from the eye to `eye + t dirs` (unit `dirs` of shape `(*B, 3)`, `t` of shape `(*B)`)."""
        return self.view.lookup_points(jnp.broadcast_to(scene.camera.eye, dirs.shape) + t[..., None] * dirs)

    def light_depth(self, index: int, points):
        """tau from light `index` to `points` of shape `(*B, 3)`."""
        return self.lights[index].lookup_points(points)

    def for_light(self, index: int) -> RayFog:
        return RayFog(self.grid, self.lights[index], self.view)


def fog_volumes(scene: ShaftsScene, *, nodes: int | tuple[int, int] | None = None) -> FogVolumes | None:
    """The volumes of `scene`'s density grid (None in uniform fog). `nodes`: (directions across,
    distances), or one number for both (default `volume_nodes`)."""
    grid = scene.medium.density
    if grid is None:
        return None
    n = _nodes(grid, nodes)
    return FogVolumes(grid, view_volume(grid, scene, n), tuple(light_volume(grid, light, n) for light in scene.lights))

"""The light-shaft scene as one pytree: camera, medium, render settings, spot lights, primitives."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..camera import Camera
from ..geometry import Quads, Spheres
from ..lights import SpotLight, unstack_spotlights
from ..shadows import ShadowMap, render_shadow_map
from ._density import DensityGrid


class Medium(eqx.Module):
    """Fog (paper 000): density `rho`, extinction coefficient `kappa`, phase scale `K`, and
    optionally a `density` grid d(x) (`DensityGrid`) that varies it in space.

    Extinction per unit length is `rho*kappa*d(x)`; scattering per unit length per steradian is
    `rho*d(x)*F(a)` with `F(a) = K (1 + 9 cos^16(a/2))`; d = 1 everywhere without a grid (uniform
    fog), d = 0 outside the grid's box with one. (The image depends on `rho*kappa*d` and `rho*K*d` only.)
    """

    rho: Float[Array, ""]
    kappa: Float[Array, ""]
    K: Float[Array, ""]
    density: DensityGrid | None = None

    def __init__(self, rho=1.0, kappa=0.1, K=0.003, density: DensityGrid | None = None):
        self.rho = jnp.asarray(rho, dtype=float)
        self.kappa = jnp.asarray(kappa, dtype=float)
        self.K = jnp.asarray(K, dtype=float)
        self.density = density

    @property
    def sigma_t(self) -> Float[Array, ""]:
        return self.rho * self.kappa


class RenderSettings(eqx.Module):
    """`render` block of the scene file. Integers are static (they set array shapes)."""

    shadow_map: int = eqx.field(static=True, default=1024)
    table_size: int = eqx.field(static=True, default=256)
    spp: int = eqx.field(static=True, default=1)  # samples per pixel (k*k grid) the command line renders with
    shadow_bias: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.asarray(0.002))
    s_min: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.asarray(0.05))
    s_max: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.asarray(20.0))
    t_max: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.asarray(20.0))
    display_white: Float[Array, ""] = eqx.field(default_factory=lambda: jnp.asarray(1.0))


class ShaftsScene(eqx.Module):
    """Everything `render_planes` / `render_raymarch` need.

    `lights` is a tuple of `SpotLight`s (a stacked SpotLight is unstacked on construction);
    `spheres`/`quads` are packed primitive groups (may hold zero rows). `source` names the file
    the scene came from (for messages only).
    """

    camera: Camera
    medium: Medium
    lights: tuple[SpotLight, ...]
    spheres: Spheres
    quads: Quads
    render: RenderSettings
    source: str = eqx.field(static=True, default="<scene>")

    def __init__(self, camera, medium, lights, spheres=None, quads=None, render=None, *, source="<scene>"):
        self.camera = camera
        self.medium = medium
        self.lights = tuple(unstack_spotlights(lights))
        self.spheres = Spheres(jnp.zeros((0, 3)), jnp.zeros((0,)), jnp.zeros((0, 3))) if spheres is None else spheres
        no_quads = Quads(jnp.zeros((0, 3)), jnp.zeros((0, 3)), jnp.zeros((0, 3)), jnp.zeros((0, 3)))
        self.quads = no_quads if quads is None else quads
        self.render = RenderSettings() if render is None else render
        self.source = str(source)

    @property
    def prims(self) -> tuple[Spheres, Quads]:
        return (self.spheres, self.quads)

    def with_size(self, width: int | None = None, height: int | None = None) -> "ShaftsScene":
        """The same scene rendered at another image size."""
        cam = self.camera
        new = Camera(cam.eye, cam.target, cam.up, cam.fov_y_deg,
                     width=cam.width if width is None else width, height=cam.height if height is None else height)
        return eqx.tree_at(lambda s: s.camera, self, new)


def shadow_maps(scene: ShaftsScene, resolution: int) -> tuple[ShadowMap, ...]:
    """One shadow map per spot light of `scene` (`render_shadow_map`), `resolution` texels square."""
    return tuple(render_shadow_map(light, scene.prims, resolution=resolution) for light in scene.lights)

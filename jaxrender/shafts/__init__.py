"""Light shafts in fog (paper 000): the scattering model of eqs. 1-4, a fast equiangular
single-scattering method, evaluated where the image needs it by the default method (`adaptive`:
a coarse grid of rays, refined at edges and silhouettes) or at every pixel, the sample-plane
method with sub-sample planes and 8-bit hardware emulation (eqs. 5-9), and a ray-marched reference;
`render` runs any of them with `samples_per_pixel` (k x k regular sub-pixel grid, box filter). Fog may vary in space: a
`DensityGrid` in `Medium(density=...)` (every method, differentiable in the grid).

    scene = jaxrender.app.scenes.load_shafts_scene("scene.json")
    image = jaxrender.shafts.render(scene, samples_per_pixel=4)                 # adaptive, 2 x 2 AA
    image = jaxrender.shafts.render_planes(scene, planes=30, subplanes=6)     # (H, W, 3)
    ref = jaxrender.shafts.render_raymarch(scene, samples=180)
"""

from ._adaptive import render_adaptive as render_adaptive
from ._density import DensityGrid as DensityGrid
from ._density import DepthVolume as DepthVolume
from ._density import box_interval as box_interval
from ._density import depth_volume as depth_volume
from ._density import segment_optical_depth as segment_optical_depth
from ._equiangular import equiangular_ladder as equiangular_ladder
from ._equiangular import equiangular_scattering as equiangular_scattering
from ._equiangular import render_equiangular as render_equiangular
from ._error_target import CountChoice as CountChoice
from ._error_target import choose_counts as choose_counts
from ._error_target import proxy_scene as proxy_scene
from ._fog import FogVolumes as FogVolumes
from ._fog import fog_volumes as fog_volumes
from ._fog import volume_nodes as volume_nodes
from ._model import attenuation_h as attenuation_h
from ._model import cone_depth_range as cone_depth_range
from ._model import cone_interval as cone_interval
from ._model import light_reach as light_reach
from ._model import phase as phase
from ._model import phase_cos as phase_cos
from ._planes import render_planes as render_planes
from ._raymarch import raymarch_scattering as raymarch_scattering
from ._raymarch import render_raymarch as render_raymarch
from ._render import DEFAULT_METHOD as DEFAULT_METHOD
from ._render import METHODS as METHODS
from ._render import render as render
from ._render import supersample as supersample
from ._scene import Medium as Medium
from ._scene import RenderSettings as RenderSettings
from ._scene import ShaftsScene as ShaftsScene
from ._scene import shadow_maps as shadow_maps

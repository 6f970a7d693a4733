"""Light shafts in fog (paper 000): the scattering model of eqs. 1-4, the sample-plane method
with sub-sample planes and 8-bit hardware emulation (eqs. 5-9), and a ray-marched reference.

    scene = jaxrender.scenes.load_shafts_scene("scene.json")
    image = jaxrender.shafts.render_planes(scene, planes=30, subplanes=6)     # (H, W, 3)
    ref = jaxrender.shafts.render_raymarch(scene, samples=180)
"""

from ._model import attenuation_h as attenuation_h
from ._model import cone_depth_range as cone_depth_range
from ._model import cone_interval as cone_interval
from ._model import light_reach as light_reach
from ._model import phase as phase
from ._model import phase_cos as phase_cos
from ._planes import render_planes as render_planes
from ._planes import shadow_maps as shadow_maps
from ._raymarch import raymarch_scattering as raymarch_scattering
from ._raymarch import render_raymarch as render_raymarch
from ._scene import Medium as Medium
from ._scene import RenderSettings as RenderSettings
from ._scene import ShaftsScene as ShaftsScene

"""Takigi Noh (paper 004, section 4): a draped Noh costume by firelight under a dusk sky.

Scene (metres, y up, the stage floor at y = 0): a garment hung from two shoulder points
(`sims.drape_cloth`, Verlet mass-spring) in front of the camera; a hinoki stage floor
(|x| < 3, -3 < z < 2.5) inside white gravel; four bonfires around the stage, each a flame quad whose
emission texture is the current frame of `sims.fire_frames`; the environment: a procedural
dusk sky (`jaxrender.sky.sky_envmap`, sun 2 degrees above the horizon) or any user EXR (lat-long,
Mitsuba `envmap` orientation).

Materials (paper Fig. 7): a mask over the garment's uv assigns each region a BTF: by the mask's
8-bit colour, gold (255, 255, 0) = `brocade` (kinran), green (0, 255, 0) = `hexagon`
(tortoise-shell kikko weave), cyan (0, 255, 255) = `satin` (the underlayer); any other colour is
the plain `pattern` weave whose rho_d is that colour (sRGB-decoded). BTFs are pyramids of 1- or
2-lobe levels (`jaxrender.fabric`), repeated `tiles` times across the garment.

Lighting per frame (eqs. 2-4): I = I_static + I_dynamic. I_static: K environment directions
drawn once per sequence by luminance x sin(theta) (`jaxrender.lights.sample_envmap`), blocked
below the horizon by the ground. I_dynamic: K_f points drawn over all four flame quads by emitted
power for the frame (`jaxrender.lights.sample_quad_lights`), shared by all shading points;
flames are volumes, so each flame quad is treated as facing the shading point (|cos_y| = 1)
while its texture gives the radiance; each fire's visibility at a point is PCSS
(`jaxrender.shadows.pcss`) over a 512^2 depth map of the garment rendered from the fire
(`jaxrender.fabric.depth_map`, SHAFTS's ShadowMap format), light size = the flame's width.
The geometry, the environment samples, the shadows and I_static are computed once per sequence
(`prepare_noh`); a frame (`noh_frame`) is the firelight, the visible flames and compositing.

Modules, one job each: `mask` (labels from the mask's colours), `materials` (procedural BTFs and
their EM pyramids), `environment` (the dusk sky), `scene` (cloth, fires, assembly), `shading`
(surface points and their shading), `prepare` (the per-sequence part), `frame` (one frame),
`animation` (the frame loop, tone mapping, PNG/EXR/GIF).
Visible flames are added to the image (additive, in front of whatever lies behind them).
"""

from .animation import render_noh as render_noh
from .animation import tonemap_frames as tonemap_frames
from .animation import write_animation as write_animation
from .environment import default_environment as default_environment
from .frame import noh_frame as noh_frame
from .frame import noh_frame_jit as noh_frame_jit
from .mask import LABELS as LABELS
from .mask import PALETTE as PALETTE
from .mask import default_mask as default_mask
from .mask import mask_from_rgb as mask_from_rgb
from .materials import btf_levels_from_channels as btf_levels_from_channels
from .materials import default_btfs as default_btfs
from .materials import procedural_btf as procedural_btf
from .prepare import NohPrepared as NohPrepared
from .prepare import prepare_noh as prepare_noh
from .scene import NohScene as NohScene
from .scene import noh_scene as noh_scene

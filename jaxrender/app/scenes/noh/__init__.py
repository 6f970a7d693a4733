"""Takigi Noh (paper 004, section 4): a costumed performer driven by motion capture on a Noh
stage at dusk between four bonfires, the woven costume in the firelight, the polished floor
reflecting it. How the scene is built and rendered: docs/noh.md.

Modules, one job each: `stage` (the stage's quads, ray cast), `performer` (the performer's mesh:
robe, body, mask), `mask` (the robe's labels), `materials` (procedural BTFs and their EM
pyramids), `environment` (the dusk sky), `scene` (assembly), `shading` (points and their
shading), `rig` (the sequence's constant part), `motion` (one frame, the sequence loop),
`animation` (rendering, tone mapping, PNG/EXR/GIF/MP4, OBJ meshes).
"""

from .animation import render_noh as render_noh
from .animation import tonemap_frames as tonemap_frames
from .animation import write_animation as write_animation
from .animation import write_meshes as write_meshes
from .environment import default_environment as default_environment
from .mask import LABELS as LABELS
from .mask import PALETTE as PALETTE
from .mask import default_mask as default_mask
from .mask import mask_from_rgb as mask_from_rgb
from .materials import btf_levels_from_channels as btf_levels_from_channels
from .materials import default_btfs as default_btfs
from .materials import procedural_btf as procedural_btf
from .motion import noh_frame as noh_frame
from .motion import noh_frame_jit as noh_frame_jit
from .motion import render_sequence as render_sequence
from .performer import ExportedMesh as ExportedMesh
from .performer import exported_meshes as exported_meshes
from .rig import NohRig as NohRig
from .rig import prepare_rig as prepare_rig
from .scene import NohScene as NohScene
from .scene import noh_scene as noh_scene
from .scene import stage_motion as stage_motion

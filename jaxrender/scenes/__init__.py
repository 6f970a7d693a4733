"""Scene files and the showcase scenes (stage, desert, Noh) used by the gallery and the CLIs."""

from ._shafts_scene import RENDER_DEFAULTS as RENDER_DEFAULTS
from ._shafts_scene import ShaftsSceneWarning as ShaftsSceneWarning
from ._shafts_scene import load_shafts_scene as load_shafts_scene
from ._shafts_scene import shafts_scene_from_dict as shafts_scene_from_dict
from .noh import render_noh as render_noh
from .desert import desert_frame as desert_frame
from .desert import desert_scene as desert_scene
from .desert import render_desert as render_desert
from .stage import load_stage_scene as load_stage_scene
from .stage import stage_scene_dict as stage_scene_dict

"""Scene files and the showcase scenes (stage, desert, Noh) used by the gallery and the CLIs."""

from .desert import desert_frame as desert_frame
from .desert import desert_scene as desert_scene
from .desert import render_desert as render_desert
from .noh import render_noh as render_noh
from .shafts_file import RENDER_DEFAULTS as RENDER_DEFAULTS
from .shafts_file import ShaftsSceneWarning as ShaftsSceneWarning
from .shafts_file import check_image_size as check_image_size
from .shafts_file import load_shafts_scene as load_shafts_scene
from .shafts_file import shafts_scene_from_dict as shafts_scene_from_dict
from .stage import load_stage_scene as load_stage_scene
from .stage import stage_scene_dict as stage_scene_dict

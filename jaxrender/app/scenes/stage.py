"""The showcase stage (paper 000, Fig. 7): five spot lights in fog, two with polka-dot light maps,
spheres on a floor in front of a back wall.

`stage_scene_dict()` is the built-in scene (design.md's scene-file format; light maps are the
PNGs shipped in `jaxrender/data/`) and `load_stage_scene()` builds it (the gallery renders it:
`jaxrender.app.gallery.stage`). `ground_fog(time)` is the stage's drifting ground fog:
a density grid over the stage floor whose pattern moves with `time`; `with_ground_fog(scene,
time)` puts it into a loaded stage (same shapes every frame: one compilation for an animation).
"""

from __future__ import annotations

import copy
from pathlib import Path

import equinox as eqx
import numpy as np

from jaxrender.shafts import DensityGrid, Medium

from .shafts_file import shafts_scene_from_dict

DATA = Path(__file__).resolve().parents[2] / "data"

_STAGE = {
    "camera": {"eye": [0.0, 2.2, 8.5], "target": [0.0, 1.6, 0.0], "up": [0, 1, 0], "fov_y_deg": 45,
               "width": 720, "height": 480},
    "medium": {"rho": 1.0, "kappa": 0.08, "K": 0.003},
    "render": {"shadow_map": 1024, "shadow_bias": 0.002, "table_size": 256, "s_min": 0.5, "s_max": 14.0,
               "t_max": 16.0, "display_white": 1.0},
    "spotlights": [
        {"position": [-3.6, 7.2, 0.5], "target": [-1.2, 0.0, -0.5], "up": [0, 0, 1], "cutoff_deg": 18,
         "beam_width_deg": 12, "intensity": [150, 100, 50], "light_map": "polka_dots.png"},
        {"position": [3.6, 7.2, 0.5], "target": [1.3, 0.0, 0.3], "up": [0, 0, 1], "cutoff_deg": 18,
         "beam_width_deg": 12, "intensity": [50, 90, 165], "light_map": "polka_small.png"},
        {"position": [0.0, 7.5, 1.0], "target": [0.0, 0.0, -1.8], "up": [0, 0, 1], "cutoff_deg": 14,
         "beam_width_deg": 10, "intensity": [180, 180, 165]},
        {"position": [-1.8, 7.6, -2.8], "target": [1.8, 0.0, -1.0], "up": [0, 0, 1], "cutoff_deg": 12,
         "beam_width_deg": 8, "intensity": [170, 50, 100]},
        {"position": [1.9, 7.6, -2.8], "target": [-2.0, 0.0, -1.2], "up": [0, 0, 1], "cutoff_deg": 12,
         "beam_width_deg": 8, "intensity": [70, 170, 85]},
    ],
    "objects": [
        {"type": "quad", "center": [0, 0, -1], "u": [5.5, 0, 0], "v": [0, 0, -3.5], "albedo": [0.45, 0.42, 0.4]},
        {"type": "quad", "center": [0, 3, -4.5], "u": [5.5, 0, 0], "v": [0, 3, 0], "albedo": [0.3, 0.3, 0.35]},
        {"type": "sphere", "center": [-1.2, 0.6, -0.5], "radius": 0.6, "albedo": [0.8, 0.75, 0.7]},
        {"type": "sphere", "center": [1.3, 0.45, 0.3], "radius": 0.45, "albedo": [0.7, 0.8, 0.75]},
        {"type": "sphere", "center": [0.0, 1.0, -1.8], "radius": 1.0, "albedo": [0.85, 0.85, 0.85]},
    ],
}


def stage_scene_dict() -> dict:
    """A fresh copy of the built-in stage scene (light maps relative to `jaxrender/data/`)."""
    return copy.deepcopy(_STAGE)


def load_stage_scene(*, width: int | None = None, height: int | None = None):
    """The stage as a `ShaftsScene`, optionally at another image size."""
    scene = shafts_scene_from_dict(stage_scene_dict(), base_dir=DATA, source="<built-in stage>")
    return scene.with_size(width, height) if (width or height) else scene


GROUND_FOG_BOX = ((-6.5, -0.05, -5.0), (6.5, 3.0, 3.2))  # the stage floor's fog bank (eye and lights above/outside)
GROUND_FOG_SHAPE = (16, 12, 32)  # (nz, ny, nx)


def ground_fog(time: float = 0.0, shape: tuple[int, int, int] = GROUND_FOG_SHAPE) -> np.ndarray:
    """Ground fog on GROUND_FOG_BOX, values (nz, ny, nx): a dense layer at the floor (~16) thinning
    upward (an e-folding height of ~0.65 m, and to 0 at the box's top, so the box has no visible
    lid) with rolling swells; `time` (in loop periods: 1.0 comes back to
    0.0) drifts the swells across the stage."""
    nz, ny, nx = shape
    z, y, x = np.meshgrid(*((np.arange(n) + 0.5) / n for n in shape), indexing="ij")
    phase = 2.0 * np.pi * time
    swell = (np.sin(2 * np.pi * (2.0 * x + 0.5 * z) - phase) + 0.6 * np.sin(2 * np.pi * (3.0 * x - 1.5 * z) - 2 * phase)
             + 0.4 * np.cos(2 * np.pi * (1.0 * x + 2.0 * z) + phase))
    height = 0.22 * (1.0 + 0.35 * swell / 2.0)  # the fog top, in box heights, rises and falls with the swells
    d = 16.0 * np.exp(-y / height) * (0.8 + 0.2 * np.cos(2 * np.pi * 3 * z + phase)) * (1.0 - y) ** 2
    return np.clip(d, 0.0, None)


def with_ground_fog(scene, time: float = 0.0, *, shape: tuple[int, int, int] = GROUND_FOG_SHAPE):
    """`scene` (the stage) with its medium's density replaced by `ground_fog(time)` (rho, kappa
    and K kept: the fog is denser than the stage's haze near the floor and absent above the box)."""
    grid = DensityGrid(ground_fog(time, shape), *GROUND_FOG_BOX)
    medium = scene.medium
    return eqx.tree_at(lambda s: s.medium, scene, Medium(medium.rho, medium.kappa, medium.K, grid))

"""The showcase stage (paper 000, Fig. 7): five spot lights in fog, two with polka-dot light maps,
spheres on a floor in front of a back wall.

`stage_scene_dict()` is the built-in scene (design.md's scene-file format; light maps are the
PNGs shipped in `jaxrender/data/`), `load_stage_scene()` builds it, and `gallery_section()`
renders it for the gallery with the sample-plane method, plus a ray-marched comparison.
"""

from __future__ import annotations

import copy
import time
from pathlib import Path

import jax
import numpy as np

from ..io import write_exr, write_image
from ..shafts import render_planes, render_raymarch
from ._shafts_scene import shafts_scene_from_dict

DATA = Path(__file__).resolve().parents[1] / "data"

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


def _timed(fn, scene, repeats):
    start = time.perf_counter()
    image = jax.block_until_ready(fn(scene))
    compile_s = time.perf_counter() - start
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(scene))
        runs.append(time.perf_counter() - start)
    return np.asarray(image, dtype=np.float32), compile_s, float(np.median(runs))


def gallery_section(out_dir: Path, *, quick: bool = False) -> list[dict]:
    """Render the stage (planes 30 x 6, float and 8-bit) and a ray-marched comparison."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    width, height = (240, 160) if quick else (720, 480)
    samples = 48 if quick else 180
    repeats = 1 if quick else 3
    scene = load_stage_scene(width=width, height=height)
    planes = jax.jit(lambda s: render_planes(s, planes=30, subplanes=6))
    img, c_p, t_p = _timed(planes, scene, repeats)
    if not quick:  # quick (tests): one compile fewer
        planes8 = jax.jit(lambda s: render_planes(s, planes=30, subplanes=6, quantize_bits=8))
        img8, c_8, t_8 = _timed(planes8, scene, repeats)
    march = jax.jit(lambda s: render_raymarch(s, samples=samples, batch_size=128))
    ref, c_r, t_r = _timed(march, scene, 1 if quick else 2)
    rel = float(np.linalg.norm(img - ref) / np.linalg.norm(ref))
    outputs = [("stage_planes", img), ("stage_raymarch", ref)] + ([] if quick else [("stage_planes_8bit", img8)])
    for name, image in outputs:
        write_image(out_dir / f"{name}.png", image, exposure=2.0)
        write_exr(out_dir / f"{name}.exr", image)
    params = {"size": f"{width}x{height}", "lights": len(scene.lights), "planes": 30, "subplanes": 6,
              "mesh": "15x10", "raymarch_samples": samples, "rho": 1.0, "kappa": 0.08, "K": 0.003}
    entries = [
        {"title": "Stage, five spot lights (sample planes 30 x 6, float)", "images": ["stage_planes.png"],
         "caption": "Paper 000 Fig. 7: five spot lights, two with polka-dot light maps, shadow shafts behind "
                    "the spheres. Sample planes with sub-sample planes, tables of F and h, 15x10 mesh.",
         "params": params, "timings": {"compile_s": c_p, "frame_s": t_p, "per_light_s": t_p / len(scene.lights)}},
        {"title": f"Ray-marched reference ({samples} samples, shadow rays)", "images": ["stage_raymarch.png"],
         "caption": f"The conventional method: relative RMS difference of the plane image to it {100 * rel:.1f} %.",
         "params": params, "timings": {"compile_s": c_r, "frame_s": t_r}},
    ]
    if not quick:
        rms8 = float(np.sqrt(np.mean((img8 - np.clip(img, 0, 1)) ** 2)) * 255)
        entries.insert(1, {"title": "Same, 8-bit hardware emulation", "images": ["stage_planes_8bit.png"],
                           "caption": "Tables, light maps and frame buffer in 8-bit steps; RMS difference to float "
                                      f"{rms8:.2f} of 255 levels. Faint fog far from the lights adds less than half an 8-bit "
                                      "step per sample plane and so vanishes from the frame buffer, as on the paper's "
                                      "hardware: the shafts fade sooner than in the float image.",
                           "params": {**params, "quantize_bits": 8}, "timings": {"compile_s": c_8, "frame_s": t_8}})
    return entries

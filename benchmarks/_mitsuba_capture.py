"""An object no setting of the fit was chosen on: a multi-light capture rendered by Mitsuba 3
(`scalar_rgb`, path tracing), with its true normals.

Two spheres on a ground plane, seen from above by an orthographic camera (image x along world x,
image rows up along world y: the capture frame), lit in turn by distant lights within 50 deg of
the view (a golden-angle spiral, as a rig's LEDs spread). It has what the DiLiGenT objects have
and the fit's model has not: cast shadows (spheres on the plane), inter-reflections (path depth 4:
plane and spheres light each other), a glossy anisotropic metal blended over a diffuse base
(Mitsuba's `roughconductor` with alpha_u != alpha_v on one sphere, along its longitude), a
glossy plastic (`roughplastic`, GGX) on the other, a rough plastic ground. True normals: Mitsuba's
shading normals (`aov` integrator, `nn:sh_normal`), averaged over each pixel like the radiance.

    render_capture(out_dir)   # OUT_DIR/capture.json, images/NNN.exr, mask.png, normals.npy

Observation = pi x radiance under unit irradiance: each light's `intensity` in capture.json is
1/pi, so that a white Lambertian plane lit at normal incidence observes 1.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import mitsuba as mi
import numpy as np

from jaxrender.io import write_exr, write_png

SIZE = 128
LIGHTS = 96
SPP = 32
MAX_THETA_DEG = 50.0
DEPTH = 4


def light_directions(n: int = LIGHTS, max_theta_deg: float = MAX_THETA_DEG) -> np.ndarray:
    """`n` unit vectors toward the lights, a golden-angle spiral of equal solid angle within the cone."""
    i = np.arange(n) + 0.5
    cos_t = 1.0 - (1.0 - math.cos(math.radians(max_theta_deg))) * i / n
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    sin_t = np.sqrt(1.0 - cos_t**2)
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], -1)


def _scene(mi, light, integrator, size, spp, seed):
    transform = mi.ScalarTransform4f
    rgb = lambda v: {"type": "rgb", "value": v}  # noqa: E731
    return {
        "type": "scene", "integrator": integrator,
        "sensor": {"type": "orthographic",
                   "to_world": transform().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0])
                   @ transform().scale([1.05, 1.05, 1]),
                   "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"},
                            "pixel_format": "rgb"},
                   "sampler": {"type": "independent", "sample_count": spp, "seed": seed}},
        "ground": {"type": "rectangle", "to_world": transform().scale([1.3, 1.3, 1]),
                   "bsdf": {"type": "roughplastic", "alpha": 0.35, "diffuse_reflectance": rgb([0.42, 0.38, 0.32])}},
        "metal": {"type": "sphere", "center": [-0.42, 0.28, 0.45], "radius": 0.45,
                  "bsdf": {"type": "blendbsdf", "weight": 0.35,
                           "bsdf_0": {"type": "diffuse", "reflectance": rgb([0.55, 0.25, 0.12])},
                           "bsdf_1": {"type": "roughconductor", "material": "Au", "distribution": "ggx",
                                      "alpha_u": 0.06, "alpha_v": 0.25}}},
        "plastic": {"type": "sphere", "center": [0.5, -0.35, 0.32], "radius": 0.32,
                    "bsdf": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.12,
                             "diffuse_reflectance": rgb([0.15, 0.3, 0.55])}},
        "light": {"type": "directional", "direction": (-np.asarray(light, float)).tolist(),
                  "irradiance": rgb([1.0, 1.0, 1.0])},
    }


def render_capture(out_dir: str | Path, *, size: int = SIZE, lights: int = LIGHTS, spp: int = SPP,
                   progress: bool = False) -> Path:
    """Render the capture into `out_dir` (module docstring); returns it."""
    mi.set_variant("scalar_rgb")
    out = Path(out_dir)
    (out / "images").mkdir(parents=True, exist_ok=True)
    dirs = light_directions(lights)
    normals = np.asarray(mi.render(mi.load_dict(_scene(mi, dirs[0], {"type": "aov", "aovs": "nn:sh_normal"},
                                                       size, spp, 0))), np.float64)
    normals /= np.maximum(np.linalg.norm(normals, axis=-1, keepdims=True), 1e-12)
    np.save(out / "normals.npy", normals)
    write_png(out / "mask.png", np.ones((size, size), np.float32), srgb=False)
    entries = []
    for i, d in enumerate(dirs):
        image = np.asarray(mi.render(mi.load_dict(_scene(mi, d, {"type": "path", "max_depth": DEPTH}, size, spp,
                                                         i + 1))), np.float32)
        name = f"images/{i:03d}.exr"
        write_exr(out / name, {"R": image[..., 0], "G": image[..., 1], "B": image[..., 2]})
        entries.append({"direction": [round(float(x), 9) for x in d], "intensity": 1.0 / math.pi, "images": [name]})
        if progress:
            print(f"\rmitsuba capture: light {i + 1}/{len(dirs)}", end="", flush=True)
    if progress:
        print()
    manifest = {"format": "jaxrender-capture", "version": 1, "size": [size, size], "response": "linear",
                "exposures_s": [1.0], "view": {"direction": [0.0, 0.0, 1.0]}, "mask": "mask.png",
                "source": f"Mitsuba 3 scalar_rgb render, {spp} spp, path depth {DEPTH} "
                          "(benchmarks/_mitsuba_capture.py)",
                "lights": entries}
    (out / "capture.json").write_text(json.dumps(manifest, indent=1))
    return out

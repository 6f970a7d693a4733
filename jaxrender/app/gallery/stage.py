"""Gallery section of the stage (paper 000, Fig. 7): the float image by the default (adaptive)
method, the paper's 8-bit sample planes, the ray march at the sample count where it reaches
about 2 % relative RMS on this stage, and the stage in drifting ground fog (a density
grid that moves between the frames of an animated GIF)."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import imageio.v3 as iio
import jax
import numpy as np

from jaxrender.io import atomic_path, tonemap, write_exr, write_image
from jaxrender.shafts import render_adaptive, render_planes, render_raymarch
from jaxrender.timing import time_calls

from ..scenes.stage import GROUND_FOG_BOX, GROUND_FOG_SHAPE, load_stage_scene, with_ground_fog

STAGE_SAMPLES = 16  # the default method's count reaching ~1.7 % on the stage (benchmarks/shafts_interactive.py)
RAYMARCH_SAMPLES = 24  # the ray march's count reaching ~2 % on the stage (1.6 % at 360x240, same benchmark)
FOG_FRAMES = 16  # one loop of the ground fog's drift
FOG_SAMPLES = 24  # the stage in ground fog: the grid adds variation along the rays, so more samples than the stage
EXPOSURE = 2.0


def _timed(fn, scene, repeats):
    image, timing = time_calls(lambda: fn(scene), repeats)
    return np.asarray(image, dtype=np.float32), timing.compile_s, timing.median_s


def _fog_animation(out_dir: Path, scene, frames: int) -> tuple[list[str], dict]:
    """Render the stage in ground fog drifting through one loop: stage_fog_NNN.png/.exr and an
    animated stage_fog.gif (the PNGs' tone mapping); the grid changes, the shapes do not (one
    compilation)."""
    fn = jax.jit(lambda s: render_adaptive(s, samples=FOG_SAMPLES))
    images, seconds = [], []
    for i in range(frames):
        foggy = with_ground_fog(scene, i / frames)
        start = time.perf_counter()
        images.append(np.asarray(jax.block_until_ready(fn(foggy)), dtype=np.float32))
        seconds.append(time.perf_counter() - start)
    compile_s, times = seconds[0], seconds[1:]  # the first frame compiles
    names = []
    for i, image in enumerate(images):
        write_image(out_dir / f"stage_fog_{i:03d}.png", image, exposure=EXPOSURE)
        write_exr(out_dir / f"stage_fog_{i:03d}.exr", image)
        names.append(f"stage_fog_{i:03d}.png")
    shown = [(np.clip(np.asarray(tonemap(im, exposure=EXPOSURE)), 0, 1) * 255 + 0.5).astype(np.uint8) for im in images]
    with atomic_path(out_dir / "stage_fog.gif") as tmp:
        iio.imwrite(tmp, np.stack(shown), extension=".gif", duration=1000.0 / 8, loop=0)
    timings = {"compile_s": compile_s, "frame_s": float(np.median(times)) if times else compile_s,
               "frames_s": compile_s + sum(times)}
    return ["stage_fog.gif", names[0]], timings


def gallery_section(out_dir: Path, *, quick: bool = False) -> Iterator[dict]:
    """Render the stage: the default method (float), planes 30 x 6 in 8-bit, a ray-marched comparison and
    the stage in drifting ground fog; each entry is yielded once its files are written."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    width, height = (240, 160) if quick else (720, 480)
    scene = load_stage_scene(width=width, height=height)
    params = {"size": f"{width}x{height}", "lights": len(scene.lights), "rho": 1.0, "kappa": 0.08, "K": 0.003}
    fast = jax.jit(lambda s: render_adaptive(s, samples=STAGE_SAMPLES))
    img, c_e, t_e = _timed(fast, scene, 1 if quick else 3)  # the default method's frame: median of 3
    _write(out_dir, "stage", img)
    yield {"title": f"Stage, five spot lights (the default adaptive method, {STAGE_SAMPLES} samples, float)",
           "images": ["stage.png"],
           "caption": "Paper 000 Fig. 7: five spot lights, two with polka-dot light maps, shadow shafts behind the "
                      "spheres. The default method: samples equally spaced in the angle seen from each light (no "
                      "1/s^2 peak), the in-scattering on a coarse grid of cells refined where it changes fast or "
                      "the depth jumps, surfaces per pixel; light maps fetched from their mip level.",
           "params": {**params, "method": "adaptive", "samples": STAGE_SAMPLES},
           "timings": {"compile_s": c_e, "frame_s": t_e, "per_light_s": t_e / len(scene.lights)}}
    # the two comparisons are timed by one frame each: at 3.4 and 5 s of CPU a frame, more repeats
    # would double the section's time for a figure benchmarks/shafts_interactive.py measures anyway
    if not quick:  # quick (tests): one compile fewer
        planes8 = jax.jit(lambda s: render_planes(s, planes=30, subplanes=6, quantize_bits=8))
        img8, c_8, t_8 = _timed(planes8, scene, 1)
        _write(out_dir, "stage_planes_8bit", img8)
        rms8 = float(np.sqrt(np.mean((img8 - np.clip(img, 0, 1)) ** 2)) * 255)
        yield {"title": "The paper's method: sample planes 30 x 6, 8-bit hardware emulation",
               "images": ["stage_planes_8bit.png"],
               "caption": "Sample planes with sub-sample planes, tables of F and h on a 15x10 mesh; tables, light maps "
                          "and frame buffer in 8-bit steps; RMS difference to the float image "
                          f"{rms8:.2f} of 255 levels. Faint fog far from the lights adds less than half an 8-bit step "
                          "per sample plane and so vanishes from the frame buffer, as on the paper's hardware: the "
                          "shafts fade sooner than in the float image.",
               "params": {**params, "method": "planes", "planes": 30, "subplanes": 6, "mesh": "15x10",
                          "quantize_bits": 8},
               "timings": {"compile_s": c_8, "frame_s": t_8}}
    march = jax.jit(lambda s: render_raymarch(s, samples=RAYMARCH_SAMPLES, batch_size=128))
    ref, c_r, t_r = _timed(march, scene, 1)
    _write(out_dir, "stage_raymarch", ref)
    rel = float(np.linalg.norm(img - ref) / np.linalg.norm(ref))
    yield {"title": f"Ray-marched reference ({RAYMARCH_SAMPLES} samples, shadow rays)",
           "images": ["stage_raymarch.png"],
           "caption": "The conventional method at the sample count where it reaches about 2 % on this stage: "
                      f"relative RMS difference of the default method's image to it {100 * rel:.1f} %.",
           "params": {**params, "method": "raymarch", "samples": RAYMARCH_SAMPLES},
           "timings": {"compile_s": c_r, "frame_s": t_r}}
    fog_frames = 3 if quick else FOG_FRAMES
    fog_images, fog_timings = _fog_animation(out_dir, scene, fog_frames)
    yield {"title": f"Stage in drifting ground fog (density grid, {fog_frames} frames, adaptive)",
           "images": fog_images,
           "caption": ("Fog whose density varies in space. A grid of "
                       f"{GROUND_FOG_SHAPE[2]} x {GROUND_FOG_SHAPE[1]} x {GROUND_FOG_SHAPE[0]} voxels over the stage "
                       "floor, dense at the floor and thinning upward, its rolling swells drifting across the stage "
                       "through one loop. The beams light the fog bank and the spheres' shadow shafts cross it. "
                       "Every frame the grid moves and the same compiled frame renders it: the light's transmittance "
                       "through the grid comes from optical-depth volumes seen from each light and from the eye."),
           "params": {**params, "method": "adaptive", "samples": FOG_SAMPLES, "grid": "x".join(
               str(n) for n in GROUND_FOG_SHAPE[::-1]), "box": f"{GROUND_FOG_BOX[0]} - {GROUND_FOG_BOX[1]}",
               "frames": fog_frames},
           "timings": fog_timings}


def _write(out_dir: Path, name: str, image) -> None:
    write_image(out_dir / f"{name}.png", image, exposure=EXPOSURE)
    write_exr(out_dir / f"{name}.exr", image)

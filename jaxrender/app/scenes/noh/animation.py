"""The Noh animation: the scene assembled, its frames rendered one jitted call each
(`render_noh`), tone mapped with one exposure for the whole sequence, and written as PNG + EXR
frames, an animated GIF and an H.264 MP4 (`write_animation`); the performer's meshes as OBJ
(`write_meshes`)."""

from __future__ import annotations

import os
import time
import warnings
from pathlib import Path

import imageio.v3 as iio
import jax
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from jaxrender.brdf import BTFTexel
from jaxrender.io import BVHMotion, atomic_path, linear_to_srgb, luminance, tonemap, write_exr, write_obj, write_png
from jaxrender.lights import EnvMap

from .motion import render_sequence
from .performer import ExportedMesh, exported_meshes, performer_mesh
from .scene import noh_scene

EXPOSURE_KEY = 0.16   # the performer's 90th-percentile luminance on screen: a night lit by fires


def render_noh(*, frames: int = 60, width: int = 720, height: int = 480, key: PRNGKeyArray | None = None,
               mask_rgb: np.ndarray | None = None, btfs: dict[str, list[BTFTexel]] | None = None,
               env: EnvMap | None = None, motion: BVHMotion | None = None, motion_source=None, k_env: int = 20,
               k_fire: int = 20, progress=None, info: dict | None = None, time_repeats: int = 0,
               shadow_resolution: int = 512, frame_dt: float = 0.1, meshes: list | None = None,
               **scene_kwargs) -> Float[Array, "F H W 3"]:
    """The animation: `frames` linear-radiance frames H x W x 3 (float32), `frame_dt` s apart, of
    the performer dancing `motion` (a BVH motion; default: the built-in `sims.noh_dance`).

    `progress(1)` is called after each frame; `info` (a dict) receives `prepare_s` (scene, robe
    and the sequence's constant part), `compile_s` (the first frame, including compilation),
    `frame_s` (a list, later frames), `recompiles` and `exposure` (for `tonemap_frames`: the
    performer's 90th-percentile luminance in frame 0 -> `EXPOSURE_KEY`). `time_repeats` = N: afterwards N
    more frames of the dance (discarded) timed into `info["timed_s"]`. `meshes` (a list) receives
    each frame's (body, robe) `ExportedMesh` as rendered (`write_meshes`).
    """
    key = jax.random.key(2024) if key is None else key
    k_scene, k_rest = jax.random.split(key)
    t0 = time.perf_counter()
    scene = noh_scene(width=width, height=height, frames=min(frames, 20), key=k_scene, mask_rgb=mask_rgb, btfs=btfs,
                      env=env, motion=motion, motion_source=motion_source,
                      duration=(frames + time_repeats) * frame_dt, **scene_kwargs)
    scene_s = time.perf_counter() - t0
    details: dict = {}
    states = None if meshes is None else []
    out, _ = render_sequence(scene, frames=frames, key=k_rest, k_env=k_env, k_fire=k_fire, frame_dt=frame_dt,
                             shadow_resolution=shadow_resolution, progress=progress, time_repeats=time_repeats,
                             info=details, states=states)
    if meshes is not None:
        meshes.extend(exported_meshes(performer_mesh(scene.performer, s), scene.performer) for s in states)
    if info is not None:
        mask = details.pop("performer_mask").reshape(-1)
        lum = np.asarray(luminance(out[0].reshape(-1, 3)[mask]))
        info.update(details, prepare_s=scene_s + details["prepare_s"],
                    exposure=EXPOSURE_KEY / max(float(np.percentile(lum, 90)) if lum.size else 1.0, 1e-6))
    return np.stack(out)


def tonemap_frames(frames: np.ndarray, *, exposure: float | None = None, key_value: float = 0.6) -> np.ndarray:
    """Display-referred (linear, for `write_png`'s sRGB encoding) frames: one exposure for the
    sequence (given, or the 90th percentile luminance of frame 0 -> `key_value`), then the
    `jaxrender.io.tonemap` curve."""
    if exposure is None:
        exposure = key_value / max(float(np.percentile(np.asarray(luminance(frames[0])), 90)), 1e-6)
    return np.stack([np.asarray(tonemap(f, exposure=exposure)) for f in frames])


def write_animation(out_dir: str | os.PathLike, frames: np.ndarray, *, name: str = "noh", fps: float = 10.0,
                    exposure: float | None = None, video: bool = True) -> list[Path]:
    """frame_NNN.png (tone mapped) + frame_NNN.exr (linear) + NAME.gif + NAME.mp4 (H.264 through
    imageio-ffmpeg, when `video`); atomic per file."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    shown = tonemap_frames(frames, exposure=exposure)
    paths = []
    for i, (lin, disp) in enumerate(zip(frames, shown)):
        paths.append(write_png(out_dir / f"frame_{i:03d}.png", disp))
        paths.append(write_exr(out_dir / f"frame_{i:03d}.exr", lin))
    rgb8 = (np.clip(np.asarray(linear_to_srgb(shown)), 0, 1) * 255 + 0.5).astype(np.uint8)
    with atomic_path(out_dir / f"{name}.gif") as tmp:
        iio.imwrite(tmp, rgb8, extension=".gif", duration=1000.0 / fps, loop=0)
    paths.append(out_dir / f"{name}.gif")
    if video:
        # H.264 in yuv420p needs even sides: pad by one edge row / column if odd
        h, w = rgb8.shape[1], rgb8.shape[2]
        even = np.pad(rgb8, ((0, 0), (0, h % 2), (0, w % 2), (0, 0)), mode="edge")
        with atomic_path(out_dir / f"{name}.mp4") as tmp, warnings.catch_warnings():
            # imageio-ffmpeg starts ffmpeg by fork + exec, which JAX warns about (harmless: exec follows)
            warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
            iio.imwrite(tmp, even, plugin="FFMPEG", fps=fps, codec="libx264", macro_block_size=1, quality=8)
        paths.append(out_dir / f"{name}.mp4")
    return paths


def write_meshes(out_dir: str | os.PathLike, meshes: list[tuple[ExportedMesh, ExportedMesh]]) -> list[Path]:
    """meshes/frame_NNN_body.obj and meshes/frame_NNN_robe.obj of each frame's (body, robe): world
    space, metres, y up, with the texture's coordinates (docs/noh.md, "Meshes")."""
    folder = Path(out_dir) / "meshes"
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, parts in enumerate(meshes):
        for part, m in zip(("body", "robe"), parts):
            paths.append(write_obj(folder / f"frame_{i:03d}_{part}.obj", m.vertices, m.triangles, uv=m.uv,
                                   uv_triangles=m.uv_triangles, name=f"{part}_{i:03d}"))
    return paths

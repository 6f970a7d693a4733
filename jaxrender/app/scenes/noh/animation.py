"""The Noh animation: a sequence of frames rendered one jitted call each (`render_noh`: the
moving garment of `.motion` by default, or the static drape), tone mapped with one exposure for
the whole sequence, and written as PNG + EXR frames and a GIF."""

from __future__ import annotations

import os
import time
from pathlib import Path

import imageio.v3 as iio
import jax
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray

from jaxrender.brdf import BTFTexel
from jaxrender.io import atomic_path, linear_to_srgb, luminance, tonemap, write_exr, write_png
from jaxrender.lights import EnvMap
from jaxrender.timing import time_calls, timed_call

from .frame import noh_frame_jit
from .motion import render_moving_noh
from .prepare import prepare_noh
from .scene import garment_rig, noh_scene


def render_noh(*, frames: int = 20, width: int = 720, height: int = 480, key: PRNGKeyArray | None = None,
               mask_rgb: np.ndarray | None = None, btfs: dict[str, list[BTFTexel]] | None = None,
               env: EnvMap | None = None, k_env: int = 20, k_fire: int = 20, progress=None,
               info: dict | None = None, time_repeats: int = 0, shadow_resolution: int = 512,
               moving: bool = True, frame_dt: float = 0.1, **scene_kwargs) -> Float[Array, "F H W 3"]:
    """The animation: `frames` linear-radiance frames H x W x 3 (float32).

    `progress(1)` is called after each frame; `info` (a dict) receives `prepare_s`, `compile_s`
    (the first frame, including compilation), `frame_s` (a list, later frames) and `exposure`
    (for `tonemap_frames`: the garment's 90th-percentile luminance in frame 0 -> 0.3).
    `time_repeats` = N: afterwards render N more frames (cycling through the sequence, discarded)
    and put their times into `info["timed_s"]` (compiled, `block_until_ready`).
    `moving` (default): the garment dances (`.motion`, frames `frame_dt` s apart) and everything
    that depends on it, shadows and the floor's reflection included, is computed every frame;
    otherwise the static drape with the per-sequence part computed once (`prepare_noh`).
    """
    if moving:
        return _render_moving(frames=frames, width=width, height=height, key=key, mask_rgb=mask_rgb, btfs=btfs,
                              env=env, k_env=k_env, k_fire=k_fire, progress=progress, info=info,
                              time_repeats=time_repeats, shadow_resolution=shadow_resolution, frame_dt=frame_dt,
                              **scene_kwargs)
    key = jax.random.key(2024) if key is None else key
    k_scene, k_env_key, k_frames = jax.random.split(key, 3)
    t0 = time.perf_counter()
    scene = noh_scene(width=width, height=height, frames=frames, key=k_scene, mask_rgb=mask_rgb, btfs=btfs, env=env,
                      **scene_kwargs)
    prep = jax.block_until_ready(prepare_noh(scene, key=k_env_key, k_env=k_env, shadow_resolution=shadow_resolution))
    prepare_s = time.perf_counter() - t0

    def frame(i: int) -> Array:
        return noh_frame_jit(scene, prep, scene.flames[:, i % frames], jax.random.fold_in(k_frames, i), k_fire=k_fire)

    out, seconds = [], []
    for f in range(frames):  # frames are sequential: one jitted call each, the first one compiles
        image, dt = timed_call(lambda f=f: frame(f))
        seconds.append(dt)
        out.append(np.asarray(image, dtype=np.float32))
        if progress is not None:
            progress(1)
    _, timed = time_calls(lambda: frame(frames), time_repeats) if time_repeats else (None, None)
    if info is not None:
        info["timed_s"] = list(timed.runs_s) if timed else []
        lum = np.asarray(luminance(out[0].reshape(-1, 3)[np.asarray(prep.garment.index)]))
        info.update(prepare_s=prepare_s, compile_s=seconds[0], frame_s=seconds[1:],
                    exposure=0.3 / max(float(np.percentile(lum, 90)) if lum.size else 1.0, 1e-6))
    return np.stack(out)


def _render_moving(*, frames, width, height, key, mask_rgb, btfs, env, k_env, k_fire, progress, info, time_repeats,
                   shadow_resolution, frame_dt, cloth_rows: int = 40, cloth_cols: int = 32, **scene_kwargs):
    key = jax.random.key(2024) if key is None else key
    k_scene, k_rest = jax.random.split(key)
    t0 = time.perf_counter()
    scene = noh_scene(width=width, height=height, frames=frames, key=k_scene, mask_rgb=mask_rgb, btfs=btfs, env=env,
                      cloth_rows=cloth_rows, cloth_cols=cloth_cols, **scene_kwargs)
    scene_s = time.perf_counter() - t0
    details: dict = {}
    out, _ = render_moving_noh(scene, garment_rig(cloth_rows, cloth_cols), frames=frames, key=k_rest, k_env=k_env,
                               k_fire=k_fire, frame_dt=frame_dt, shadow_resolution=shadow_resolution,
                               progress=progress, time_repeats=time_repeats, info=details)
    if info is not None:
        mask = details.pop("garment_mask").reshape(-1)
        lum = np.asarray(luminance(out[0].reshape(-1, 3)[mask]))
        info.update(details, prepare_s=scene_s + details["prepare_s"],
                    exposure=0.3 / max(float(np.percentile(lum, 90)) if lum.size else 1.0, 1e-6))
    return np.stack(out)


def tonemap_frames(frames: np.ndarray, *, exposure: float | None = None, key_value: float = 0.6) -> np.ndarray:
    """Display-referred (linear, for `write_png`'s sRGB encoding) frames: one exposure for the
    sequence (given, or the 90th percentile luminance of frame 0 -> `key_value`), then the
    `jaxrender.io.tonemap` curve."""
    if exposure is None:
        exposure = key_value / max(float(np.percentile(np.asarray(luminance(frames[0])), 90)), 1e-6)
    return np.stack([np.asarray(tonemap(f, exposure=exposure)) for f in frames])


def write_animation(out_dir: str | os.PathLike, frames: np.ndarray, *, gif_name: str = "noh.gif",
                    fps: float = 10.0, exposure: float | None = None) -> list[Path]:
    """frame_NNN.png (tone mapped) + frame_NNN.exr (linear) + an animated GIF; atomic per file."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    shown = tonemap_frames(frames, exposure=exposure)
    paths = []
    for i, (lin, disp) in enumerate(zip(frames, shown)):
        paths.append(write_png(out_dir / f"frame_{i:03d}.png", disp))
        paths.append(write_exr(out_dir / f"frame_{i:03d}.exr", lin))
    rgb8 = (np.clip(np.asarray(linear_to_srgb(shown)), 0, 1) * 255 + 0.5).astype(np.uint8)
    with atomic_path(out_dir / gif_name) as tmp:
        iio.imwrite(tmp, rgb8, extension=".gif", duration=1000.0 / fps, loop=0)
    paths.append(out_dir / gif_name)
    return paths

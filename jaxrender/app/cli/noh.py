"""`jaxrender noh`: Takigi Noh (paper 004), a costumed performer on a Noh stage between bonfires,
driven by the built-in dance or a BVH motion; frames + animated GIF + MP4."""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import numpy as np
from tqdm import tqdm

from jaxrender.io import InputError, output_folder, read_btf, read_bvh, read_image
from jaxrender.lights import load_envmap

from ..scenes.noh import LABELS, btf_levels_from_channels, render_noh, write_animation, write_meshes
from .arguments import check_cells, number
from .timed import add_time_argument, print_timing


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, type=Path,
                        help="output directory (frames PNG + EXR, noh.gif, noh.mp4; meshes/ with --meshes)")
    parser.add_argument("--motion", type=Path, help="BVH motion capture to dance (default: the built-in Noh "
                        "motion: kamae, suriashi steps, a slow turn, the sleeve raised and lowered)")
    parser.add_argument("--mask", type=Path, help="RGB label PNG over the robe's uv (docs/noh.md): gold (255,255,0) "
                        "brocade, green (0,255,0) hexagon weave, cyan (0,255,255) satin, any other colour = plain "
                        "weave in that colour (default: built in)")
    parser.add_argument("--btf", action="append", default=[], metavar="LABEL=BTF_DIR",
                        help=f"BTF directory for a label ({', '.join(LABELS)}); repeatable")
    parser.add_argument("--env", type=Path, help="lat-long HDR environment (EXR, Mitsuba envmap orientation; "
                        "default: procedural dusk sky)")
    parser.add_argument("--env-scale", type=number, default=1.0, help="multiplier for --env radiance")
    parser.add_argument("--frames", type=int, default=60, help="number of frames (default 60: the built-in dance)")
    parser.add_argument("--fps", type=number, default=10.0, help="frames per second of the sequence (default 10)")
    parser.add_argument("--width", type=int, default=720)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--seed", type=int, default=2024, help="random seed (fires, light samples)")
    parser.add_argument("--no-video", action="store_true", help="skip the MP4")
    parser.add_argument("--meshes", action="store_true", help="also write each frame's performer as OBJ with uv: "
                        "meshes/frame_NNN_body.obj (body, hands, mask) and meshes/frame_NNN_robe.obj (world space, "
                        "metres, y up)")
    add_time_argument(parser, "render a frame (the dance going on)")


def _load_inputs(args):
    """Validate and load every input before any output is written (InputError on bad input)."""
    if args.frames < 1:
        raise InputError(None, f"--frames must be >= 1, got {args.frames}")
    if not args.fps > 0:
        raise InputError(None, f"--fps must be > 0, got {args.fps}")
    if args.width < 16 or args.height < 16:
        raise InputError(None, f"--width/--height must be >= 16, got {args.width}x{args.height}")
    # peak memory per pixel: 1.2 kB measured between 180 x 120 and 540 x 360, with a margin
    check_cells(f"a {args.width} x {args.height} frame", args.width * args.height, bytes_per_cell=2048)
    if args.out.exists() and not args.out.is_dir():
        raise InputError(args.out, "exists and is not a directory")
    motion = read_bvh(args.motion) if args.motion is not None else None
    mask = None
    if args.mask is not None:
        if args.mask.suffix.lower() != ".png":
            raise InputError(args.mask, "the label mask must be an 8-bit RGB PNG")
        raw = read_image(args.mask, srgb=False)
        if raw.ndim != 3 or raw.shape[-1] < 3:
            raise InputError(args.mask, f"the label mask must be RGB, got shape {raw.shape}")
        mask = np.clip(np.round(raw[..., :3] * 255), 0, 255).astype(np.uint8)
    btfs = {}
    for spec in args.btf:
        if "=" not in spec:
            raise InputError(None, f"--btf {spec!r}: expected LABEL=BTF_DIR")
        label, path = spec.split("=", 1)
        if label not in LABELS:
            raise InputError(None, f"--btf {spec!r}: unknown label {label!r} (use one of {', '.join(LABELS)})")
        _, levels = read_btf(path)
        btfs[label] = btf_levels_from_channels(levels)
    env = load_envmap(args.env, scale=args.env_scale) if args.env is not None else None
    return motion, mask, (btfs or None), env


def _inputs(args) -> list:
    """The files this run reads: its output never replaces one of them."""
    return [args.motion, args.mask, args.env]


def run(args) -> int:
    motion, mask, btfs, env = _load_inputs(args)
    info: dict = {}
    meshes = [] if args.meshes else None
    with tqdm(total=args.frames, desc="noh frames", disable=None) as bar:
        frames = render_noh(frames=args.frames, width=args.width, height=args.height, key=jax.random.key(args.seed),
                            mask_rgb=mask, btfs=btfs, env=env, motion=motion, motion_source=args.motion,
                            frame_dt=1.0 / args.fps, progress=bar.update, info=info, time_repeats=args.time,
                            meshes=meshes)
    with output_folder(args.out, inputs=_inputs(args)) as stage:
        write_animation(stage, frames, exposure=info["exposure"], fps=args.fps, video=not args.no_video)
        if meshes is not None:
            write_meshes(stage, meshes)
    if args.time > 0:
        print(f"prepare_s={info['prepare_s']:.4f} recompiles={info['recompiles']}")
        print_timing(info["compile_s"], info["timed_s"])
    else:
        print(f"wrote {args.frames} frames, noh.gif{'' if args.no_video else ' and noh.mp4'} to {args.out}")
    return 0

"""`jaxrender shafts SCENE.json --out OUT.exr|.png`: light shafts in fog (paper 000).

A thin layer over `jaxrender.app.scenes.load_shafts_scene`, `jaxrender.shafts.render_planes` and
`jaxrender.shafts.render_raymarch`.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import numpy as np

from jaxrender.io import InputError, write_image
from jaxrender.shafts import render_planes, render_raymarch

from ..scenes import load_shafts_scene
from .timed import add_time_argument, render_timed


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", type=Path, help="scene file (JSON, see design.md)")
    parser.add_argument("--out", type=Path, required=True, help="output image: .exr (linear) or .png (tone-mapped)")
    parser.add_argument("--width", type=int, default=None, help="override the scene's image width")
    parser.add_argument("--height", type=int, default=None, help="override the scene's image height")
    parser.add_argument("--method", choices=("planes", "raymarch"), default="planes",
                        help="sample planes (the paper's method, default) or the ray-marched reference")
    parser.add_argument("--planes", type=int, default=30, help="sample planes per light (default 30)")
    parser.add_argument("--subplanes", type=int, default=6, help="sub-sample planes per interval (default 6)")
    parser.add_argument("--quantize-bits", type=int, default=0,
                        help="hardware emulation: bits of tables, maps and frame buffer (0 = float, 8 = paper)")
    parser.add_argument("--samples", type=int, default=180, help="ray-march samples per ray (default 180)")
    add_time_argument(parser)


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    if out.suffix.lower() not in (".exr", ".png"):
        raise InputError(out, "output must end in .exr or .png")
    if args.method == "raymarch" and args.quantize_bits:
        raise InputError(None, "--quantize-bits applies to --method planes only "
                               "(the ray march is the unquantized reference)")
    for name in ("planes", "subplanes", "samples"):
        if getattr(args, name) < 1:
            raise InputError(None, f"--{name} must be >= 1")
    if not 0 <= args.quantize_bits <= 16:
        raise InputError(None, "--quantize-bits must be between 0 and 16")
    for name in ("width", "height"):
        if getattr(args, name) is not None and getattr(args, name) < 1:
            raise InputError(None, f"--{name} must be >= 1")

    scene = load_shafts_scene(args.scene)
    if args.width is not None or args.height is not None:
        scene = scene.with_size(args.width, args.height)
    if args.method == "planes":
        render = jax.jit(lambda s: render_planes(s, planes=args.planes, subplanes=args.subplanes,
                                                 quantize_bits=args.quantize_bits))
    else:
        render = jax.jit(lambda s: render_raymarch(s, samples=args.samples))
    image = render_timed(lambda: jax.block_until_ready(render(scene)), args.time)
    write_image(out, np.asarray(image, dtype=np.float32))
    return 0

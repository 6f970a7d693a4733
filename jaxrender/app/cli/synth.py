"""`fitting synth OUT_DIR`: write a synthetic multi-light HDR capture with known parameter maps."""

from __future__ import annotations

import argparse

import jax

from fitting import Sensor, synth_capture
from jaxrender.errors import InputError

from .arguments import check_cells, non_negative, number, positive_int


def _lights(value: str):
    if value == "all":
        return value
    try:
        n = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{value!r} is not 'all' or a number") from None
    if n < 1:
        raise argparse.ArgumentTypeError("the number of lights must be >= 1")
    return n


def configure(parser):
    parser.add_argument("out_dir", metavar="OUT_DIR", help="new capture directory (capture.json, images/, truth/)")
    parser.add_argument("--size", nargs=2, type=positive_int, default=[32, 32], metavar=("H", "W"),
                        help="texels (default 32 32)")
    parser.add_argument("--lights", type=_lights, default=300,
                        help="'all' (the paper's 2160 directions) or N, a stratified subset chosen by the seed "
                             "(default 300)")
    parser.add_argument("--seed", type=int, default=0, help="random seed: maps, light subset and noise (default 0)")
    parser.add_argument("--bits", type=int, choices=(8, 16), default=8, help="PNG bit depth (default 8)")
    parser.add_argument("--format", choices=("png", "exr"), default="png", help="image format (default png)")
    parser.add_argument("--response", choices=("linear", "srgb"), default="linear",
                        help="PNG response curve (default linear; EXR is always linear)")
    parser.add_argument("--noise", type=non_negative, default=1.0,
                        help="scale of the shot and read noise (0 = noiseless; default 1)")
    parser.add_argument("--full-well", type=number, default=20000.0, help="electrons at full scale (default 20000)")
    parser.add_argument("--read-noise", type=non_negative, default=10.0, help="read noise in electrons (default 10)")
    parser.add_argument("--white", type=number, default=0.95, help="white board reflectance (default 0.95)")
    parser.add_argument("--model", choices=("reciprocal", "paper"), default="reciprocal",
                        help="model form the images are rendered with (default reciprocal)")


def run(args) -> int:
    if not args.full_well > 0:
        raise InputError(None, "--full-well must be > 0")
    if not args.white > 0:
        raise InputError(None, "--white must be > 0")
    # peak memory per texel: 15 kB measured at 256 x 256 with 50 lights a batch (64 at most), with a margin
    check_cells(f"--size {args.size[0]} {args.size[1]}", args.size[0] * args.size[1], bytes_per_cell=20_000)
    sensor = Sensor(noise=args.noise, full_well=args.full_well, read_noise=args.read_noise)
    out = synth_capture(args.out_dir, key=jax.random.PRNGKey(args.seed), size=tuple(args.size), lights=args.lights,
                        bits=args.bits, image_format=args.format, response=args.response, noise=args.noise,
                        model=args.model, white_reflectance=args.white, sensor=sensor)
    print(f"capture written to {out} (true maps in {out / 'truth'})")
    return 0

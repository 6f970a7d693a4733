"""`jaxrender desert`: render the desert of dunes and wind ripples (paper 001)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from jaxrender.io import InputError, output_file, write_image

from ..scenes.desert import EXPOSURE, render_desert
from .arguments import check_cells, number
from .timed import add_time_argument, render_timed


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, required=True, help="output image: .exr (linear) or .png (tone-mapped)")
    parser.add_argument("--width", type=int, default=720, help="image width (default 720)")
    parser.add_argument("--height", type=int, default=480, help="image height (default 480)")
    parser.add_argument("--sun-elevation", type=number, default=18.0, help="sun elevation in degrees (default 18)")
    parser.add_argument("--sun-azimuth", type=number, default=165.0,
                        help="sun azimuth in degrees from +x (downwind) toward +y (default 165)")
    for name, help_ in [("ripples", "bump-mapped wind ripples and sand grain"),
                        ("lod", "level of detail per dune quad"),
                        ("culling", "back-face and view-frustum culling of dune quads"),
                        ("dune-shadows", "dune shadows (ray march toward the sun)"),
                        ("ripple-shadows", "ripple shadows (horizon maps)"), ("dust", "sand-dust billboards")]:
        parser.add_argument(f"--{name}", action=argparse.BooleanOptionalAction, default=True,
                            help=f"{help_} (default on)")
    parser.add_argument("--footprints", action=argparse.BooleanOptionalAction, default=False,
                        help="a trail of footprints pressed into the sand across the foreground (Fig. 18; default off)")
    parser.add_argument("--dune-size", type=int, default=64, help="dune grid size in quads (default 64)")
    parser.add_argument("--ripple-size", type=int, default=64, help="ripple map size in texels (default 64)")
    parser.add_argument("--texels", type=int, default=64, help="ripple texels per dune quad at level 0 (default 64)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the automata, grain and dust (default 0)")
    add_time_argument(parser)


def run(args: argparse.Namespace) -> int:
    out = output_file(args.out, suffixes=(".exr", ".png"))
    for name in ("width", "height", "dune_size", "ripple_size", "texels"):
        if getattr(args, name) < 1:
            raise InputError(None, f"--{name.replace('_', '-')} must be >= 1")
    if args.texels % 8 or args.ripple_size % 8:
        raise InputError(None, "--texels and --ripple-size must be multiples of 8 (4 ripple levels)")
    if not -10.0 <= args.sun_elevation <= 90.0:
        raise InputError(None, "--sun-elevation must be within [-10, 90] degrees")
    # peak memory per cell measured at 720 x 480 and 1440 x 960 (pixels), with margins for the grids
    check_cells(f"a {args.width} x {args.height} image", args.width * args.height, bytes_per_cell=200)
    check_cells(f"--dune-size {args.dune_size}", args.dune_size**2, bytes_per_cell=256)
    check_cells(f"--ripple-size {args.ripple_size}", args.ripple_size**2, bytes_per_cell=256)
    check_cells(f"--dune-size {args.dune_size} x --texels {args.texels}", (args.dune_size * args.texels) ** 2,
                bytes_per_cell=0)

    kwargs = dict(width=args.width, height=args.height, ripples=args.ripples, lod=args.lod, culling=args.culling,
                  dune_shadows=args.dune_shadows, ripple_shadows=args.ripple_shadows, dust=args.dust,
                  sun_elevation=args.sun_elevation, sun_azimuth=args.sun_azimuth, dune_size=args.dune_size,
                  ripple_size=args.ripple_size, texels=args.texels, seed=args.seed,
                  footprints=args.footprints)
    # the first run grows the fields, builds the maps, compiles
    image = render_timed(lambda: render_desert(**kwargs), args.time)
    write_image(out, np.asarray(image, dtype=np.float32), exposure=EXPOSURE)
    return 0

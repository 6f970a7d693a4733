"""Arguments and the run shared by `sims ripples` and `sims dunes`."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

import jax
import jax.numpy as jnp

from jaxrender.io import InputError, output_file, write_png
from sims import FIELD_SUFFIXES, load_field, preview_image, save_field, simulate_in_chunks

from .arguments import check_cells, number

BYTES_PER_CELL = 64   # the automata's peak memory per cell: 42 bytes measured at 4000 x 4000, with a margin


def add_common(parser: argparse.ArgumentParser, *, L0: float, b: float, D: float, size: str, steps: int) -> None:
    parser.add_argument("--size", default=size, help=f"grid size N or HxW (default {size}; ignored with --init)")
    parser.add_argument("--steps", type=int, default=steps, help=f"automaton steps (default {steps})")
    parser.add_argument("--L0", type=number, default=L0, help=f"hop length offset L0 in cells (default {L0})")
    parser.add_argument("--b", type=number, default=b, help=f"hop length coefficient b (default {b})")
    parser.add_argument("--D", type=number, default=D, help=f"creep coefficient D (default {D})")
    parser.add_argument("--hop", choices=("split", "nearest"), default="split",
                        help="split: share between the two nearest cells (default, differentiable); nearest: the paper")
    parser.add_argument("--wind-deg", type=number, default=0.0,
                        help="wind direction, degrees from +x (columns) toward +y (rows) (default 0)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the initial field (default 0)")
    parser.add_argument("--init", type=Path, default=None, metavar="FIELD.npy",
                        help="continue from this height field (.npy or .exr) instead of a random one")
    parser.add_argument("--out", type=Path, required=True, metavar="FIELD.npy",
                        help="output height field: .npy or .exr")
    parser.add_argument("--preview", type=Path, default=None, metavar="PNG", help="also write a shaded PNG preview")


def parse_size(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"\s*(\d+)\s*(?:[xX]\s*(\d+))?\s*", str(text))
    if not match:
        raise InputError(None, f"--size must be N or HxW, got {text!r}")
    h = int(match.group(1))
    w = int(match.group(2) or match.group(1))
    if min(h, w) < 3:
        raise InputError(None, f"--size must be at least 3x3, got {h}x{w}")
    return h, w


def validate(args: argparse.Namespace) -> None:
    output_file(args.out, suffixes=FIELD_SUFFIXES, inputs=[args.init])
    if args.preview is not None:
        output_file(args.preview, suffixes=(".png",), inputs=[args.init, args.out])
        if args.preview.resolve() == args.out.resolve():
            raise InputError(args.preview, "is also --out; give the preview its own name")
    if args.steps < 0:
        raise InputError(None, f"--steps must be >= 0, got {args.steps}")
    if not 0.0 <= args.D <= 1.0:
        raise InputError(None, f"--D must be in [0, 1] (creep beyond 1 is unstable), got {args.D}")


def execute(args: argparse.Namespace, *, simulate, init_random, desc: str) -> int:
    """Load or draw the initial field, run with a progress bar, write the outputs."""
    validate(args)
    if args.init is not None:
        field = jnp.asarray(load_field(args.init))
    else:
        h, w = parse_size(args.size)
        check_cells(f"--size {h}x{w}", h * w, bytes_per_cell=BYTES_PER_CELL)
        field = init_random(jax.random.key(args.seed), (h, w))
    field = simulate_in_chunks(simulate, field, args.steps, desc=desc)
    out = save_field(args.out, field)
    if args.preview is not None:
        write_png(args.preview, preview_image(field), srgb=False)
    print(f"wrote {out} ({field.shape[0]}x{field.shape[1]}, {args.steps} steps, "
          f"height {float(field.min()):.3f}..{float(field.max()):.3f})")
    return 0

"""Arguments and the run shared by `sims ripples` and `sims dunes`."""

from __future__ import annotations

import argparse
import math
import re
from pathlib import Path

import jax
import jax.numpy as jnp

from jaxrender.io import InputError, write_png
from sims import FIELD_SUFFIXES, load_field, preview_image, save_field, simulate_in_chunks


def add_common(parser: argparse.ArgumentParser, *, L0: float, b: float, D: float, size: str, steps: int) -> None:
    parser.add_argument("--size", default=size, help=f"grid size N or HxW (default {size}; ignored with --init)")
    parser.add_argument("--steps", type=int, default=steps, help=f"automaton steps (default {steps})")
    parser.add_argument("--L0", type=float, default=L0, help=f"hop length offset L0 in cells (default {L0})")
    parser.add_argument("--b", type=float, default=b, help=f"hop length coefficient b (default {b})")
    parser.add_argument("--D", type=float, default=D, help=f"creep coefficient D (default {D})")
    parser.add_argument("--hop", choices=("split", "nearest"), default="split",
                        help="split: share between the two nearest cells (default, differentiable); nearest: the paper")
    parser.add_argument("--wind-deg", type=float, default=0.0,
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
    if args.out.suffix.lower() not in FIELD_SUFFIXES:
        raise InputError(args.out, "output must end in .npy or .exr")
    if args.preview is not None and args.preview.suffix.lower() != ".png":
        raise InputError(args.preview, "preview must end in .png")
    if args.steps < 0:
        raise InputError(None, f"--steps must be >= 0, got {args.steps}")
    for name, value in vars(args).items():
        if isinstance(value, float) and not math.isfinite(value):
            raise InputError(None, f"--{name.replace('_', '-')} must be finite, got {value}")
    if not 0.0 <= args.D <= 1.0:
        raise InputError(None, f"--D must be in [0, 1] (creep beyond 1 is unstable), got {args.D}")


def execute(args: argparse.Namespace, *, simulate, init_random, desc: str) -> int:
    """Load or draw the initial field, run with a progress bar, write the outputs."""
    validate(args)
    if args.init is not None:
        field = jnp.asarray(load_field(args.init))
    else:
        field = init_random(jax.random.key(args.seed), parse_size(args.size))
    field = simulate_in_chunks(simulate, field, args.steps, desc=desc)
    out = save_field(args.out, field)
    if args.preview is not None:
        write_png(args.preview, preview_image(field), srgb=False)
    print(f"wrote {out} ({field.shape[0]}x{field.shape[1]}, {args.steps} steps, "
          f"height {float(field.min()):.3f}..{float(field.max()):.3f})")
    return 0

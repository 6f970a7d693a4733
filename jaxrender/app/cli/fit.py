"""`fitting fit CAPTURE_DIR --out BTF_DIR`: per-texel anisotropic BRDF fit of a capture directory."""

from __future__ import annotations

import argparse
import json

from fitting import fit_capture
from fitting.lm import DEFAULT_MAX_STEPS


def _positive_int(value: str) -> int:
    try:
        n = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{value!r} is not an integer") from None
    if n < 1:
        raise argparse.ArgumentTypeError("must be >= 1")
    return n


def configure(parser):
    parser.add_argument("capture_dir", metavar="CAPTURE_DIR", help="capture directory (capture.json + images)")
    parser.add_argument("--out", required=True, metavar="BTF_DIR",
                        help="output BTF directory (rerun on the same one to resume an interrupted fit)")
    parser.add_argument("--solver", choices=("optimistix", "jaxopt", "native"), default="optimistix",
                        help="Levenberg-Marquardt backend (default optimistix; native = fitting.lm's own, faster loop)")
    parser.add_argument("--chunk", type=_positive_int, default=4096,
                        help="texels per chunk: bounds memory, one checkpoint each (default 4096)")
    parser.add_argument("--max-steps", type=_positive_int, default=None,
                        help="Levenberg-Marquardt steps per texel (default 40)")
    parser.add_argument("--model", choices=("reciprocal", "paper"), default="reciprocal",
                        help="model form (default reciprocal; paper = eq. 1 as printed)")
    parser.add_argument("--no-pyramid", action="store_true", help="write level 0 only (skip the EM pyramid)")


def run(args) -> int:
    out = fit_capture(args.capture_dir, args.out, solver=args.solver, chunk=args.chunk,
                      max_steps=args.max_steps or DEFAULT_MAX_STEPS, model=args.model,
                      pyramid=not args.no_pyramid)
    info = json.loads((out / "btf.json").read_text()).get("fit", {})
    print(f"{out}: converged {info.get('converged_fraction', float('nan')):.1%}, "
          f"median residual {info.get('median_residual', float('nan')):.4g}, fit {info.get('seconds', 0):.1f} s")
    return 0

"""`fitting pyramid BTF_DIR [--levels N]`: EM multi-resolution levels of a fitted BTF."""

from __future__ import annotations

from tqdm import tqdm

from fitting.em import DEFAULT_ITERATIONS
from fitting.pyramid import build_pyramid, pyramid_sizes
from jaxrender.io import InputError, read_btf


def configure(parser):
    parser.add_argument("btf_dir", metavar="BTF_DIR", help="a complete BTF directory (with btf.json)")
    parser.add_argument("--levels", type=int, default=None,
                        help="total number of levels, level 0 included (default: down to 1x1)")
    parser.add_argument("--iterations", type=int, default=None, help="maximum EM iterations per texel")


def run(args) -> int:
    if args.levels is not None and args.levels < 1:
        raise InputError(args.btf_dir, f"--levels must be >= 1, got {args.levels}")
    if args.iterations is not None and args.iterations < 1:
        raise InputError(args.btf_dir, f"--iterations must be >= 1, got {args.iterations}")
    manifest, _ = read_btf(args.btf_dir, load=False)
    total = len(pyramid_sizes(tuple(manifest["levels"][0]["size"]), levels=args.levels)) - 1
    with tqdm(total=total, desc="EM levels", unit="level", disable=None) as bar:
        out = build_pyramid(args.btf_dir, levels=args.levels, progress=bar.update,
                            iterations=args.iterations or DEFAULT_ITERATIONS)
    print(f"{total} EM levels written to {out}")
    return 0

"""`fitting relight BTF_DIR --theta T --phi P --out IMG.exr|png`: the fitted sample under one light."""

from __future__ import annotations

import numpy as np

from fitting import direction_from_angles, relight
from jaxrender.io import InputError, output_file, write_image

from .arguments import number


def configure(parser):
    parser.add_argument("btf_dir", metavar="BTF_DIR", help="fitted BTF directory")
    parser.add_argument("--theta", type=number, required=True, help="light elevation from the normal, degrees [0, 90)")
    parser.add_argument("--phi", type=number, required=True, help="light azimuth, degrees (0 = along image columns)")
    parser.add_argument("--view-theta", type=number, default=0.0, help="view elevation, degrees (default 0)")
    parser.add_argument("--view-phi", type=number, default=0.0, help="view azimuth, degrees (default 0)")
    parser.add_argument("--level", type=int, default=0, help="pyramid level (default 0)")
    parser.add_argument("--out", required=True, metavar="IMG",
                        help="output image: .exr (linear R) or .png (tone-mapped)")


def run(args) -> int:
    out = output_file(args.out, suffixes=(".exr", ".png"))
    for name in ("theta", "view_theta"):
        value = getattr(args, name)
        if not 0.0 <= value < 90.0:
            raise InputError(None, f"--{name.replace('_', '-')} {value} must be in [0, 90) degrees")
    light = direction_from_angles(args.theta, args.phi)
    view = direction_from_angles(args.view_theta, args.view_phi)
    image = relight(args.btf_dir, light, view, level=args.level)
    write_image(out, np.asarray(image, np.float32))
    print(f"{out}: {image.shape[1]}x{image.shape[0]}, mean R {float(np.mean(image)):.4g}")
    return 0

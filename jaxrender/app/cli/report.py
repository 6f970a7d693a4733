"""`fitting report CAPTURE_DIR BTF_DIR [--holdout K] [--normals GT]`: relighting error per light,
residuals and maps of a fit; held-out lights and normals against a ground truth when asked."""

from __future__ import annotations

from fitting import fit_report
from jaxrender.io import InputError, output_file


def configure(parser):
    parser.add_argument("capture_dir", metavar="CAPTURE_DIR", help="the capture the BTF was fitted to")
    parser.add_argument("btf_dir", metavar="BTF_DIR", help="fitted BTF directory")
    parser.add_argument("--out", default=None, metavar="REPORT.png", help="figure (default BTF_DIR/report.png)")
    parser.add_argument("--holdout", type=int, default=None, metavar="K",
                        help="refit without every K-th light and report the error predicting those lights, beside a "
                             "least-squares Lambertian fit of the same lights")
    parser.add_argument("--normals", default=None, metavar="GT",
                        help="ground-truth normal map (.mat, .npy, .exr): report the mean angular error over the mask")


def run(args) -> int:
    if args.holdout is not None and args.holdout < 2:
        raise InputError(None, f"--holdout must be >= 2, got {args.holdout}")
    if args.out is not None:
        output_file(args.out, suffixes=(".png",), inputs=[args.normals])
    report = fit_report(args.capture_dir, args.btf_dir, out=args.out, holdout=args.holdout, normals=args.normals)
    print(report["table"])
    print(f"figure: {report['figure']}")
    return 0

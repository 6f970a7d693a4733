"""`fitting report CAPTURE_DIR BTF_DIR`: relighting error per light, residuals and maps of a fit."""

from __future__ import annotations

from fitting import fit_report


def configure(parser):
    parser.add_argument("capture_dir", metavar="CAPTURE_DIR", help="the capture the BTF was fitted to")
    parser.add_argument("btf_dir", metavar="BTF_DIR", help="fitted BTF directory")
    parser.add_argument("--out", default=None, metavar="REPORT.png", help="figure (default BTF_DIR/report.png)")


def run(args) -> int:
    report = fit_report(args.capture_dir, args.btf_dir, out=args.out)
    print(report["table"])
    print(f"figure: {report['figure']}")
    return 0

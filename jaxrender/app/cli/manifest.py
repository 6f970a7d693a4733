"""`fitting manifest IMAGES.csv|OBJECT_DIR --out CAPTURE_DIR/capture.json`: a capture manifest from a
CSV of images (columns image, kind, a direction, optional intensity, exposure_s) or from a
DiLiGenT-format photometric-stereo folder (images referred to in place)."""

from __future__ import annotations

from pathlib import Path

from fitting.manifest import write_folder_manifest, write_manifest

from .arguments import positive_float


def _float(value: str) -> float:
    import argparse

    try:
        return float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{value!r} is not a number") from None


def configure(parser):
    parser.add_argument("source", metavar="IMAGES.csv|OBJECT_DIR",
                        help="a CSV (one row per image: image, kind, theta_deg, phi_deg or light_x, light_y, light_z, "
                             "optional intensity or intensity_r/g/b, exposure_s) or a DiLiGenT-format folder "
                             "(filenames.txt, light_directions.txt, light_intensities.txt, mask.png, 16-bit PNGs)")
    parser.add_argument("--out", required=True, metavar="CAPTURE_DIR/capture.json", help="manifest to write")
    parser.add_argument("--response", choices=("linear", "srgb"), default="linear",
                        help="how integer codes are linearised (default linear; camera JPEGs: srgb)")
    parser.add_argument("--white-reflectance", type=positive_float, nargs="+", default=[1.0], metavar="R",
                        help="the white board's reflectance: one number or R G B (default 1.0)")
    parser.add_argument("--view", type=_float, nargs=2, default=(0.0, 0.0), metavar=("THETA", "PHI"),
                        help="camera direction in degrees (default 0 0)")


def run(args) -> int:
    refl = args.white_reflectance
    if Path(args.source).is_dir():
        out = write_folder_manifest(args.source, args.out)
    else:
        out = write_manifest(args.source, args.out, response=args.response,
                             white_reflectance=refl[0] if len(refl) == 1 else list(refl), view=tuple(args.view))
    print(f"{out}: written")
    return 0

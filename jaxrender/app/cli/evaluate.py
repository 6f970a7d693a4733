"""`fitting evaluate OBJECT_DIR|CAPTURE_DIR [--folds K]`: K-fold light cross-validation of a fit
(`fitting.crossval`): each light held out once, the held-out photographs predicted by the fit of
the others beside a least-squares Lambertian fit of the same lights, normals against a ground
truth where there is one; a table on the terminal and a PNG of the error maps."""

from __future__ import annotations

import tempfile
from pathlib import Path

from fitting import load_capture, merge_capture, write_folder_manifest
from fitting.crossval import DEFAULT_FOLDS, cross_validate, figure
from fitting.evaluate import read_normal_map
from jaxrender.io import InputError, output_file

from .arguments import positive_int
from .fit_options import add_fit_settings, fit_settings

GROUND_TRUTH = ("Normal_gt.mat", "truth/level_00.exr")   # a DiLiGenT object's; a `fitting synth` capture's


def configure(parser):
    parser.add_argument("source", metavar="OBJECT_DIR|CAPTURE_DIR",
                        help="a DiLiGenT-format object folder (filenames.txt, light_directions.txt, ...) or a "
                             "capture directory (capture.json)")
    parser.add_argument("--folds", type=positive_int, default=DEFAULT_FOLDS, metavar="K",
                        help=f"folds of lights, light i in fold i mod K, each held out once (default {DEFAULT_FOLDS})")
    parser.add_argument("--normals", default=None, metavar="GT",
                        help="ground-truth normal map (.mat, .npy, .exr; default: the folder's Normal_gt.mat or "
                             "a synthetic capture's truth/level_00.exr, when there)")
    parser.add_argument("--out", default=None, metavar="REPORT.png",
                        help="figure of the error maps (default NAME_evaluate.png in the current directory)")
    add_fit_settings(parser)


def _observations(source: Path):
    """The merged observations of a capture directory, or of an object folder through a manifest
    written to a temporary directory (the images stay where they are)."""
    if (source / "capture.json").is_file():
        return merge_capture(load_capture(source), progress=False)
    if (source / "filenames.txt").is_file():
        with tempfile.TemporaryDirectory() as tmp:
            write_folder_manifest(source, Path(tmp) / "capture.json")
            return merge_capture(load_capture(tmp), progress=False)
    what = "no such directory" if not source.is_dir() else \
        "neither a capture directory (capture.json) nor a DiLiGenT-format object folder (filenames.txt)"
    raise InputError(source, what)


def run(args) -> int:
    source = Path(args.source)
    out = output_file(args.out if args.out is not None else f"{source.resolve().name}_evaluate.png",
                      suffixes=(".png",), inputs=[args.normals])
    settings = fit_settings(args)
    obs = _observations(source)
    if not 2 <= args.folds <= obs.n_lights:
        raise InputError(None, f"--folds {args.folds}: must be in 2..{obs.n_lights} (the capture's lights)")
    truth = Path(args.normals) if args.normals is not None else \
        next((source / name for name in GROUND_TRUTH if (source / name).is_file()), None)
    normals = None if truth is None else read_normal_map(truth, obs.size)
    result = cross_validate(obs, settings, folds=args.folds, normals=normals, progress=None)
    print(result.table())
    if truth is not None:
        print(f"ground truth: {truth}")
    title = f"{source.resolve().name}: {args.folds}-fold light cross-validation, {settings.method} method"
    print(f"figure: {figure(result, out, title)}")
    return 0

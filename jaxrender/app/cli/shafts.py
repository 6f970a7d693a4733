"""`jaxrender shafts SCENE.json --out OUT.exr|.png`: light shafts in fog (paper 000).

A thin layer over `jaxrender.app.scenes.load_shafts_scene` and `jaxrender.shafts.render`
(methods `equiangular`, the default, `planes` and `raymarch`; `--spp` antialiasing for each;
`--error E`: the counts chosen by `jaxrender.shafts.choose_counts`, the choice printed).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

from jaxrender.io import FLOAT32_MAX, InputError, output_file, write_image
from jaxrender.shafts import DEFAULT_METHOD, METHODS, choose_counts, render

from ..scenes import check_image_size, load_shafts_scene
from .arguments import number
from .timed import add_time_argument, render_timed


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scene", type=Path, help="scene file (JSON, see design.md)")
    parser.add_argument("--out", type=Path, required=True, help="output image: .exr (linear) or .png (tone-mapped)")
    parser.add_argument("--width", type=int, default=None, help="override the scene's image width")
    parser.add_argument("--height", type=int, default=None, help="override the scene's image height")
    parser.add_argument("--method", choices=tuple(METHODS), default=DEFAULT_METHOD,
                        help="equiangular: fast single scattering, steps of equal angle seen from each light "
                             "(default); planes: the paper's sample planes; raymarch: the exact reference")
    parser.add_argument("--spp", type=int, default=None, metavar="N",
                        help="antialiasing: N samples per PIXEL, a regular k x k sub-pixel grid (N = k*k), box "
                             "filter; default: the scene's render.spp (1). Not --samples, which counts samples "
                             "along each view ray")
    parser.add_argument("--planes", type=int, default=None, help="sample planes per light (default 30)")
    parser.add_argument("--subplanes", type=int, default=None, help="sub-sample planes per interval (default 6)")
    parser.add_argument("--quantize-bits", type=int, default=0,
                        help="hardware emulation: bits of tables, maps and frame buffer (0 = float, 8 = paper)")
    parser.add_argument("--samples", type=int, default=None,
                        help="samples along each view ray and light: adaptive and equiangular (default 24), raymarch "
                             "(default 180); see --spp for samples per pixel")
    parser.add_argument("--error", type=number, default=None, metavar="E",
                        help="choose --samples (or --planes and --subplanes) so that the in-scattered light is "
                             "predicted within relative RMS E of the converged result (e.g. 0.02), from a quick "
                             "estimate on a small proxy of the scene; the choice is printed")
    add_time_argument(parser)


def run(args: argparse.Namespace) -> int:
    out = output_file(args.out, suffixes=(".exr", ".png"), inputs=[args.scene])
    if args.method != "planes" and args.quantize_bits:
        raise InputError(None, "--quantize-bits applies to --method planes only "
                               "(the other methods are unquantized)")
    for name in ("planes", "subplanes", "samples", "spp"):
        if getattr(args, name) is not None and getattr(args, name) < 1:
            raise InputError(None, f"--{name} must be >= 1")
    if args.spp is not None and math.isqrt(args.spp) ** 2 != args.spp:
        raise InputError(None, f"--spp must be a perfect square (1, 4, 9, 16, ...), got {args.spp}")
    if args.error is not None:
        if not 0 < args.error < 1:
            raise InputError(None, f"--error must be a relative error between 0 and 1 (e.g. 0.02), got {args.error}")
        given = [f"--{n}" for n in ("samples", "planes", "subplanes") if getattr(args, n) is not None]
        if given:
            raise InputError(None, f"--error chooses the counts itself: drop {' and '.join(given)}")
    if not 0 <= args.quantize_bits <= 16:
        raise InputError(None, "--quantize-bits must be between 0 and 16")
    for name in ("width", "height"):
        if getattr(args, name) is not None and getattr(args, name) < 1:
            raise InputError(None, f"--{name} must be >= 1")

    scene = load_shafts_scene(args.scene)
    if args.width is not None or args.height is not None:
        scene = scene.with_size(args.width, args.height)
    spp = scene.render.spp if args.spp is None else args.spp
    check_image_size(scene.camera.width, scene.camera.height, spp)
    if args.method == "planes":
        options = dict(planes=30 if args.planes is None else args.planes,
                       subplanes=6 if args.subplanes is None else args.subplanes, quantize_bits=args.quantize_bits)
    else:
        options = {} if args.samples is None else dict(samples=args.samples)  # the method's default
    if args.error is not None:
        fixed = {k: v for k, v in options.items() if k not in ("planes", "subplanes")}
        choice = choose_counts(scene, args.error, method=args.method, **fixed)
        options.update(choice.options)
        print(choice.describe())
    scene, scale = _unit_lights(scene) if not args.quantize_bits else (scene, 1.0)
    fn = jax.jit(lambda s: render(s, method=args.method, samples_per_pixel=spp, **options))
    image = np.asarray(render_timed(lambda: jax.block_until_ready(fn(scene)), args.time), np.float64) * scale
    if np.any(np.isinf(image) | (np.abs(image) > FLOAT32_MAX)):
        raise InputError(args.scene, f"the rendered radiance exceeds float32's range ({FLOAT32_MAX:.4g}): lower "
                                     "the lights' intensities")
    write_image(out, image.astype(np.float32))
    return 0


def _unit_lights(scene):
    """The scene with its light intensities divided by the largest, and that scale. Radiance is linear
    in them: a float32 render of very bright lights then overflows only where the image itself would
    (the 8-bit frame buffer of --quantize-bits is not linear: it renders as given)."""
    peak = max(float(np.max(np.asarray(light.intensity))) for light in scene.lights)
    if not peak > 0:
        return scene, 1.0
    unit = [jax.numpy.asarray(light.intensity) / peak for light in scene.lights]
    return eqx.tree_at(lambda s: [light.intensity for light in s.lights], scene, unit), peak

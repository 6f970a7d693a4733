"""Paper 000, section 5.1: the sample-plane method (30 planes x 6 sub-planes, 8-bit hardware emulation)
against the "conventional method" (a ray march with 180 samples per view ray and a shadow ray per
sample), on the scene of fig. 6(b): a sphere under one spot light, 720 x 480.

Paper (GeForce2 GTS + Pentium III 733 MHz): RMS difference 2.6 % of 256 levels; 27 s (ray tracing)
vs 0.17 s (planes).

    python benchmarks/shafts_sec51.py [--quick]

Prints a table (compile time apart; median of repeats) and writes benchmarks/figures/shafts_sec51.png.
"""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _shafts_common as C  # noqa: E402
from _results import write_results  # noqa: E402

PAPER_RMS = 0.026  # of 256 levels


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="120 x 80 instead of 720 x 480, 1 repeat, no float frame")
    args = parser.parse_args(argv)

    import equinox as eqx
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from jaxrender.shafts import render_planes, render_raymarch

    w, h = (120, 80) if args.quick else (C.PAPER_W, C.PAPER_H)
    repeats = 1 if args.quick else 5
    scene = C.load(C.sphere_scene(w, h))
    white = float(C.RENDER["display_white"])
    print(f"# section 5.1, {w} x {h}; {C.machine()}")

    planes8 = eqx.filter_jit(functools.partial(render_planes, planes=30, subplanes=6, quantize_bits=8))
    planesf = eqx.filter_jit(functools.partial(render_planes, planes=30, subplanes=6, quantize_bits=0))
    march = eqx.filter_jit(functools.partial(render_raymarch, samples=180))

    img8, c8, t8 = C.timed(planes8, scene, repeats=repeats)
    u8 = C.timed.cpu
    if args.quick:  # a smoke run: the float frame is one compile more (shafts_speed --quick renders one)
        imgf, cf, tf, uf = img8, c8, t8, u8
    else:
        imgf, cf, tf = C.timed(planesf, scene, repeats=repeats)
        uf = C.timed.cpu
    ref, cr, tr = C.timed(march, scene, repeats=max(1, repeats // 2))
    ur = C.timed.cpu

    lref = C.levels(ref, white)
    rms8 = float(np.sqrt(np.mean((C.levels(img8, white) - lref) ** 2)))
    rmsf = float(np.sqrt(np.mean((C.levels(imgf, white) - lref) ** 2)))
    rows = [
        ["planes 30 x 6, 8-bit", f"{rms8:.2f} ({100 * rms8 / 256:.2f} %)", f"{c8:.1f}", f"{t8:.3f}", f"{tr / t8:.1f}x",
         f"{u8:.3f}", f"{ur / u8:.1f}x"],
        ["planes 30 x 6, float", f"{rmsf:.2f} ({100 * rmsf / 256:.2f} %)", f"{cf:.1f}", f"{tf:.3f}", f"{tr / tf:.1f}x",
         f"{uf:.3f}", f"{ur / uf:.1f}x"],
        ["ray march 180 samples", "(reference)", f"{cr:.1f}", f"{tr:.3f}", "1x", f"{ur:.3f}", "1x"],
        ["paper: planes (GeForce2 GTS)", "6.7 (2.6 %)", "-", "0.17", "159x (27 s / 0.17 s)", "-", "-"],
        ["paper: ray tracing (P-III 733)", "(reference)", "-", "27", "1x", "-", "-"],
    ]
    text = C.table(["method", "RMS diff. to ray march, levels (% of 256)", "compile + 1st run s",
                    "median frame s", "speed-up vs ray march", "median CPU s per frame", "CPU speed-up"], rows)
    print(text)

    fig, ax = plt.subplots(1, 3, figsize=(13, 3.2))
    for a, img, title in [(ax[0], img8, "planes 30 x 6, 8-bit"), (ax[1], ref, "ray march, 180 samples")]:
        a.imshow(np.clip(np.asarray(img) / white, 0, 1) ** (1 / 2.2))
        a.set_title(title)
        a.axis("off")
    diff = np.abs(C.levels(img8, white) - lref).mean(axis=-1)
    im = ax[2].imshow(diff, cmap="magma", vmin=0, vmax=max(8.0, float(np.percentile(diff, 99.5))))
    ax[2].set_title(f"|difference| in levels (RMS {rms8:.2f} = {100 * rms8 / 256:.2f} %)")
    ax[2].axis("off")
    fig.colorbar(im, ax=ax[2], fraction=0.03)
    path = C.save_figure(fig, "shafts_sec51.png", quick=args.quick)
    print(f"figure: {path.relative_to(C.REPO)}")
    write_results("shafts_sec51", [dict(
        area="shafts", target="paper sec. 5.1: 30 x 6 planes (8-bit) within the paper's 2.6 % RMS of a ray march",
        measured=f"{100 * rms8 / 256:.2f} % of 256 levels ({rms8:.2f} levels RMS; float planes "
                 f"{100 * rmsf / 256:.2f} %)",
        status="met" if rms8 / 256 <= PAPER_RMS else "missed",
        notes=f"vs a 180-sample ray march, {w}x{h}, fig. 6(b) scene; speed-up {tr / t8:.1f}x wall, {ur / u8:.1f}x CPU "
              f"({t8:.3f} s vs {tr:.2f} s; paper 27 s / 0.17 s = 159x, GPU planes vs CPU ray tracer, ours both on "
              f"the same CPU); figure {path.relative_to(C.REPO)}",
        figures={"rms8_levels": rms8, "rmsf_levels": rmsf, "planes8_s": t8, "planes8_cpu_s": u8, "march_s": tr,
                 "march_cpu_s": ur})], quick=args.quick)
    return {"rms8_levels": rms8, "rmsf_levels": rmsf, "t_planes8": t8, "t_planesf": tf, "t_march": tr}


if __name__ == "__main__":
    main()

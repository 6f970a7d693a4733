"""Paper 000, fig. 4: quantization error and time vs. the number of sample planes (8-bit mode).

One spot light in fog over a dark floor, 720 x 480, sample planes n = 10..200 with no sub-sample
planes (m = 1: the paper introduces them only after this experiment; its 0.05 s at n = 30 vs. 0.17 s
with m = 6 in fig. 5 says so too), texture-coordinate mesh 15 x 10, 8-bit tables, light map and
frame buffer. Error: mean absolute difference, in display levels 0..255, at 10 representative
pixels, against a 200-sample unquantized ray march ("true value"). The 10 pixels are chosen
deterministically among the pixels whose true value is 15..240 levels (inside the shaft, not
saturated): the ones at 10 evenly spaced quantiles of the true value.

Paper: the error falls until about 30 planes and then rises (accumulated quantization error:
each plane adds its own rounded contribution to an 8-bit frame buffer); time grows linearly.

    python benchmarks/shafts_fig4.py [--quick]
"""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _shafts_common as C  # noqa: E402
from _results import write_results  # noqa: E402

PLANES = [10, 20, 30, 50, 100, 200]
PLANES_QUICK = [30]  # each count is a compile


def representative_pixels(true_levels, count: int = 10):
    """(rows, cols) of `count` pixels at evenly spaced quantiles of the true value among 15..240."""
    import numpy as np

    lum = true_levels.mean(axis=-1)
    rows, cols = np.nonzero((lum >= 15) & (lum <= 240))
    order = np.argsort(lum[rows, cols], kind="stable")
    pick = order[np.linspace(0, len(order) - 1, count).round().astype(int)]
    return rows[pick], cols[pick]


def fig4_row(plane_counts, errors, errors_f, cpus, w, h, figure) -> dict:
    """The result row: the paper's curve is reproduced if the 8-bit error is smallest at about 30 planes
    (20-50) and larger at both ends of the range, falling before the minimum and rising after it."""
    import numpy as np

    i = int(np.argmin(errors))
    falls = all(a >= b for a, b in zip(errors[: i + 1], errors[1 : i + 1]))
    rises = all(a <= b for a, b in zip(errors[i:], errors[i + 1 :]))
    shape = 20 <= plane_counts[i] <= 50 and 0 < i < len(errors) - 1 and falls and rises
    per_n = " / ".join(f"{e:.2f}" for e in errors)
    notes = (f"float (unquantized) planes: {' / '.join(f'{e:.2f}' for e in errors_f)} levels; 8-bit CPU s per frame "
             f"{' / '.join(f'{c:.3f}' for c in cpus)}; mean |difference| at 10 pixels vs a 200-sample ray march, "
             f"{w}x{h}, m = 1; figure {figure.relative_to(C.REPO)}")
    return dict(area="shafts", target="paper fig. 4: error falls to ~30 planes, then rises (8-bit)",
                measured=f"8-bit error {per_n} levels at {' / '.join(map(str, plane_counts))} planes; smallest at "
                         f"{plane_counts[i]}",
                status="reproduced" if shape else "not reproduced", notes=notes,
                figures={"planes": plane_counts, "error8_levels": errors, "errorf_levels": errors_f, "cpu8_s": cpus})


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="120 x 80, 30 planes only, no float column, 1 repeat")
    args = parser.parse_args(argv)

    import equinox as eqx
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from jaxrender.shafts import render_planes, render_raymarch

    w, h = (120, 80) if args.quick else (C.PAPER_W, C.PAPER_H)
    plane_counts = PLANES_QUICK if args.quick else PLANES
    repeats = 1 if args.quick else 2
    scene = C.load(C.spot_scene(w, h))
    white = float(C.RENDER["display_white"])
    print(f"# fig. 4, {w} x {h}, m = 1 sub-plane, 8-bit; {C.machine()}")

    ref, c_ref, t_ref = C.timed(eqx.filter_jit(functools.partial(render_raymarch, samples=200)), scene, repeats=1)
    true = C.levels(ref, white)
    rr, cc = representative_pixels(true)

    rows, errors, times, errors_f, cpus = [], [], [], [], []
    for n in plane_counts:
        fn8 = eqx.filter_jit(functools.partial(render_planes, planes=n, subplanes=1, quantize_bits=8))
        img8, c8, t8 = C.timed(fn8, scene, repeats=repeats)
        cpu8 = C.timed.cpu
        e8 = float(np.mean(np.abs(C.levels(img8, white)[rr, cc] - true[rr, cc])))
        ef = float("nan")
        if not args.quick:  # float mode: the same planes without quantization (one compile more each)
            fnf = eqx.filter_jit(functools.partial(render_planes, planes=n, subplanes=1, quantize_bits=0))
            imgf, _, _ = C.timed(fnf, scene, repeats=0)
            ef = float(np.mean(np.abs(C.levels(imgf, white)[rr, cc] - true[rr, cc])))
        errors.append(e8)
        errors_f.append(ef)
        times.append(t8)
        cpus.append(cpu8)
        rows.append([n, f"{e8:.2f}", f"{ef:.2f}", f"{c8:.1f}", f"{t8:.3f}", f"{cpu8:.3f}"])
        print(f"  n = {n}: 8-bit error {e8:.2f} levels, float {ef:.2f}, frame {t8:.3f} s, {cpu8:.3f} CPU s", flush=True)

    best = plane_counts[int(np.argmin(errors))]
    text = C.table(["planes n", "8-bit: mean abs error, levels", "float: mean abs error, levels",
                    "compile + 1st run s", "8-bit median frame s", "8-bit median CPU s per frame"], rows)
    print(text)
    print(f"reference: ray march 200 samples, unquantized: {t_ref:.2f} s (incl. compile)")
    print(f"smallest 8-bit error at n = {best} (paper: about 30); paper time at n = 30: 0.05 s (GeForce2 GTS)")

    fig, ax = plt.subplots(figsize=(6.4, 4))
    ax.plot(plane_counts, errors, "o-", color="C0", label="8-bit error (levels)")
    if not args.quick:
        ax.plot(plane_counts, errors_f, "s--", color="C2", label="float error (levels)")
    ax.set_xlabel("number of sample planes")
    ax.set_ylabel("mean |difference| at 10 pixels (levels)")
    ax2 = ax.twinx()
    ax2.plot(plane_counts, times, "^:", color="C1", label="8-bit time (wall)")
    ax2.plot(plane_counts, cpus, "v:", color="C3", label="8-bit CPU s (both cores)")
    ax2.set_ylabel("seconds per frame")
    lines = ax.get_legend_handles_labels()[0] + ax2.get_legend_handles_labels()[0]
    labels = ax.get_legend_handles_labels()[1] + ax2.get_legend_handles_labels()[1]
    ax.legend(lines, labels, loc="upper center")
    ax.set_title(f"Fig. 4 rerun: one spot light, {w} x {h}, 8-bit")
    path = C.save_figure(fig, "shafts_fig4.png", quick=args.quick)
    print(f"figure: {path.relative_to(C.REPO)}")
    write_results("shafts_fig4", [fig4_row(plane_counts, errors, errors_f, cpus, w, h, path)], quick=args.quick)
    return {"planes": plane_counts, "error8": errors, "errorf": errors_f, "time8": times, "cpu8": cpus, "best": best}


if __name__ == "__main__":
    main()

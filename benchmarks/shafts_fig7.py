"""Paper 000, fig. 7 / section 5.2: a stage under five spot lights (two projecting polka-dot light
maps), 720 x 480, 30 planes x 6 sub-planes, 8-bit: frame time against the number of lights 1..5
and the time per light (slope of a least-squares line).

Paper (GeForce2 GTS): 1.2 s for five lights, 0.4 s for the objects and 0.8 s for the shafts;
time proportional to the number of lights (~0.16 s per light).

    python benchmarks/shafts_fig7.py [--quick]
"""

from __future__ import annotations

import argparse
import functools
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _shafts_common as C  # noqa: E402
from _results import write_results  # noqa: E402


def fig7_row(counts, times, cpus, fit, size, figure) -> dict:
    """The result row. The paper's fig. 7 / section 5.2: five spot lights, the frame time proportional to the
    number of lights. Judged on CPU time (the load disturbs it least): reproduced if one slope per light
    explains it (R^2 >= 0.95); reproduced in shape if the cost is additive per light (R^2 >= 0.95) with
    separate slopes for plain and light-mapped lights, both positive; not reproduced otherwise."""
    per = " / ".join(f"{cpus[k]:.3f}" for k in counts)
    if fit is None:
        status, fitted = "not measured (fewer than 4 light counts)", ""
    else:
        fitted = (f"; CPU = {fit['a0']:.3f} s + {fit['plain']:.3f} s x plain lights + {fit['mapped']:.3f} s x "
                  f"light-mapped lights (R^2 {fit['r2']:.3f}; one slope for all: R^2 {fit['r2_one_slope']:.3f})")
        if fit["r2_one_slope"] >= 0.95:
            status = "reproduced"
        elif fit["r2"] >= 0.95 and fit["plain"] > 0 and fit["mapped"] > 0:
            status = (f"reproduced in shape (additive per light; a light-mapped light costs "
                      f"{fit['mapped'] / fit['plain']:.1f}x a plain one)")
        else:
            status = "not reproduced"
    return dict(area="shafts", target="paper fig. 7: stage of 5 spot lights, frame time proportional to the lights",
                measured=f"CPU s per frame {per} for {' / '.join(map(str, counts))} lights ({counts[-1]} lights: "
                         f"{times[counts[-1]]:.2f} s wall; paper 1.2 s for 5){fitted}",
                status=status,
                notes=f"30 x 6 planes, 8-bit, {size[0]}x{size[1]} (lights 3 and 4 with polka-dot light maps); figure "
                      f"{figure.relative_to(C.REPO)}",
                figures={"lights": counts, "frame_s": [times[k] for k in counts], "cpu_s": [cpus[k] for k in counts],
                         **({"fit_cpu": fit} if fit else {})})


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="120 x 80, lights 1 and 3 (one light-mapped), 1 repeat")
    args = parser.parse_args(argv)

    import equinox as eqx
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from jaxrender.shafts import render_planes

    w, h = (120, 80) if args.quick else (C.PAPER_W, C.PAPER_H)
    counts = [1, 3] if args.quick else [1, 2, 3, 4, 5]  # quick: each count is a compile
    repeats = 1 if args.quick else 2
    white = float(C.RENDER["display_white"])
    print(f"# fig. 7, {w} x {h}, 30 x 6 planes, 8-bit; {C.machine()}")

    render = eqx.filter_jit(functools.partial(render_planes, planes=30, subplanes=6, quantize_bits=8))
    times, cpus, compiles, maps, image = {}, {}, {}, {}, None
    with tempfile.TemporaryDirectory() as tmp:
        for k in counts:
            scene_dict = C.stage_scene(k, w, h, base_dir=Path(tmp))
            maps[k] = sum(1 for s in scene_dict["spotlights"] if s.get("light_map"))
            scene = C.load(scene_dict, Path(tmp))
            image, compiles[k], times[k] = C.timed(render, scene, repeats=repeats)
            cpus[k] = C.timed.cpu
            print(f"  {k} lights: frame {times[k]:.3f} s, {cpus[k]:.3f} CPU s", flush=True)
    slope, intercept = np.polyfit(counts, [times[k] for k in counts], 1)
    rows = [[k, maps[k], f"{compiles[k]:.1f}", f"{times[k]:.3f}", f"{times[k] / k:.3f}", f"{cpus[k]:.3f}"]
            for k in counts]
    text = C.table(["lights", "of which with a polka-dot light map", "compile + 1st run s", "median frame s",
                    "frame s / lights", "median CPU s per frame (2 cores)"], rows)
    print(text)
    print(f"least squares: frame = {intercept:.3f} s + {slope:.3f} s x lights "
          f"(paper: 1.2 s for 5 lights = 0.4 s objects + 0.8 s shafts, ~0.16 s per light)")
    c_slope, c_icept = np.polyfit(counts, [cpus[k] for k in counts], 1)
    print(f"least squares on CPU time: {c_icept:.3f} CPU s + {c_slope:.3f} CPU s x lights")
    fit = None
    if len(counts) >= 4:  # plain and light-mapped lights cost differently: fit both slopes
        design = np.array([[1.0, k - maps[k], maps[k]] for k in counts])
        (a0, b_plain, b_map), *_ = np.linalg.lstsq(design, np.array([times[k] for k in counts]), rcond=None)
        print(f"least squares: frame = {a0:.3f} s + {b_plain:.3f} s x plain lights "
              f"+ {b_map:.3f} s x light-mapped lights")
        y = np.array([cpus[k] for k in counts])
        (a0, b_plain, b_map), *_ = np.linalg.lstsq(design, y, rcond=None)
        print(f"least squares on CPU time: {a0:.3f} CPU s + {b_plain:.3f} CPU s x plain lights "
              f"+ {b_map:.3f} CPU s x light-mapped lights")
        r2 = 1 - float(np.sum((design @ [a0, b_plain, b_map] - y) ** 2) / np.sum((y - y.mean()) ** 2))
        r2_one = 1 - float(np.sum((c_icept + c_slope * np.asarray(counts) - y) ** 2) / np.sum((y - y.mean()) ** 2))
        fit = {"a0": float(a0), "plain": float(b_plain), "mapped": float(b_map), "r2": r2, "r2_one_slope": r2_one}

    fig, ax = plt.subplots(1, 2, figsize=(12, 3.8), gridspec_kw={"width_ratios": [1.5, 1]})
    ax[0].imshow(np.clip(image / white, 0, 1) ** (1 / 2.2))
    ax[0].set_title(f"stage, {counts[-1]} spot lights, 30 x 6 planes, 8-bit")
    ax[0].axis("off")
    ax[1].plot(counts, [times[k] for k in counts], "o-", label="measured")
    ax[1].plot(counts, intercept + slope * np.asarray(counts, dtype=float), "--", label=f"{slope:.3f} s / light")
    ax[1].plot(counts, [cpus[k] for k in counts], "s-", label="CPU seconds (both cores)")
    ax[1].set_xlabel("number of spot lights (3rd and 4th with light maps)")
    ax[1].set_ylabel("seconds per frame")
    ax[1].set_xticks(counts)
    ax[1].legend()
    path = C.save_figure(fig, "shafts_fig7.png", quick=args.quick)
    print(f"figure: {path.relative_to(C.REPO)}")
    write_results("shafts_fig7", [fig7_row(counts, times, cpus, fit, (w, h), path)], quick=args.quick)
    return {"lights": counts, "time": times, "cpu": cpus, "slope": float(slope), "intercept": float(intercept)}


if __name__ == "__main__":
    main()

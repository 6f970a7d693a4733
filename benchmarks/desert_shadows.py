"""Paper 001 section 4: frame time without shadows, with dune shadows, with dune + ripple shadows,
and the horizon-map precompute (paper: 1.5 s, 9.1 s, 10.2 s with 6.8 s precompute). The speed of
horizon maps against numpy and numba peers at equal cores is benchmarks/horizon_speed.py.

    python benchmarks/desert_shadows.py [--quick]
"""

from __future__ import annotations

import argparse
import functools
import os
import time
from pathlib import Path

from _results import cpu_description, write_results  # (benchmarks/ is on sys.path when run as a script)
from _timing import timed

from jaxrender.app.scenes import desert as D
from jaxrender.shadows import horizon_map

FIG = Path(__file__).parent / "figures"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="120x80, 8x8 dunes, 8 texels, all shadows, 1 repeat")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    if args.quick:
        w, h, size = 120, 80, dict(dune_size=8, ripple_size=8, texels=8)
        args.repeats = 1
    else:
        w, h, size = 720, 480, dict(dune_size=64, ripple_size=64, texels=64)
    print(f"# desert shadows, {w}x{h}; {cpu_description()}, load average {os.getloadavg()[0]:.1f} at start",
          flush=True)
    scene = D.desert_scene(**size)
    camera = D.default_camera(scene, width=w, height=h)
    elevation, azimuth = 11.0, 200.0
    rows = []
    imgs = []
    configs = [("no shadows", False, False), ("dune shadows", True, False), ("dune + ripple shadows", True, True)]
    if args.quick:
        configs = configs[-1:]  # the smoke run: one compile, every shadow path
    for name, dune, ripple in configs:
        kw = dict(sun_elevation=elevation, sun_azimuth=azimuth, dune_shadows=dune, ripple_shadows=ripple, dust=False)
        c, _ = timed(lambda: D.desert_frame(scene, camera, **kw), 0)
        cpu0 = time.process_time()
        _, t = timed(lambda: D.desert_frame(scene, camera, **kw), args.repeats)
        cpu = (time.process_time() - cpu0) / (args.repeats + 1)  # timed() calls once more before its repeats
        imgs.append(D.to_display(D.desert_frame(scene, camera, **kw)))
        rows.append((name, c, t, cpu))
        print(f"{name}: compile {c:.1f} s, frame {t:.3f} s, {cpu:.3f} CPU s", flush=True)
    # horizon-map precompute of the scene's ripple map
    hz = functools.partial(horizon_map, directions=8, texel_size=1.0 / size["texels"])  # jitted itself
    c_pre, t_pre = timed(lambda: hz(scene.ripple_height), args.repeats)
    print()
    print(f"{w}x{h}, {size['dune_size']}^2 dune quads, ripple maps up to {size['texels']}^2 per quad, LOD + culling, "
          f"sun elevation {elevation} deg, no dust")
    print("| configuration | frame (s) | CPU s per frame (all threads) | compile (s) |")
    print("|---|---|---|---|")
    for name, c, t, cpu in rows:
        print(f"| {name} | {t:.3f} | {cpu:.3f} | {c:.1f} |")
    print(f"| horizon-map precompute ({size['ripple_size']}^2 x 8) | {t_pre:.4f} | | {c_pre:.1f} |")
    _, _, frame_s, frame_cpu = rows[-1]  # dune + ripple shadows
    load = os.getloadavg()[0]
    others = "; ".join(f"{name} {t:.3f} s" for name, _, t, _ in rows[:-1])
    write_results("desert_shadows", [dict(
        area="desert", target="720x480 frame with dune + ripple shadows <= 2 s (paper 10.2 s)",
        measured=f"{frame_s:.3f} s wall (median of {args.repeats}), {frame_cpu:.3f} s CPU (mean)"
                 + (f"; {others}" if others else "")
                 + f"; ripple horizon map {size['ripple_size']}^2 x 8 in {t_pre * 1e3:.1f} ms (paper: 6.8 s)",
        status=("met" if frame_s <= 2.0 else "missed")
               + (f" at load {load:.1f} (wall)" if load > (os.cpu_count() or 1) else ""),
        notes="paper: 1.5 s without shadows, 9.1 s with dune shadows, 10.2 s with both (Pentium III); LOD + culling, "
              "sun 11 deg, no dust; figure benchmarks/figures/desert_shadows.png",
        figures={"frames_s": {name: t for name, _, t, _ in rows}, "frames_cpu_s": {name: c for name, _, _, c in rows},
                 "horizon_precompute_s": t_pre})],
        quick=args.quick)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, len(rows), figsize=(5 * len(rows), 3.6), squeeze=False)
    for a, img, (name, _, t, _) in zip(ax[0], imgs, rows):
        a.imshow(img)
        a.set_title(f"{name} ({t:.2f} s)")
        a.axis("off")
    FIG.mkdir(exist_ok=True)
    fig.savefig(FIG / ("desert_shadows_quick.png" if args.quick else "desert_shadows.png"), dpi=80, bbox_inches="tight")


if __name__ == "__main__":
    main()

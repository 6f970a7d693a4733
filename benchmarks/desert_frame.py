"""Full desert frame: 720 x 480, 64 x 64 dunes, ripple maps up to 64 x 64 per
quad, LOD + culling, dune and ripple shadows, dust. Target: <= 2 s per frame after compilation.
The peer in the same run is the same frame without culling and LOD (every quad at 64 x 64).

    python benchmarks/desert_frame.py [--quick] [--no-peer]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import jax
from _results import cpu_description, write_results  # (benchmarks/ is on sys.path when run as a script)
from _timing import timed

from jaxrender.app.scenes import desert as D
from jaxrender.io import write_png

FIG = Path(__file__).parent / "figures"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="120x80, 8^2 dunes and texels, 1 repeat, no peer")
    parser.add_argument("--no-peer", action="store_true", help="skip the no-culling, no-LOD frame")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    if args.quick:
        w, h, size = 120, 80, dict(dune_size=8, ripple_size=8, texels=8)
        args.repeats, args.no_peer = 1, True  # the no-LOD frame is a second compile (desert_lod --quick renders one)
    else:
        w, h, size = 720, 480, dict(dune_size=64, ripple_size=64, texels=64)
    print(f"# desert frame, {w}x{h}; {cpu_description()}, load average {os.getloadavg()[0]:.1f} at start", flush=True)
    start = time.perf_counter()
    scene = D.desert_scene(**size)
    jax.block_until_ready(scene)
    scene_s = time.perf_counter() - start
    camera = D.default_camera(scene, width=w, height=h)
    rows = []
    configs = [("LOD + culling", True, True)] + ([] if args.no_peer else [("no LOD, no culling", False, False)])
    for name, lod, culling in configs:
        kw = dict(lod=lod, culling=culling)
        c, _ = timed(lambda: D.desert_frame(scene, camera, **kw), 0)
        repeats = args.repeats if lod else 1
        cpu0 = time.process_time()
        _, t = timed(lambda: D.desert_frame(scene, camera, **kw), repeats)
        cpu = (time.process_time() - cpu0) / (repeats + 1)  # timed() calls once more before its repeats
        rows.append((name, c, t, cpu))
        print(f"{name}: compile {c:.1f} s, frame {t:.3f} s, {cpu:.3f} CPU s", flush=True)
        if lod:
            FIG.mkdir(exist_ok=True)
            write_png(FIG / ("desert_frame_quick.png" if args.quick else "desert_frame.png"),
                      D.to_display(D.desert_frame(scene, camera, **kw)), srgb=False)
    print()
    print(f"{w}x{h}, {size['dune_size']}^2 dune quads, ripple maps up to {size['texels']}^2 per quad, "
          f"both shadows, dust; scene build (automata + maps) {scene_s:.1f} s")
    print("| frame | time after compilation (s) | CPU s per frame (all threads) | compile (s) | ratio |")
    print("|---|---|---|---|---|")
    for name, c, t, cpu in rows:
        print(f"| {name} | {t:.3f} | {cpu:.3f} | {c:.1f} | {rows[-1][2] / t:.1f}x |")
    _, compile_s, frame_s, frame_cpu = rows[0]
    peer = ""
    if len(rows) > 1:
        peer = (f"; {rows[-1][2] / frame_s:.1f}x faster (wall) than the same frame without LOD and culling "
                f"({rows[-1][2]:.2f} s, same run)")
    load = os.getloadavg()[0]
    verdict = "met" if frame_s <= 2.0 else "missed"
    write_results("desert_frame", [dict(
        area="desert", target="full 720x480 frame <= 2 s",
        measured=f"{frame_s:.3f} s wall (median of {args.repeats} frames), {frame_cpu:.3f} s CPU (mean), after a "
                 f"{compile_s:.0f} s compile{peer}",
        status=verdict + (f" at load {load:.1f} (wall)" if load > (os.cpu_count() or 1) else ""),
        notes=f"LOD + culling, dune and ripple shadows, dust; {size['dune_size']}^2 dunes, ripple maps up to "
              f"{size['texels']}^2 per quad; figure benchmarks/figures/desert_frame.png",
        figures={"frame_s": frame_s, "frame_cpu_s": frame_cpu, "compile_s": compile_s,
                 **({"no_lod_frame_s": rows[-1][2]} if peer else {})})],
        quick=args.quick)


if __name__ == "__main__":
    main()

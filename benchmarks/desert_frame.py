"""Full desert frame: 720 x 480, 64 x 64 dunes, ripple maps up to 64 x 64 per
quad, LOD + culling, dune and ripple shadows, dust. Target: <= 2 s per frame after compilation.
The peer in the same run is the same frame without culling and LOD (every quad at 64 x 64).

    python benchmarks/desert_frame.py [--quick] [--no-peer]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax
from _timing import timed  # noqa: E402  (benchmarks/ is on sys.path when run as a script)

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
    start = time.perf_counter()
    scene = D.desert_scene(**size)
    jax.block_until_ready(scene)
    scene_s = time.perf_counter() - start
    camera = D.default_camera(scene, width=w, height=h)
    rows = []
    configs = [("LOD + culling", True, True)] + ([] if args.no_peer else [("no LOD, no culling", False, False)])
    for name, lod, culling in configs:
        kw = dict(lod=lod, culling=culling)
        c, t = timed(lambda: D.desert_frame(scene, camera, **kw), args.repeats if lod else 1)
        rows.append((name, c, t))
        print(f"{name}: compile {c:.1f} s, frame {t:.3f} s", flush=True)
        if lod:
            FIG.mkdir(exist_ok=True)
            write_png(FIG / ("desert_frame_quick.png" if args.quick else "desert_frame.png"),
                      D.to_display(D.desert_frame(scene, camera, **kw)), srgb=False)
    print()
    print(f"{w}x{h}, {size['dune_size']}^2 dune quads, ripple maps up to {size['texels']}^2 per quad, "
          f"both shadows, dust; scene build (automata + maps) {scene_s:.1f} s")
    print("| frame | time after compilation (s) | compile (s) | ratio |")
    print("|---|---|---|---|")
    for name, c, t in rows:
        print(f"| {name} | {t:.3f} | {c:.1f} | {rows[-1][2] / t:.1f}x |")


if __name__ == "__main__":
    main()

"""Paper 001 section 4: frame time without shadows, with dune shadows, with dune + ripple shadows,
and the horizon-map precompute (paper: 1.5 s, 9.1 s, 10.2 s with 6.8 s precompute). The speed of
horizon maps against numpy and numba peers at equal cores is benchmarks/horizon_speed.py.

    python benchmarks/desert_shadows.py [--quick]
"""

from __future__ import annotations

import argparse
import functools
from pathlib import Path

from _timing import timed  # noqa: E402  (benchmarks/ is on sys.path when run as a script)

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
        c, t = timed(lambda: D.desert_frame(scene, camera, **kw), args.repeats)
        imgs.append(D.to_display(D.desert_frame(scene, camera, **kw)))
        rows.append((name, c, t))
        print(f"{name}: compile {c:.1f} s, frame {t:.3f} s", flush=True)
    # horizon-map precompute of the scene's ripple map
    hz = functools.partial(horizon_map, directions=8, texel_size=1.0 / size["texels"])  # jitted itself
    c_pre, t_pre = timed(lambda: hz(scene.ripple_height), args.repeats)
    print()
    print(f"{w}x{h}, {size['dune_size']}^2 dune quads, ripple maps up to {size['texels']}^2 per quad, LOD + culling, "
          f"sun elevation {elevation} deg, no dust")
    print("| configuration | frame (s) | compile (s) |")
    print("|---|---|---|")
    for name, c, t in rows:
        print(f"| {name} | {t:.3f} | {c:.1f} |")
    print(f"| horizon-map precompute ({size['ripple_size']}^2 x 8) | {t_pre:.4f} | {c_pre:.1f} |")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, len(rows), figsize=(5 * len(rows), 3.6), squeeze=False)
    for a, img, (name, _, t) in zip(ax[0], imgs, rows):
        a.imshow(img)
        a.set_title(f"{name} ({t:.2f} s)")
        a.axis("off")
    FIG.mkdir(exist_ok=True)
    fig.savefig(FIG / ("desert_shadows_quick.png" if args.quick else "desert_shadows.png"), dpi=80, bbox_inches="tight")


if __name__ == "__main__":
    main()

"""Paper 001 section 4: frame time without shadows, with dune shadows, with dune + ripple shadows,
and the horizon-map precompute (paper: 1.5 s, 9.1 s, 10.2 s with 6.8 s precompute); and the
speed of horizon maps for 256 x 256 x 8 directions against a vectorized numpy brute force
(target >= 10x, issue 3 section 4).

    python benchmarks/desert_shadows.py [--quick]
"""

from __future__ import annotations

import argparse
import functools
import math
import statistics
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from _timing import timed  # noqa: E402  (benchmarks/ is on sys.path when run as a script)
from jaxrender.app.scenes import desert as D
from jaxrender.shadows import horizon_directions, horizon_map

FIG = Path(__file__).parent / "figures"


def horizon_numpy(h: np.ndarray, directions: int = 8) -> np.ndarray:
    """Vectorized numpy brute force: for every step k of every lattice direction, one np.roll of
    the whole field (note 2's periodic path), slopes clamped at 0."""
    n = h.shape[0]
    best = np.zeros((directions,) + h.shape, h.dtype)
    for d, (ex, ey) in enumerate(horizon_directions(directions)):
        length = math.hypot(ex, ey)
        for k in range(1, n):
            np.maximum(best[d], (np.roll(h, (-k * int(ey), -k * int(ex)), axis=(0, 1)) - h) / (k * length), out=best[d])
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="360x240, 32x32 dunes, 32 texels per quad")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--horizon-only", action="store_true", help="only the horizon-map timings")
    args = parser.parse_args()
    if args.quick:
        w, h, size = 360, 240, dict(dune_size=32, ripple_size=32, texels=32)
    else:
        w, h, size = 720, 480, dict(dune_size=64, ripple_size=64, texels=64)
    scene = D.desert_scene(**size)
    camera = D.default_camera(scene, width=w, height=h)
    elevation, azimuth = 11.0, 200.0
    rows = []
    imgs = []
    configs = [] if args.horizon_only else [("no shadows", False, False), ("dune shadows", True, False),
                                            ("dune + ripple shadows", True, True)]
    for name, dune, ripple in configs:
        kw = dict(sun_elevation=elevation, sun_azimuth=azimuth, dune_shadows=dune, ripple_shadows=ripple, dust=False)
        c, t = timed(lambda: D.desert_frame(scene, camera, **kw), args.repeats)
        imgs.append(D.to_display(D.desert_frame(scene, camera, **kw)))
        rows.append((name, c, t))
        print(f"{name}: compile {c:.1f} s, frame {t:.3f} s", flush=True)
    # horizon-map precompute of the scene's ripple map
    hz = functools.partial(horizon_map, directions=8, texel_size=1.0 / size["texels"])  # jitted itself
    c_pre, t_pre = timed(lambda: hz(scene.ripple_height), args.repeats)
    # 256 x 256 x 8 vs numpy: a ripple field grown by the automaton (what the scene uses), and a
    # synthetic field with long, slowly varying crests (a harder case for the early exit)
    from sims.ripples import RippleParams, init_ripples, simulate_ripples

    grown = np.asarray(simulate_ripples(init_ripples(jax.random.key(5), (256, 256)), RippleParams(),
                                        steps=500 if args.quick else 3000), np.float32)
    grown = (grown - grown.mean()) * (0.35 / (np.max(np.abs(np.roll(grown, -1, 1) - np.roll(grown, 1, 1))) / 2))
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:256, 0:256] / 256 * 2 * np.pi
    synthetic = np.sin(20 * x + 2 * np.sin(3 * y)) + 0.3 * np.sin(40 * x + 5 * y) + 0.05 * rng.standard_normal((256, 256))
    hz256 = functools.partial(horizon_map, directions=8)  # jitted itself (its own compiler options)
    horizon_rows = []
    for label, field in [("automaton ripples (3000 steps)", grown), ("synthetic long crests + noise", synthetic)]:
        field = np.asarray(field, np.float32)
        c256, t256 = timed(lambda: hz256(jnp.asarray(field)), max(5, args.repeats))
        np_times = []
        for _ in range(3 if not args.quick else 1):
            start = time.perf_counter()
            ref = horizon_numpy(field)
            np_times.append(time.perf_counter() - start)
        t_np = statistics.median(np_times)
        err = float(np.max(np.abs(np.asarray(hz256(jnp.asarray(field))) - ref)))
        horizon_rows.append((label, t_np, t256, err, c256))
        print(f"horizon 256^2 x 8, {label}: numpy {t_np:.3f} s, jax {t256:.4f} s, max err {err:.1e}", flush=True)
    print()
    print(f"{w}x{h}, {size['dune_size']}^2 dune quads, ripple maps up to {size['texels']}^2 per quad, LOD + culling, "
          f"sun elevation {elevation} deg, no dust")
    print("| configuration | frame (s) | compile (s) |")
    print("|---|---|---|")
    for name, c, t in rows:
        print(f"| {name} | {t:.3f} | {c:.1f} |")
    print(f"| horizon-map precompute ({size['ripple_size']}^2 x 8) | {t_pre:.4f} | {c_pre:.1f} |")
    print()
    print("| horizon maps 256x256 x 8 | numpy vectorized brute force (s) | horizon_map, jit (s) | ratio | max abs diff |")
    print("|---|---|---|---|---|")
    for label, t_np, t256, err, c256 in horizon_rows:
        print(f"| {label} | {t_np:.3f} | {t256:.4f} | {t_np / t256:.1f}x | {err:.1e} |")
    if args.horizon_only:
        return
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(15, 3.6))
    for a, img, (name, _, t) in zip(ax, imgs, rows):
        a.imshow(img)
        a.set_title(f"{name} ({t:.2f} s)")
        a.axis("off")
    FIG.mkdir(exist_ok=True)
    fig.savefig(FIG / ("desert_shadows_quick.png" if args.quick else "desert_shadows.png"), dpi=80, bbox_inches="tight")


if __name__ == "__main__":
    main()

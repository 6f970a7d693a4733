"""The headline frames on whatever backend JAX runs on (a GPU check of the CPU benchmarks).

    python benchmarks/device_frames.py [--quick] [--repeats 5] [--json OUT.json]

Times, compile apart (first call), min / median / max wall seconds of `--repeats` calls:
- light shafts at 720 x 480, float32: the textured spot (examples/scenes/spot_sphere.json with
  dots.png) by the equiangular method at 32 samples, the five-spot stage by the equiangular method
  at 24 samples, the ray march at 24 samples and the paper's 8-bit planes (30 x 6): each method's
  setting that reaches 2 % in benchmarks/shafts_interactive.py; and the gradient of an image loss
  over the spot scene against its forward pass;
- the moving Noh garment at 720 x 480 (`render_noh(moving=True)`: cloth, shadow maps, PCSS,
  mips and the polished floor every frame), as `jaxrender noh --time` measures it.
Prints the backend and device, a table, and writes the rows as JSON with `--json`. It does not touch
RESULTS.md: the CPU figures come from shafts_interactive.py and noh_frame.py, this script gives
the same frames on another device (RESULTS, section "On a GPU").
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from shafts_interactive import spot_scene  # noqa: E402

from jaxrender.app.scenes import load_stage_scene, render_noh  # noqa: E402
from jaxrender.shafts import render  # noqa: E402


def timed(fn, *args, repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - t0
    runs = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        runs.append(time.perf_counter() - t0)
    return compile_s, runs


def row(name, compile_s, runs, **extra):
    out = dict(name=name, compile_s=compile_s, min_s=min(runs), median_s=statistics.median(runs), max_s=max(runs),
               **extra)
    print(f"{name:44s} compile {compile_s:6.1f} s   wall {out['min_s']:.4f} / {out['median_s']:.4f} / "
          f"{out['max_s']:.4f} s", flush=True)
    return out


def shafts_rows(width, height, repeats, quick):
    spot, stage = spot_scene(width, height), load_stage_scene().with_size(width, height)
    cases = [("spot, equiangular 32 samples", spot, dict(method="equiangular", samples=32)),
             ("stage, equiangular 24 samples", stage, dict(method="equiangular", samples=24)),
             ("stage, ray march 24 samples", stage, dict(method="raymarch", samples=24)),
             ("stage, planes 30x6 8-bit", stage, dict(method="planes", planes=30, subplanes=6, quantize_bits=8))]
    rows = []
    for name, scene, options in cases[:1] if quick else cases:
        fn = jax.jit(lambda s, options=options: render(s, **options))
        rows.append(row(name, *timed(fn, scene, repeats=repeats)))
    if quick:
        return rows
    weights = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, (height, width, 3)), dtype=jnp.float32)

    def loss(p):
        s = eqx.tree_at(lambda s: (s.medium.rho, s.medium.kappa, s.lights[0].position), spot, p)
        return jnp.sum(weights * render(s, samples=32))

    p0 = (spot.medium.rho, spot.medium.kappa, spot.lights[0].position)
    forward = row("spot, loss forward", *timed(jax.jit(loss), p0, repeats=repeats))
    grad = row("spot, loss value and gradient", *timed(jax.jit(jax.value_and_grad(loss)), p0, repeats=repeats))
    grad["ratio_to_forward"] = grad["median_s"] / forward["median_s"]
    print(f"gradient / forward: {grad['ratio_to_forward']:.2f}x")
    return rows + [forward, grad]


def noh_row(width, height, repeats):
    info: dict = {}
    t0 = time.perf_counter()
    render_noh(frames=3, width=width, height=height, info=info, time_repeats=repeats)
    total = time.perf_counter() - t0
    return row("Noh, moving garment, every frame", info["compile_s"], info["timed_s"], prepare_s=info["prepare_s"],
               total_s=total)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke test: 120x80, 1 repeat, the spot scene "
                        "only (the other frames' code runs in shafts_interactive.py and noh_frame.py --quick)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", type=Path, help="write the rows here")
    args = parser.parse_args(argv)
    width, height = (120, 80) if args.quick else (720, 480)
    repeats = 1 if args.quick else args.repeats
    device = jax.devices()[0]
    print(f"backend {jax.default_backend()}, device {device.device_kind}, jax {jax.__version__}", flush=True)
    rows = shafts_rows(width, height, repeats, args.quick) + ([] if args.quick else [noh_row(width, height, repeats)])
    if args.json is not None:
        args.json.write_text(json.dumps(dict(backend=jax.default_backend(), device=device.device_kind,
                                             size=f"{width}x{height}", rows=rows), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

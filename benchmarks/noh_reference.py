"""The composed Noh frame against its float64 brute-force reference (tests/noh_reference.py), the
figures of tests/test_noh_bruteforce.py at its size: for both motions and both frames, in float64
and float32, the relative RMS where the frame must match and where it may differ (penumbrae,
shadow edges, reflected edges), and a difference map per case: benchmarks/figures/noh_reference_<case>.png
(left to right: the production frame, the reference, |difference| / the reference's mean over the
image x 4, the pixels that may differ in red). Rows "Noh reference" to benchmarks/results/noh_reference.json.

Run: `python benchmarks/noh_reference.py` (about 5 min CPU); `--quick`: the built-in dance's first
frame in float64 at 48 x 32, no figures (a smoke run).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from _results import cpu_description, write_results  # noqa: E402
from noh_reference import (  # noqa: E402
    FRAMES,
    case_scene,
    float32_frames,
    may_differ,
    production_frame,
    reference_inputs,
    relative_rms,
    render_reference,
    small_scene,
    state_before,
)
from test_noh_bruteforce import GLOW, RADIUS, SHADOW_RESOLUTION, SHARE, SIZE  # noqa: E402

from jaxrender.io import linear_to_srgb, write_png  # noqa: E402

FIGURES = Path(__file__).resolve().parent / "figures"
TARGET = 0.02   # relative RMS where the frame must match, float32 and float64


def difference_map(image: np.ndarray, ref, differ: np.ndarray) -> np.ndarray:
    scale = 1.0 / max(float(np.percentile(ref.image, 99)), 1e-9)
    show = lambda a: np.clip(np.asarray(linear_to_srgb(np.clip(a * scale, 0, 1))), 0, 1)  # noqa: E731
    diff = np.abs(image - ref.image).mean(-1) / max(float(ref.image.mean()), 1e-12) * 0.25
    heat = np.stack([np.clip(diff, 0, 1)] * 3, -1)
    marked = heat.copy()
    marked[differ] = 0.5 * marked[differ] + np.asarray([0.5, 0.0, 0.0])
    return np.concatenate([show(image), show(ref.image), marked], axis=1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one frame, float64, 48 x 32 (a smoke run)")
    args = parser.parse_args()
    cases, size = ({"built-in": (FRAMES["built-in"][0],)}, (48, 32)) if args.quick else (FRAMES, SIZE)
    t0, c0 = time.perf_counter(), time.process_time()
    out, states, scenes = {}, {}, {}
    with jax.numpy_rank_promotion("allow"):
        for label, frames in cases.items():
            scene = scenes[label] = case_scene(label, *size, **small_scene())
            for frame in frames:
                state = state_before(scene, frame)
                states.update({f"{label}_{frame}_{k}": np.asarray(getattr(state, k)) for k in ("x", "x_prev", "time")})
                image, new_state, _ = production_frame(scene, frame, state, shadow_resolution=SHADOW_RESOLUTION)
                ref = render_reference(scene, reference_inputs(scene, frame, new_state))
                out[(label, frame, "float64")] = image, ref
        spec = dict(width=size[0], height=size[1], shadow_resolution=SHADOW_RESOLUTION, cases=cases)
        with tempfile.TemporaryDirectory() as tmp:
            for (label, frame), (image, fr, scene32) in ({} if args.quick else
                                                         float32_frames(spec, states, scenes, Path(tmp))).items():
                out[(label, frame, "float32")] = image, render_reference(scene32, fr)
    rows, figures = [], {}
    FIGURES.mkdir(exist_ok=True)
    for (label, frame, dtype), (image, ref) in sorted(out.items()):
        differ = may_differ(ref, radius=RADIUS, share=SHARE, glow=GLOW)
        must, may = relative_rms(image, ref.image, ~differ), relative_rms(image, ref.image, differ)
        perf = relative_rms(image, ref.image, ref.performer)
        name = f"{label.replace('-', '')}_{frame}_{dtype}"
        figures[name] = dict(must_match_rms=must, may_differ_rms=may, performer_rms=perf,
                             must_match_share=float((~differ).mean()))
        if not args.quick:
            write_png(FIGURES / f"noh_reference_{name}.png", difference_map(image, ref, differ))
        print(f"{label} frame {frame} {dtype}: must match {(~differ).mean():.2f} of the image, relative RMS "
              f"{must:.4f}; may differ {may:.4f}; performer {perf:.4f}", flush=True)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    for dtype in ("float64",) if args.quick else ("float64", "float32"):
        worst = max(v["must_match_rms"] for k, v in figures.items() if k.endswith(dtype))
        may = [v["may_differ_rms"] for k, v in figures.items() if k.endswith(dtype)]
        rows.append(dict(
            area="noh", target=f"composed frame vs brute force, relative RMS outside the penumbrae <= "
                                          f"{TARGET:.0%} ({dtype})",
            measured=f"worst {worst:.4f} over {sum(map(len, cases.values()))} frames at {size[0]}x{size[1]}; "
                     f"where they may differ {min(may):.3f}-{max(may):.3f}; {wall:.0f} s wall, {cpu:.0f} s CPU, load "
                     f"{os.getloadavg()[0]:.1f}, {cpu_description()}",
            status="met" if worst <= TARGET else "missed",
            figures={k: v for k, v in figures.items() if k.endswith(dtype)}))
    write_results("noh_reference", rows, quick=args.quick)


if __name__ == "__main__":
    main()

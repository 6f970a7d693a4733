"""Light shafts (paper 000): frame time of the sample-plane method, gradient cost, and speed
against the ray march at equal error vs. the exact integral.

    python benchmarks/shafts_speed.py [--quick] [--no-results]

Scene: examples/scenes/spot_sphere.json (one spot light, a sphere, a floor), 720 x 480.
1. planes 30 x 6 (float and 8-bit): compile time apart, median frame time.
2. gradient of an image loss w.r.t. rho, kappa, K, spot intensity and position vs. the forward time.
3. equal error: each method's cheapest setting reaching 2 % relative RMS of the in-scattered light
   (the shafts) vs. a converged ray march (512 samples), and the time ratio. Both times are of the
   whole frame (surfaces included).
Prints a table; without --no-results (and without --quick) it writes the table into
benchmarks/RESULTS.md under "### vs. ray march and per-frame time".
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from _timing import timed  # noqa: E402  (benchmarks/ is on sys.path when run as a script)

from jaxrender.app.scenes import load_shafts_scene  # noqa: E402
from jaxrender.shafts import render_planes, render_raymarch  # noqa: E402

TARGET_ERR = 0.02
SECTION = "### vs. ray march and per-frame time"


def rel_rms(x, ref):
    return float(jnp.linalg.norm(x - ref) / jnp.linalg.norm(ref))


def gradient_times(scene, repeats):
    """(compile s, median s of value_and_grad, median s of the forward) of a weighted image loss of the
    30x6 planes frame w.r.t. rho, kappa, K, the spot's intensity and position."""
    weights = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, (scene.camera.height, scene.camera.width, 3)),
                          dtype=jnp.float32)

    def with_params(p):
        s = eqx.tree_at(lambda s: (s.medium.rho, s.medium.kappa, s.medium.K), scene, (p["rho"], p["kappa"], p["K"]))
        return eqx.tree_at(lambda s: (s.lights[0].intensity, s.lights[0].position), s, (p["intensity"], p["position"]))

    light = scene.lights[0]
    params = dict(rho=scene.medium.rho, kappa=scene.medium.kappa, K=scene.medium.K,
                  intensity=light.intensity, position=light.position)
    loss = lambda p: jnp.sum(weights * render_planes(with_params(p), planes=30, subplanes=6))  # noqa: E731
    fwd, grad = jax.jit(loss), jax.jit(jax.value_and_grad(loss))
    _, t_loss = timed(lambda: fwd(params), repeats)
    c_g, t_g = timed(lambda: grad(params), repeats)
    return c_g, t_g, t_loss


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="120 x 80, one setting per study, 1 repeat, no gradient (smoke)")
    parser.add_argument("--no-results", action="store_true", help="do not edit benchmarks/RESULTS.md")
    parser.add_argument("--error-size", default="360x240", help="image size of the equal-error study (WxH)")
    args = parser.parse_args(argv)

    load = os.getloadavg()[0]
    scene = load_shafts_scene(ROOT / "examples" / "scenes" / "spot_sphere.json")
    if args.quick:  # a smoke run: every section once at a small size (each setting is a compile)
        scene = scene.with_size(120, 80)
    repeats = 1 if args.quick else 7
    W, H = scene.camera.width, scene.camera.height
    rows = []

    # 1. frame time
    planes_f = jax.jit(lambda s: render_planes(s, planes=30, subplanes=6))
    c_f, t_f = timed(lambda: planes_f(scene), repeats)
    rows.append((f"planes 30x6 float, {W}x{H}", c_f, t_f, "<= 0.17 s/frame", "met" if t_f <= 0.17 else "MISSED"))
    planes_q = jax.jit(lambda s: render_planes(s, planes=30, subplanes=6, quantize_bits=8))
    c_q, t_q = (c_f, t_f) if args.quick else timed(lambda: planes_q(scene), repeats)  # quick: 8-bit in fig4/sec51
    rows.append((f"planes 30x6 8-bit, {W}x{H}", c_q, t_q, "<= 0.17 s/frame", "met" if t_q <= 0.17 else "MISSED"))
    print(f"frame: float {t_f:.3f} s (compile {c_f:.1f} s), 8-bit {t_q:.3f} s", flush=True)

    # 2. gradient of an image loss w.r.t. medium and light parameters
    if args.quick:  # its compile was a third of the smoke run; tests/test_shafts.py checks the gradient's values
        print("gradient: not timed with --quick", flush=True)
    else:
        c_g, t_g, t_loss = gradient_times(scene, repeats)
        ratio_g = t_g / t_loss
        rows.append(("value_and_grad (rho, kappa, K, I, pos)", c_g, t_g, "<= 4x forward",
                     f"{ratio_g:.2f}x forward: " + ("met" if ratio_g <= 4 else "MISSED")))
        print(f"gradient: {t_g:.3f} s = {ratio_g:.2f} x forward {t_loss:.3f} s (compile {c_g:.1f} s)", flush=True)

    # 3. equal error vs the exact integral (converged ray march)
    ew, eh = (120, 80) if args.quick else tuple(int(x) for x in args.error_size.split("x"))
    small = scene.with_size(ew, eh)
    # error of the in-scattered light (the shafts): the surfaces are the same computation in both
    # methods and would swamp the comparison (they converge with any sample count)
    ref_samples = 64 if args.quick else 512
    ref = jax.jit(lambda s: render_raymarch(s, samples=ref_samples, batch_size=128, return_parts=True)[1][1])(small)
    ref = jax.block_until_ready(ref)
    march = []
    # every count up to 8 (8 samples already give ~1.4 %): the ray march at its cheapest 2 % count
    counts = (8,) if args.quick else (4, 5, 6, 7, 8, 10, 12, 16, 24, 32, 48, 64, 96, 128)  # quick: a smoke run
    for samples in counts:
        # returns (image, scattering): the whole frame is computed and timed
        fn = jax.jit(lambda s, n=samples: (lambda out: (out[0], out[1][1]))(
            render_raymarch(s, samples=n, return_parts=True)))
        _, t = timed(lambda: fn(small), 3)
        err = rel_rms(fn(small)[1], ref)
        march.append((samples, err, t))
        print(f"  ray march {samples:4d} samples: err {err:.4f} time {t:.4f}", flush=True)
        if err <= TARGET_ERR:
            break
    plane_runs = []
    for g_pp in (False,) if args.quick else (False, True):  # the paper's 15x10 tex-coordinate mesh, then g per pixel
        plane_settings = ((8, 4),) if args.quick else ((4, 2), (6, 2), (8, 2), (6, 3), (8, 3), (6, 4), (8, 4), (12, 3),
                                                         (16, 4), (24, 6), (30, 6), (48, 8))
        for n, m in plane_settings:
            fn = jax.jit(lambda s, n=n, m=m, g_pp=g_pp: (lambda out: (out[0], sum(out[1][1])))(
                render_planes(s, planes=n, subplanes=m, g_per_pixel=g_pp, tables=not g_pp, return_parts=True)))
            _, t = timed(lambda: fn(small), 3)
            err = rel_rms(fn(small)[1], ref)
            label = f"{n}x{m}" + (", g per pixel" if g_pp else ", mesh 15x10 + tables")
            plane_runs.append((label, err, t))
            print(f"  planes {label}: err {err:.4f} time {t:.4f}", flush=True)
            if err <= TARGET_ERR:  # the next settings of this family cost more
                break
    # each method's fastest setting that reaches the target error
    m_ok = sorted((r for r in march if r[1] <= TARGET_ERR), key=lambda r: r[2])
    p_ok = sorted((r for r in plane_runs if r[1] <= TARGET_ERR), key=lambda r: r[2])
    if m_ok and p_ok:
        speedup = m_ok[0][2] / p_ok[0][2]
        verdict = f"{speedup:.2f}x: " + ("met" if speedup >= 5 else "MISSED")
        rows.append((f"ray march, {ew}x{eh}, {m_ok[0][0]} samples (err {m_ok[0][1]:.4f})", float("nan"), m_ok[0][2],
                     "", ""))
        rows.append((f"planes, {ew}x{eh}, {p_ok[0][0]} (err {p_ok[0][1]:.4f})", float("nan"), p_ok[0][2],
                     ">= 5x faster at 2 % error", verdict))
    else:
        rows.append(("equal-error study", float("nan"), float("nan"), ">= 5x faster at 2 % error",
                     "2 % not reached by " + ("planes" if not p_ok else "ray march")))

    header = "| case | compile (s) | time (s) | target | result |\n|---|---|---|---|---|"
    lines = [header] + [f"| {a} | {'' if np.isnan(b) else f'{b:.1f}'} | {c:.4f} | {d} | {e} |"
                        for a, b, c, d, e in rows]
    table = "\n".join(lines)
    sweep = ["", "Equal-error sweep (relative RMS of the in-scattered light vs. a 512-sample ray march; "
             "median time of the whole frame):", "",
             "| method | setting | rel. RMS | time (s) |", "|---|---|---|---|"]
    sweep += [f"| ray march | {s} samples | {e:.4f} | {t:.4f} |" for s, e, t in march]
    sweep += [f"| planes | {label} | {e:.4f} | {t:.4f} |" for label, e, t in plane_runs]
    text = table + "\n" + "\n".join(sweep)
    print()
    print(text)
    if not args.quick and not args.no_results:
        machine = (f"{platform.machine()}, {os.cpu_count()} CPU cores, jax {jax.__version__} "
                   f"({jax.default_backend()}), float32")
        write_results(f"{SECTION}\n\nCommand: `python benchmarks/shafts_speed.py` ({machine}; load average "
                      f"{load:.1f} at the start: other jobs on the 2 cores inflate the times). Reading and history "
                      f"in the next section.\n\n{text}\n")
    return 0


def write_results(block: str) -> None:
    """Replace (or add) our sub-section inside '## Light shafts: speed vs. ray march and Mitsuba 3'."""
    path = ROOT / "benchmarks" / "RESULTS.md"
    text = path.read_text()
    heading = "## Light shafts: speed vs. ray march and Mitsuba 3"
    if SECTION in text:
        start = text.index(SECTION)
        nxt = [i for i in (text.find("\n### ", start + 1), text.find("\n## ", start + 1),
                           text.find("\n<!--", start + 1))
               if i != -1]
        end = min(nxt) + 1 if nxt else len(text)
        text = text[:start] + block + "\n" + text[end:]
    else:
        at = text.index(heading) + len(heading)
        text = text[:at] + "\n\n" + block + text[at:]
    path.write_text(text)


if __name__ == "__main__":
    raise SystemExit(main())

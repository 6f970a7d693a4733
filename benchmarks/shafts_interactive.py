"""Light shafts at interactive rates: the equiangular method against the ray march and
the sample planes, each at settings around 2 % error, whole frames (shadow maps and surfaces
included), float32, compile time apart.

    python benchmarks/shafts_interactive.py [--quick] [--size 720x480] [--ref-samples 256]

Scenes: "spot" = examples/scenes/spot_sphere.json with the polka-dot light map dots.png (one
textured spot, a sphere, a floor); "stage" = the gallery's five-spot stage (two light maps).
Error: relative RMS of the in-scattered light (design.md) against a converged ray march
(`--ref-samples`, shadow rays). Times: min / median / max wall and median CPU seconds (this
process, all threads) of `--repeats` frames; the machine is shared: the load average is printed.
Outputs: a table (stdout and benchmarks/results/shafts_interactive.json), the error-vs-time plot
benchmarks/figures/shafts_interactive.png, and renders benchmarks/figures/shafts_interactive_*.png.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import statistics
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

from _results import write_results  # noqa: E402

from jaxrender.app.scenes import load_stage_scene, shafts_scene_from_dict  # noqa: E402
from jaxrender.io import write_image  # noqa: E402
from jaxrender.shadows import render_shadow_map  # noqa: E402
from jaxrender.shafts import render_equiangular, render_planes, render_raymarch  # noqa: E402
from jaxrender.shafts._equiangular import (  # noqa: E402
    active_rays_map,
    bake_light_map,
    equiangular_scattering,
    primary_hits,
)
from jaxrender.shafts._model import (  # noqa: E402
    FAR,
    cone_intervals,
    light_reach,
    shadow_map_visibility,  # noqa: E402
    surface_term,
)

TARGET = 0.02
FIGURES = HERE / "figures"


def spot_scene(width, height):
    d = json.loads((ROOT / "examples" / "scenes" / "spot_sphere.json").read_text())
    d["spotlights"][0]["light_map"] = "dots.png"
    return shafts_scene_from_dict(d, base_dir=ROOT / "examples" / "scenes").with_size(width, height)


def frame_times(fn, scene, repeats):
    """(result, compile s, wall times, median CPU s): the first call apart."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(scene))
    compile_s = time.perf_counter() - t0
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn(scene))
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return out, compile_s, wall, statistics.median(cpu)


def rel(x, ref):
    return float(np.linalg.norm(np.asarray(x, np.float64) - ref) / np.linalg.norm(ref))


def method_fn(method, setting, *, parts: bool):
    """A jitted frame: the image as `jaxrender shafts` renders it (parts=False, the one timed), or
    (image, in-scattered part) for the error (parts=True: per-light images kept, not timed)."""
    if method == "equiangular":
        n, sm = setting
        body = lambda s: render_equiangular(s, samples=n, shadow_map=sm, return_parts=parts)  # noqa: E731
    elif method == "raymarch":
        body = lambda s: render_raymarch(s, samples=setting, return_parts=parts)  # noqa: E731
    else:
        n, m, gpp = setting
        body = lambda s: render_planes(s, planes=n, subplanes=m, g_per_pixel=gpp, tables=not gpp,  # noqa: E731
                                       return_parts=parts)
    if not parts:
        return jax.jit(body)

    def frame(s):
        image, (surface, fog) = body(s)
        return image, (sum(fog) if isinstance(fog, list) else fog)

    return jax.jit(frame)


def label(method, setting):
    if method == "equiangular":
        n, sm = setting
        return f"{n} samples" + (", scene's shadow map (1024)" if sm is None else f", shadow map {sm}")
    if method == "raymarch":
        return f"{setting} samples"
    n, m, gpp = setting
    return f"{n}x{m}" + (", g per pixel" if gpp else ", mesh 15x10 + tables")


def sweep(name, scene, ref, settings, repeats, *, quick=False):
    rows = []
    for method, setting in settings:
        parts_fn = method_fn(method, setting, parts=True)
        image, fog = parts_fn(scene)
        err = rel(fog, ref)
        # quick (a smoke run) times the parts call itself: one compile per setting instead of two
        timed_fn = parts_fn if quick else method_fn(method, setting, parts=False)
        _, c, wall, cpu = frame_times(timed_fn, scene, repeats)
        rows.append(dict(scene=name, method=method, setting=label(method, setting), err=err, compile_s=c,
                         min_s=min(wall), median_s=statistics.median(wall), max_s=max(wall), cpu_s=cpu,
                         image=np.asarray(image)))
        print(f"  {name:5s} {method:11s} {label(method, setting):28s} err {err:.4f}  compile {c:5.1f} s  "
              f"wall {min(wall):.3f}/{statistics.median(wall):.3f}/{max(wall):.3f} s  cpu {cpu:.3f} s  "
              f"load {os.getloadavg()[0]:.1f}", flush=True)
    return rows


def frame_profile(scene, samples, repeats, shadow_map=512):
    """Median wall and CPU seconds of the pieces of an equiangular frame, each jitted on its own
    from the previous pieces' outputs (so a piece's time is its own), and of the whole frame."""
    eye, medium, bias = scene.camera.eye, scene.medium, scene.render.shadow_bias
    hits = jax.jit(primary_hits)(scene)
    dirs, t_hit, normals, albedo, points = hits
    surface_t = jnp.where(jnp.isfinite(t_hit), t_hit, FAR)

    def maps(s):
        return tuple(render_shadow_map(light, s.prims, resolution=shadow_map) for light in s.lights)

    def intervals(s, d, st):
        return [cone_intervals(s, light, d, st, light_reach(s, light)) for light in s.lights]

    shadow_maps, cones = jax.jit(maps)(scene), jax.jit(intervals)(scene, dirs, surface_t)
    baked = jax.jit(lambda s: [bake_light_map(light) for light in s.lights])(scene)

    def surface(s, maps_):
        return surface_term(s, points, normals, albedo, t_hit, shadow_map_visibility(s, maps_))

    def compaction(cones_):  # the gathers and scatters of active_rays_map around an empty kernel
        return sum(active_rays_map(lambda d, a, b: d * (b - a)[:, None], dirs, t0, t1) for t0, t1 in cones_)

    def scattering(s, maps_, cones_, baked_):
        return sum(active_rays_map(functools.partial(equiangular_scattering, light, jax.lax.stop_gradient(sm.depth),
                                                     bk, eye, rho=medium.rho, kappa=medium.kappa, K=medium.K,
                                                     bias=bias, samples=samples), dirs, t0, t1)
                   for light, sm, (t0, t1), bk in zip(s.lights, maps_, cones_, baked_))

    pieces = {"primary hits": (primary_hits, (scene,)), "shadow maps": (maps, (scene,)),
              "surface shading": (surface, (scene, shadow_maps)),
              "cone intervals": (intervals, (scene, dirs, surface_t)),
              "light-map bake": (lambda s: [bake_light_map(light) for light in s.lights], (scene,)),
              "compaction of active runs (empty kernel)": (compaction, (cones,)),
              f"in-scattering, {samples} samples (incl. compaction)": (scattering, (scene, shadow_maps, cones, baked)),
              "whole frame": (lambda s: render_equiangular(s, samples=samples, shadow_map=shadow_map), (scene,))}
    out = {}
    for key, (fn, args) in pieces.items():
        jitted = jax.jit(fn)
        _, _, wall, cpu = frame_times(lambda a, jitted=jitted: jitted(*a), args, repeats)
        out[key] = (statistics.median(wall), cpu)
    return out


def gradient_ratio(scene, samples, repeats):
    weights = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, (scene.camera.height, scene.camera.width, 3)),
                          dtype=jnp.float32)
    light = scene.lights[0]
    params = dict(rho=scene.medium.rho, kappa=scene.medium.kappa, K=scene.medium.K,
                  intensity=light.intensity, position=light.position)

    def with_params(p):
        s = eqx.tree_at(lambda s: (s.medium.rho, s.medium.kappa, s.medium.K), scene, (p["rho"], p["kappa"], p["K"]))
        return eqx.tree_at(lambda s: (s.lights[0].intensity, s.lights[0].position), s, (p["intensity"], p["position"]))

    loss = lambda p: jnp.sum(weights * render_equiangular(with_params(p), samples=samples))  # noqa: E731
    _, c_f, wall_f, cpu_f = frame_times(jax.jit(loss), params, repeats)
    _, c_g, wall_g, cpu_g = frame_times(jax.jit(jax.value_and_grad(loss)), params, repeats)
    return dict(forward_s=statistics.median(wall_f), grad_s=statistics.median(wall_g), compile_grad_s=c_g,
                ratio_wall=statistics.median(wall_g) / statistics.median(wall_f), ratio_cpu=cpu_g / cpu_f)


def stage_ratio_row(eq, rm):
    """The result row of the ray march's time over ours on the stage, each at its cheapest setting reaching 2 %."""
    if eq and rm:
        ratio = rm["median_s"] / eq["median_s"]
        text = f"{ratio:.2f}x wall, {rm['cpu_s'] / eq['cpu_s']:.2f}x CPU (ray march {rm['setting']})"
    else:
        ratio, text = 0.0, "no ratio: a method reached 2 % at none of its settings"
    return dict(area="shafts", target=">= 17x the ray march at 2 % on the stage", measured=text,
                status="met" if ratio >= 17 else "missed")


def reference(name, scene, samples):
    size = f"{scene.camera.width}x{scene.camera.height}"
    cache = Path(os.environ.get("TMPDIR", "/tmp")) / f"shafts_ref_{name}_{size}_{samples}.npy"
    if cache.exists():
        return np.load(cache)
    fn = jax.jit(lambda s: render_raymarch(s, samples=samples, batch_size=128, return_parts=True)[1][1])
    t0 = time.perf_counter()
    ref = np.asarray(jax.block_until_ready(fn(scene)), dtype=np.float64)
    print(f"  reference {name}: ray march {samples} samples, {time.perf_counter() - t0:.0f} s", flush=True)
    np.save(cache, ref)
    return ref


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, name in zip(axes, ("stage", "spot")):
        for method, colour in (("equiangular", "C0"), ("planes", "C2"), ("raymarch", "C3")):
            # in the sweep's order (more samples / planes along each line); the 1024-map variant apart
            pts = [(r["cpu_s"], r["err"]) for r in rows if r["scene"] == name and r["method"] == method
                   and "1024" not in r["setting"]]
            if not pts:
                continue
            ax.plot([p[0] for p in pts], [100 * p[1] for p in pts], "o-", color=colour, label=method)
        ax.axhline(100 * TARGET, color="k", lw=0.8, ls="--")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("median CPU seconds per frame (both cores)")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())  # overlapping minor labels
        ax.set_ylabel("relative RMS of in-scattered light (%)")
        ax.set_title(name if name in {r["scene"] for r in rows} else f"{name} (not run)")
        if ax.get_legend_handles_labels()[0]:
            ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="smoke test: 120x80, the spot scene only, one setting per method, no gradient")
    parser.add_argument("--size", default="720x480")
    parser.add_argument("--ref-samples", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    w, h = (120, 80) if args.quick else tuple(int(x) for x in args.size.split("x"))
    repeats = 2 if args.quick else args.repeats
    print(f"{os.cpu_count()} CPU cores, JAX {jax.__version__} ({jax.default_backend()}), float32, {w}x{h}, "
          f"load average {os.getloadavg()}", flush=True)
    scenes = {"spot": spot_scene(w, h)}
    if args.quick:  # a smoke run: the one-light textured spot (the compile grows with the lights), one setting per
        eq, rm, pl = [(16, 512)], (16,), [(8, 4, True)]  # method (each setting and each profile piece is a compile)
    else:
        scenes["stage"] = load_stage_scene(width=w, height=h)
        eq = [(n, 512) for n in (8, 12, 16, 24, 32)] + [(24, None)]
        rm, pl = (8, 16, 24, 32, 48), [(8, 4, True), (16, 4, True), (30, 6, False)]
    rows = []
    for name, scene in scenes.items():
        ref = reference(name, scene, 64 if args.quick else args.ref_samples)
        settings = [("equiangular", s) for s in eq] + [("raymarch", s) for s in rm] + [("planes", s) for s in pl]
        rows += sweep(name, scene, ref, settings, repeats, quick=args.quick)
    FIGURES.mkdir(exist_ok=True)
    suffix = "_quick" if args.quick else ""
    plot(rows, FIGURES / f"shafts_interactive{suffix}.png")
    for name in scenes:
        best = min((r for r in rows if r["scene"] == name and r["method"] == "equiangular" and r["err"] <= TARGET),
                   key=lambda r: r["median_s"], default=None)
        if best is not None:
            write_image(FIGURES / f"shafts_interactive_{name}{suffix}.png", best["image"], exposure=2.0)

    summary = {}
    for name in scenes:
        for method in ("equiangular", "raymarch", "planes"):
            ok = [r for r in rows if r["scene"] == name and r["method"] == method and r["err"] <= TARGET]
            summary[(name, method)] = min(ok, key=lambda r: r["median_s"]) if ok else None
    best_samples = {name: int(summary[(name, "equiangular")]["setting"].split()[0]) if summary[(name, "equiangular")]
                    else 24 for name in scenes}
    profiles = {name: frame_profile(scene, best_samples[name], max(repeats, 5)) for name, scene in scenes.items()}
    # the gradient's two compiles are half a smoke run: quick skips it (tests/test_shafts_fast.py checks the gradients)
    grad = None if args.quick else gradient_ratio(scenes["spot"], 24, repeats)
    for name, prof in profiles.items():
        print(f"\nwhere the time goes, {name} (median wall s / median CPU s, each piece jitted alone):")
        for key, (wall, cpu) in prof.items():
            print(f"  {key:48s} {wall:.4f} / {cpu:.4f}")
    print(f"gradient: {grad}")
    print("\n| scene | method | cheapest setting reaching 2 % | rel. RMS | compile s | wall s min/median/max | CPU s |")
    print("|---|---|---|---|---|---|---|")
    for (name, method), r in summary.items():
        if r is None:
            print(f"| {name} | {method} | none of the settings | | | | |")
            continue
        print(f"| {name} | {method} | {r['setting']} | {100 * r['err']:.2f} % | {r['compile_s']:.1f} | "
              f"{r['min_s']:.3f} / {r['median_s']:.3f} / {r['max_s']:.3f} | {r['cpu_s']:.3f} |")
    print("\nAll settings:\n\n| scene | method | setting | rel. RMS | compile s | wall s min/median/max | CPU s |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['scene']} | {r['method']} | {r['setting']} | {100 * r['err']:.2f} % | {r['compile_s']:.1f} | "
              f"{r['min_s']:.3f} / {r['median_s']:.3f} / {r['max_s']:.3f} | {r['cpu_s']:.3f} |")

    def verdict(ok):
        return "met" if ok else "missed"

    results = []
    spot_target = "textured spot + sphere + floor 720x480 <= 40 ms at <= 2 %"
    stage_target = "five-spot stage 720x480 <= 0.17 s at <= 2 %"
    for name, target, limit in (("spot", spot_target, 0.04), ("stage", stage_target, 0.17)):
        if name not in scenes:
            continue
        best = summary[(name, "equiangular")]
        if best is None:  # a row all the same: "no setting reached 2 %" is a result too
            lowest = min(r["err"] for r in rows if r["scene"] == name and r["method"] == "equiangular")
            results.append(dict(area="shafts", target=target, status="missed",
                                measured=f"no equiangular setting reached 2 % (lowest {100 * lowest:.2f} %)"))
            continue
        results.append(dict(area="shafts", target=target,
                            measured=f"{best['median_s']:.3f} s wall, {best['cpu_s']:.3f} s CPU "
                                     f"({best['setting']}, {100 * best['err']:.2f} %)",
                            status=verdict(best["median_s"] <= limit)))
    if "stage" in scenes:
        results.append(stage_ratio_row(summary[("stage", "equiangular")], summary[("stage", "raymarch")]))
    if grad:
        results.append(dict(area="shafts", target="gradient <= 4x forward",
                            measured=f"{grad['ratio_wall']:.2f}x wall, {grad['ratio_cpu']:.2f}x CPU (spot scene)",
                            status=verdict(grad["ratio_wall"] <= 4)))
    write_results("shafts_interactive", results, quick=args.quick)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Light shafts at interactive rates: the default method (adaptive: in-scattering on a coarse grid,
refined where it changes fast or a silhouette crosses a lit cell) against the equiangular method at
every pixel and the ray march, whole frames (shadow maps and surfaces included), float32, compile
time apart, with light maps of realistic sizes; and the gradient's cost for every parameter.

    python benchmarks/shafts_interactive.py [--quick] [--size 720x480] [--ref-samples 256] [--repeats 3]
                                            [--sections frames,maps,gradient]

Scenes: "spot" = examples/scenes/spot_sphere.json with a 256 x 256 polka-dot light map (one
textured spot, a sphere, a floor); "stage" = the gallery's five-spot stage with three of its spots
projecting 256 x 256 polka-dot maps; "fog" = benchmarks/_shafts_common.py's grid-fog scene (three
spots, a light map, occluders, a density grid) for the gradient.

1. frames: each method at a few settings on the spot and the stage; error = relative RMS of the
   in-scattered light (design.md) against a converged ray march (`--ref-samples`, shadow rays);
   the cheapest setting of each reaching 2 %, the ray march's time over ours on the stage at equal
   error, and the error within 2 pixels of a depth edge (the halo check) on the stage.
2. maps: the spot with 64^2, 256^2 and 1024^2 light maps (the same dots), the default method at
   the setting of section 1: frame time and error per map size.
3. gradient: value_and_grad of an image loss over its forward time, for each parameter alone and all
   at once, uniform fog (spot) and grid fog (fog scene).

Times: min / median / max wall and median CPU seconds (this process, all threads) of `--repeats`
frames; the machine may be shared: the load average is printed with each row, and the CPU named.
Outputs: tables on stdout, benchmarks/results/shafts_interactive.json (the headline rows), the
error-vs-time plot benchmarks/figures/shafts_interactive.png and renders
benchmarks/figures/shafts_interactive_{spot,stage}.png.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))

import _shafts_common as C  # noqa: E402
from _results import cpu_description, write_results  # noqa: E402

from jaxrender.app.scenes import shafts_scene_from_dict, stage_scene_dict  # noqa: E402
from jaxrender.app.scenes.stage import DATA  # noqa: E402
from jaxrender.io import write_image  # noqa: E402
from jaxrender.shafts import render_adaptive, render_equiangular, render_raymarch  # noqa: E402
from jaxrender.shafts._equiangular import primary_hits  # noqa: E402

TARGET = 0.02
SPOT_LIMIT_S, STAGE_LIMIT_S, RAYMARCH_RATIO, GRAD_RATIO = 0.04, 0.17, 17.0, 5.0
EDGE_JUMP = 0.05  # a depth edge: depth off the mean of its two row / column neighbours by > 5 % (as the halo test)
FIGURES = HERE / "figures"


def light_map_file(directory: Path, n: int) -> str:
    """The polka-dot light map at n x n texels (the same 4 x 4 dots at every size), as an EXR."""
    return C.write_light_map(directory, f"dots_{n}.exr", C.polka_dots(n, dots=4))


def spot_scene(width, height, directory: Path, map_size: int = 256):
    d = json.loads((ROOT / "examples" / "scenes" / "spot_sphere.json").read_text())
    d["spotlights"][0]["light_map"] = str(directory / light_map_file(directory, map_size))
    return shafts_scene_from_dict(d, base_dir=directory).with_size(width, height)


def stage_scene(width, height, directory: Path, map_size: int = 256):
    """The five-spot stage with its two textured spots and the middle one carrying n x n maps."""
    d = stage_scene_dict()
    name = str(directory / light_map_file(directory, map_size))
    for spot in (d["spotlights"][0], d["spotlights"][1], d["spotlights"][2]):
        spot["light_map"] = name
    return shafts_scene_from_dict(d, base_dir=DATA).with_size(width, height)


def frame_times(fn, args, repeats):
    """(result, compile s, wall times, median CPU s): the first call apart."""
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - t0
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn(*args))
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return out, compile_s, wall, statistics.median(cpu)


def rel(x, ref, mask=None):
    d = np.asarray(x, np.float64) - ref
    if mask is not None:
        return float(np.linalg.norm(d[mask]) / np.linalg.norm(ref[mask]))
    return float(np.linalg.norm(d) / np.linalg.norm(ref))


def depth_edge_band(scene, reach: int = 2) -> np.ndarray:
    """Pixels within `reach` pixels of a depth edge (misses count as far)."""
    _, t, *_ = jax.jit(primary_hits)(scene)
    t = np.where(np.isfinite(np.asarray(t)), np.asarray(t), 1e6)
    h, w = t.shape
    edge = np.zeros(t.shape, bool)
    edge[1:-1, :] |= np.abs(t[:-2, :] - 2 * t[1:-1, :] + t[2:, :]) > EDGE_JUMP * t[1:-1, :]
    edge[:, 1:-1] |= np.abs(t[:, :-2] - 2 * t[:, 1:-1] + t[:, 2:]) > EDGE_JUMP * t[:, 1:-1]
    band = np.zeros_like(edge)
    for dy in range(-reach, reach + 1):
        for dx in range(-reach, reach + 1):
            band[max(dy, 0):h + min(dy, 0), max(dx, 0):w + min(dx, 0)] |= \
                edge[max(-dy, 0):h + min(-dy, 0), max(-dx, 0):w + min(-dx, 0)]
    return band


METHODS = {"adaptive": render_adaptive, "equiangular": render_equiangular, "raymarch": render_raymarch}


def method_fn(method, samples, *, parts: bool):
    """A jitted frame: the image (parts=False, the one timed) or (image, in-scattered part) for the error."""
    fn = METHODS[method]
    if not parts:
        return jax.jit(lambda s: fn(s, samples=samples))

    def frame(s):
        image, (_, fog) = fn(s, samples=samples, return_parts=True)
        return image, (sum(fog) if isinstance(fog, list) else fog)

    return jax.jit(frame)


def reference(name, scene, samples):
    size = f"{scene.camera.width}x{scene.camera.height}"
    cache = Path(os.environ.get("TMPDIR", "/tmp")) / f"shafts_interactive_ref_{name}_{size}_{samples}.npy"
    if cache.exists():
        return np.load(cache)
    fn = jax.jit(lambda s: render_raymarch(s, samples=samples, batch_size=128, return_parts=True)[1][1])
    t0 = time.perf_counter()
    ref = np.asarray(jax.block_until_ready(fn(scene)), dtype=np.float64)
    print(f"  reference {name}: ray march {samples} samples, {time.perf_counter() - t0:.0f} s", flush=True)
    np.save(cache, ref)
    return ref


def sweep(name, scene, ref, settings, repeats, *, band=None, quick=False):
    rows = []
    for method, samples in settings:
        parts_fn = method_fn(method, samples, parts=True)
        image, fog = parts_fn(scene)
        err = rel(fog, ref)
        edge_err = rel(fog, ref, band) if band is not None else float("nan")
        timed_fn = parts_fn if quick else method_fn(method, samples, parts=False)  # quick: one compile a setting
        _, c, wall, cpu = frame_times(timed_fn, (scene,), repeats)
        rows.append(dict(scene=name, method=method, samples=samples, err=err, edge_err=edge_err, compile_s=c,
                         min_s=min(wall), median_s=statistics.median(wall), max_s=max(wall), cpu_s=cpu,
                         load=os.getloadavg()[0], image=np.asarray(image)))
        print(f"  {name:5s} {method:11s} {samples:3d} samples  err {100 * err:5.2f} %  within 2 px of edges "
              f"{100 * edge_err:5.2f} %  compile {c:5.1f} s  wall {min(wall):.3f}/{statistics.median(wall):.3f}/"
              f"{max(wall):.3f} s  cpu {cpu:.3f} s  load {os.getloadavg()[0]:.1f}", flush=True)
    return rows


def cheapest(rows, name, method):
    ok = [r for r in rows if r["scene"] == name and r["method"] == method and r["err"] <= TARGET]
    return min(ok, key=lambda r: r["median_s"], default=None)


def describe(r):
    return (f"{1e3 * r['median_s']:.0f} ms wall ({1e3 * r['min_s']:.0f}-{1e3 * r['max_s']:.0f}), "
            f"{1e3 * r['cpu_s']:.0f} ms CPU, {r['samples']} samples, {100 * r['err']:.2f} %, load {r['load']:.1f}")


def plot(rows, path):
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for ax, name in zip(axes, ("stage", "spot")):
        for method, colour in (("adaptive", "C0"), ("equiangular", "C1"), ("raymarch", "C3")):
            pts = [(r["median_s"], r["err"]) for r in rows if r["scene"] == name and r["method"] == method]
            if pts:
                ax.plot([p[0] for p in pts], [100 * p[1] for p in pts], "o-", color=colour, label=method)
        ax.axhline(100 * TARGET, color="k", lw=0.8, ls="--")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("median wall seconds per frame")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_ylabel("relative RMS of in-scattered light (%)")
        ax.set_title(name if name in {r["scene"] for r in rows} else f"{name} (not run)")
        if ax.get_legend_handles_labels()[0]:
            ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def frames(args, w, h, directory, repeats):
    scenes = {"spot": spot_scene(w, h, directory)}
    if args.quick:
        settings = [("adaptive", 16), ("equiangular", 16), ("raymarch", 16)]
    else:
        scenes["stage"] = stage_scene(w, h, directory)
        settings = ([("adaptive", n) for n in (12, 16, 24, 32)] + [("equiangular", n) for n in (16, 24, 32)]
                    + [("raymarch", n) for n in (16, 24, 32, 48)])
    rows = []
    for name, scene in scenes.items():
        ref = reference(name, scene, 64 if args.quick else args.ref_samples)
        rows += sweep(name, scene, ref, settings, repeats, band=depth_edge_band(scene), quick=args.quick)
    FIGURES.mkdir(exist_ok=True)
    suffix = "_quick" if args.quick else ""
    plot(rows, FIGURES / f"shafts_interactive{suffix}.png")
    print("\n| scene | method | samples | rel. RMS | within 2 px of depth edges | compile s | wall s min/median/max "
          "| CPU s | load |\n|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['scene']} | {r['method']} | {r['samples']} | {100 * r['err']:.2f} % | {100 * r['edge_err']:.2f} % "
              f"| {r['compile_s']:.1f} | {r['min_s']:.3f} / {r['median_s']:.3f} / {r['max_s']:.3f} | "
              f"{r['cpu_s']:.3f} | {r['load']:.1f} |")
    results = []
    for name, target, limit in (("spot", f"one spot with a 256^2 light map {w}x{h} <= 40 ms at <= 2 %", SPOT_LIMIT_S),
                                ("stage", f"five-spot stage, three 256^2 maps, {w}x{h} <= 0.17 s at <= 2 %",
                                 STAGE_LIMIT_S)):
        if name not in scenes:
            continue
        best = cheapest(rows, name, "adaptive")
        if best is not None:
            write_image(FIGURES / f"shafts_interactive_{name}{suffix}.png", best["image"], exposure=2.0)
        old = cheapest(rows, name, "equiangular")
        old_text = f"; equiangular at every pixel {describe(old)}" if old else ""
        if best is None:
            lowest = min(r["err"] for r in rows if r["scene"] == name and r["method"] == "adaptive")
            results.append(dict(area="shafts", target=target, status="missed",
                                measured=f"no adaptive setting reached 2 % (lowest {100 * lowest:.2f} %){old_text}"))
            continue
        results.append(dict(area="shafts", target=target, measured=f"adaptive {describe(best)}{old_text}",
                            status="met" if best["median_s"] <= limit else "missed"))
    if "stage" in scenes:
        ours, rm = cheapest(rows, "stage", "adaptive"), cheapest(rows, "stage", "raymarch")
        if ours and rm:
            ratio = rm["median_s"] / ours["median_s"]
            text = (f"{ratio:.1f}x wall, {rm['cpu_s'] / ours['cpu_s']:.1f}x CPU (ray march {rm['samples']} samples "
                    f"{100 * rm['err']:.2f} % in {rm['median_s']:.3f} s; adaptive {ours['samples']} samples "
                    f"{100 * ours['err']:.2f} % in {ours['median_s']:.3f} s)")
        else:
            ratio, text = 0.0, "no ratio: a method reached 2 % at none of its settings"
        results.append(dict(area="shafts", target=">= 17x the ray march at 2 % on the stage", measured=text,
                            status="met" if ratio >= RAYMARCH_RATIO else "missed"))
        edge = [r for r in rows if r["scene"] == "stage" and r["method"] == "adaptive"]
        if ours:
            results.append(dict(area="shafts", target="no halo: error within 2 px of a depth edge <= 2 % on the stage",
                                measured=f"{100 * ours['edge_err']:.2f} % within 2 px of depth edges "
                                         f"({100 * ours['err']:.2f} % over the image), adaptive {ours['samples']} "
                                         f"samples; at {', '.join(str(r['samples']) for r in edge)} samples: "
                                         f"{', '.join('%.2f' % (100 * r['edge_err']) for r in edge)} %",
                                status="met" if ours["edge_err"] <= TARGET else "missed"))
    best_spot = cheapest(rows, "spot", "adaptive")
    return results, (best_spot["samples"] if best_spot else 24)


def maps(args, w, h, directory, repeats, samples):
    """The spot with each light map size; the sizes' frames timed interleaved (round after round),
    so that the machine's speed, which drifts over minutes, weighs on every size alike."""
    sizes = (64, 256, 1024)
    rows, timed = [], []
    for n in sizes:
        scene = spot_scene(w, h, directory, n)
        ref = reference(f"spot_map{n}", scene, 64 if args.quick else args.ref_samples)
        fn = method_fn("adaptive", samples, parts=True)
        _, fog = fn(scene)
        fn = fn if args.quick else method_fn("adaptive", samples, parts=False)
        t0 = time.perf_counter()
        jax.block_until_ready(fn(scene))
        rows.append(dict(n=n, err=rel(fog, ref), compile_s=time.perf_counter() - t0))
        timed.append((fn, (scene,)))
    for row, (wall, cpu) in zip(rows, C.alternate(timed, repeats)):
        row.update(median_s=wall, cpu_s=cpu, load=os.getloadavg()[0])
        print(f"  spot, {row['n']}^2 light map, adaptive {samples} samples: err {100 * row['err']:.2f} %  compile "
              f"{row['compile_s']:.1f} s  wall {row['median_s']:.3f} s  cpu {row['cpu_s']:.3f} s  "
              f"load {row['load']:.1f}", flush=True)
    spread = max(r["median_s"] for r in rows) / min(r["median_s"] for r in rows)
    text = "; ".join(f"{r['n']}^2 {1e3 * r['median_s']:.0f} ms wall {1e3 * r['cpu_s']:.0f} ms CPU "
                     f"{100 * r['err']:.2f} %" for r in rows)
    return [dict(area="shafts", target=f"spot frame nearly independent of the light map's size (64^2-1024^2), {w}x{h}",
                 measured=f"slowest / fastest {spread:.2f}x ({text}; adaptive {samples} samples)",
                 status="met" if spread <= 1.25 else "missed")]


def gradient(args, w, h, directory, repeats, save):
    rng = np.random.default_rng(0)
    weights = jnp.asarray(rng.uniform(0.5, 1.5, (h, w, 3)), dtype=jnp.float32)
    fog_dir = Path(tempfile.mkdtemp(dir=directory))
    scenes = {"uniform fog (spot, 256^2 map)": spot_scene(w, h, directory),
              "grid fog (fog scene)": C.load(C.fog_scene(w, h, base_dir=fog_dir), fog_dir)}
    results, table = [], []
    for label, scene in scenes.items():
        grid = scene.medium.density is not None
        p0 = dict(rho=scene.medium.rho, kappa=scene.medium.kappa, K=scene.medium.K,
                  intensity=[light.intensity for light in scene.lights],
                  position=[light.position for light in scene.lights])
        if grid:
            p0 = dict(values=scene.medium.density.values, **p0)

        def with_params(p, scene=scene, grid=grid):
            s = eqx.tree_at(lambda s: (s.medium.rho, s.medium.kappa, s.medium.K), scene, (p["rho"], p["kappa"], p["K"]))
            if grid:
                s = eqx.tree_at(lambda s: s.medium.density.values, s, p["values"])
            return eqx.tree_at(lambda s: [x.intensity for x in s.lights] + [x.position for x in s.lights],
                               s, p["intensity"] + p["position"])

        def loss(p, with_params=with_params):
            return jnp.sum(weights * render_adaptive(with_params(p)))

        forward = jax.jit(loss)
        jax.block_until_ready(forward(p0))
        ratios, forwards = {}, []
        for keys in [(k,) for k in p0 if k != "intensity"] + [tuple(p0)]:  # intensity: linear, in "all"
            def part(q, loss=loss, p0=p0):
                return loss({**p0, **q})

            grad, q0 = jax.jit(jax.value_and_grad(part)), {k: p0[k] for k in keys}
            t0 = time.perf_counter()
            jax.block_until_ready(grad(q0))
            c_g = time.perf_counter() - t0
            (fwd, cpu_f), (wall_g, cpu_g) = C.alternate([(forward, (p0,)), (grad, (q0,))], repeats)
            forwards.append(fwd)
            name = "all" if len(keys) > 1 else keys[0]
            ratios[name] = (wall_g / fwd, cpu_g / cpu_f)
            table.append(f"| {label} | {name} | {fwd:.3f} | {wall_g:.3f} | "
                         f"{ratios[name][0]:.2f}x | {ratios[name][1]:.2f}x | {c_g:.0f} | {os.getloadavg()[0]:.1f} |")
            print("  " + table[-1], flush=True)
        fwd = statistics.median(forwards)
        worst = max(ratios, key=lambda k: ratios[k][0])
        results.append(dict(area="shafts", target=f"gradient <= 5x forward for every parameter, {label}, {w}x{h}",
                            measured=", ".join(f"{k} {v[0]:.2f}x" for k, v in ratios.items())
                            + f" wall (CPU: {', '.join(f'{v[1]:.2f}x' for v in ratios.values())}); forward "
                              f"{1e3 * fwd:.0f} ms, adaptive 24 samples",
                            status="met" if ratios[worst][0] <= GRAD_RATIO else f"missed ({worst})"))
        save(results[-1:])  # each fog's row as soon as it is measured (a grid-fog compile takes minutes)
    print("\n| fog | w.r.t. | forward s | value and gradient s | ratio wall | ratio CPU | compile s | load |\n"
          "|---|---|---|---|---|---|---|---|\n" + "\n".join(table))
    return results


SECTIONS = ("frames", "maps", "gradient")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="smoke test: 120x80, the spot scene only, one setting per method, no gradient")
    parser.add_argument("--size", default="720x480")
    parser.add_argument("--ref-samples", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--sections", default=",".join(SECTIONS))
    args = parser.parse_args(argv)
    sections = [s for s in args.sections.split(",") if s]
    unknown = [s for s in sections if s not in SECTIONS]
    if unknown:
        parser.error(f"--sections: unknown {', '.join(unknown)} (choose from {', '.join(SECTIONS)})")
    w, h = (120, 80) if args.quick else tuple(int(x) for x in args.size.split("x"))
    repeats = 2 if args.quick else args.repeats
    print(f"{os.cpu_count()} CPU cores of {cpu_description()}, JAX {jax.__version__} ({jax.default_backend()}), "
          f"float32, {w}x{h}, load average {os.getloadavg()}", flush=True)
    results, samples, saved = [], 24, []

    def save(rows):  # rows written as each section ends: a full run replaces the file, a partial one updates it
        results.extend(rows)
        partial = bool(saved) or set(sections) != set(SECTIONS)
        write_results("shafts_interactive", rows, quick=args.quick, update=partial)
        saved.append(True)

    with tempfile.TemporaryDirectory() as tmp:
        directory = Path(tmp)
        if "frames" in sections:
            rows, samples = frames(args, w, h, directory, repeats)
            save(rows)
        if "maps" in sections:
            save(maps(args, w, h, directory, repeats, samples))
        if "gradient" in sections and not args.quick:  # two compiles a parameter: tests/ check the gradients
            gradient(args, w, h, directory, repeats, save)
    for r in results:
        print(f"{r['status']:>8s}  {r['target']}: {r['measured']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Frame time of the Takigi Noh scene (paper 004 section 4): a 720x480 frame of the
costumed performer on the Noh stage with everything that moves redone every frame (the robe's
200 Verlet steps on the skeleton, the performer's mesh, its G-buffer and its mirror image's, 4
depth maps, PCSS at the performer's and the stage's points, 20 environment + 20 fire samples on
2-lobe EM BTF levels, the stage's light, the floor's reflection, the flames).

Target: <= 1 s median per frame on 2 cores, compile apart, for the built-in motion and
for a captured one (`../shared/data/mocap/dance-short_normal_001.bvh`, or $JAXRENDER_MOCAP).

Timed: the scene + rig setup (robe made and settled, stage cast and lit), the first frame
(compile) apart, then `--frames` frames (default 24: frames 1-12 of the dance twice), wall and
process CPU, min/median/max, rendered as `jaxrender noh` renders them (`sequence_frames`: the next frame's robe
simulated in a second thread while this one renders), and beside them the same frames with the
robe and the image one after the other (`noh_frame`), in two blocks each, alternately; then the
pieces of the last frame, each jitted alone (median of 3, wall and CPU).
Rows "25 Noh" to benchmarks/results/noh_frame.json (not with --quick). The last frame goes
to benchmarks/figures/noh_frame_<motion>.png (`--quick`: ..._quick.png, not committed).

Run: `python benchmarks/noh_frame.py` (720x480, both motions) or `--quick` (160x120, a coarse
robe not settled, 64^2 depth maps, level-0 BTFs, 3 frames of the built-in motion: the smoke run).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time
from pathlib import Path

import jax
import numpy as np

MOCAP = Path(os.environ.get("JAXRENDER_MOCAP", Path(__file__).resolve().parents[2] / "shared" / "data" / "mocap"))
CAPTURED = "dance-short_normal_001.bvh"


def _timed(fn, *args, repeats: int = 3) -> tuple[float, float]:
    """(median wall s, median process CPU s) of a compiled call."""
    jax.block_until_ready(fn(*args))
    wall, cpu = [], []
    for _ in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn(*args))
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return statistics.median(wall), statistics.median(cpu)


def _pieces(scene, rig, state, key) -> list[tuple[str, float, float]]:
    """The frame's parts, each jitted alone at the pose of `state` (what `noh_frame` does)."""
    import jax.numpy as jnp

    from jaxrender.app.scenes.noh import motion as mo
    from jaxrender.app.scenes.noh.performer import performer_mesh
    from sims import advance_costume

    performer = scene.performer
    mesh = performer_mesh(performer, state)
    split = dict(window=rig.window, large_window=rig.large_view_window, large_capacity=rig.large_view_capacity)
    maps = mo.fire_depth_maps(rig, mesh.vertices, mesh.triangles)[0]
    n = rig.capacity + rig.reflection_capacity
    points = jnp.broadcast_to(mesh.vertices.mean(axis=0), (n, 3))
    parts = [
        (f"robe: {rig.steps} Verlet steps", jax.jit(lambda s: advance_costume(performer.costume, s, performer.motion,
                                                                              steps=rig.steps)), (state,)),
        ("performer mesh", jax.jit(lambda s: performer_mesh(performer, s)), (state,)),
        ("G-buffer in the performer's box (two windows)", jax.jit(
            lambda m: mo.split_rasterize(mo._cropped(rig.pinhole, rig.view_box), m.vertices, m.triangles, m.uv,
                                         **split)), (mesh,)),
        ("4 depth maps (two windows)", jax.jit(lambda m: mo.fire_depth_maps(rig, m.vertices, m.triangles)[0]),
         (mesh,)),
        (f"PCSS x 4 at {n} performer + reflected points (capacities) and "
         f"{rig.shadow_grid.points.shape[1]} stage points per fire", jax.jit(lambda mp, p: mo.fire_shadows(rig, mp, p)),
         (maps, points)),
        ("the frame's image (all but the robe)",
         jax.jit(lambda s, k: mo.frame_image(scene, rig, s, scene.flames[:, 0], k)[0]), (state, key)),
        ("the whole frame, robe then image",
         jax.jit(lambda s, k: mo.noh_frame(scene, rig, s, scene.flames[:, 0], k)[0]), (state, key)),
    ]
    return [(name, *_timed(fn, *args)) for name, fn, args in parts]


def run_motion(label: str, motion, args) -> dict:
    """Scene, rig, then frames of `motion` (None: the built-in dance): the figures of one row."""
    from jaxrender.app.scenes import noh
    from jaxrender.app.scenes.noh.motion import noh_frame_jit, sequence_frames
    from jaxrender.app.scenes.noh.rig import prepare_rig

    quick = args.quick
    width, height, res = (160, 120, 64) if quick else (720, 480, 512)
    n_frames = args.frames or (3 if quick else 24)
    blocks = 1 if quick else 2          # each way of rendering timed in this many blocks, alternately
    per_block = max(n_frames // blocks, 1)
    key = jax.random.key(2024)                     # as `jaxrender noh` (its default seed)
    k_scene, k_rest = jax.random.split(key)
    k_env, k_frames = jax.random.split(k_rest)
    small = dict(robe=dict(rows=14, cols=14, sleeve_rows=5, sleeve_cols=8, settle_steps=0),
                 flame_size=(32, 16)) if quick else {}
    t = time.perf_counter()
    btfs = noh.default_btfs(size=8, pyramid="none") if quick else None
    scene = noh.noh_scene(width=width, height=height, frames=20, key=k_scene, btfs=btfs, motion=motion,
                          duration=(per_block + 2) * 0.1, **small)
    rig = jax.block_until_ready(prepare_rig(scene, key=k_env, shadow_resolution=res))
    setup_s = time.perf_counter() - t
    frame_args = lambda i: (scene.flames[:, i % scene.flames.shape[1]], jax.random.fold_in(k_frames, i))  # noqa: E731
    start = scene.performer.costume.state

    def piped(rig):
        """Frames 0..per_block as `jaxrender noh` renders them (`sequence_frames`: the next frame's robe
        simulated while this one renders; one frame more than timed, so that the last one timed has
        its successor's robe to simulate too): per-frame (wall, CPU), the last frame, recompiles."""
        seconds, regrown, t, c = [], 0, time.perf_counter(), time.process_time()
        for i, frame in enumerate(sequence_frames(scene, rig, start, per_block + 2, frame_args)):
            seconds.append((time.perf_counter() - t, time.process_time() - c))
            regrown += frame.regrown
            if i == per_block:
                break
            t, c = time.perf_counter(), time.process_time()
        return seconds, frame, regrown

    def serial(rig):
        """The same frames with the robe and the image one after the other (`noh_frame`)."""
        seconds, state = [], start
        for i in range(per_block + 1):
            t, c = time.perf_counter(), time.process_time()
            _, state, _ = jax.block_until_ready(noh_frame_jit(scene, rig, state, *frame_args(i)))
            seconds.append((time.perf_counter() - t, time.process_time() - c))
        return seconds

    timed, alone, recompiles = [], [], 0
    for block in range(blocks):   # the two ways alternately, so that both see the same machine
        seconds, frame, regrown = piped(rig)
        rig, recompiles = frame.rig, recompiles + regrown
        if block == 0:
            compile_s = seconds[0][0]
        timed += seconds[1:]
        if not quick:
            alone += serial(rig)[1:]
    wall, cpu = [w for w, _ in timed], [c for _, c in timed]
    state, image, counts = frame.state, frame.image, frame.counts
    pieces = [] if quick else _pieces(scene, rig, state, jax.random.key(0))
    out = Path(__file__).resolve().parent / "figures" / (f"noh_frame_{label}{'_quick' if quick else ''}.png")
    out.parent.mkdir(exist_ok=True)
    mask = np.asarray(counts.performer_mask)
    lum = np.asarray(image)[mask] @ np.asarray([0.2126, 0.7152, 0.0722])
    from jaxrender.app.scenes.noh.animation import EXPOSURE_KEY
    from jaxrender.io import write_png

    exposure = EXPOSURE_KEY / max(float(np.percentile(lum, 90)) if lum.size else 1.0, 1e-6)
    write_png(out, noh.tonemap_frames(np.asarray(image)[None], exposure=exposure)[0])
    return dict(label=label, width=width, height=height, res=res, setup_s=setup_s, compile_s=compile_s,
                serial_wall=[w for w, _ in alone], serial_cpu=[c for _, c in alone],
                frames=f"{blocks} x frames 1-{per_block}",
                recompiles=recompiles, wall=wall, cpu=cpu, pieces=pieces, performer=int(counts.performer),
                reflection=int(counts.reflection), load=os.getloadavg()[0])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--frames", type=int, default=None, help="frames of the dance timed (default 24)")
    parser.add_argument("--only", choices=("built-in", "captured"), default=None)
    args = parser.parse_args()
    from jaxrender.io import read_bvh

    runs = []
    if args.only in (None, "built-in"):
        runs.append(run_motion("built-in", None, args))
    captured = MOCAP / CAPTURED
    if not args.quick and args.only in (None, "captured"):
        if captured.is_file():
            runs.append(run_motion("captured", read_bvh(captured), args))
        else:
            print(f"{captured}: not found (set JAXRENDER_MOCAP): the captured motion is not timed")
    rows = []
    for r in runs:
        med, med_cpu = statistics.median(r["wall"]), statistics.median(r["cpu"])
        print(f"\n# noh_frame {r['label']} ({'quick' if args.quick else 'full'}) {r['width']}x{r['height']}, "
              f"{r['res']}^2 depth maps, {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
              f"load average {r['load']:.1f}, jax {jax.__version__}")
        print("| quantity | value |")
        print("|---|---|")
        for k, v in [("scene + rig setup (robe made and settled, stage cast and lit; incl. compile) s",
                      f"{r['setup_s']:.2f}"), ("first frame (compile + run) s", f"{r['compile_s']:.2f}"),
                     ("recompiles (a buffer grew)", str(r["recompiles"])),
                     (f"frame wall s, min / median / max of {len(r['wall'])} ({r['frames']})",
                      f"{min(r['wall']):.3f} / {med:.3f} / {max(r['wall']):.3f}"),
                     ("frame process CPU s (both cores), min / median / max",
                      f"{min(r['cpu']):.3f} / {med_cpu:.3f} / {max(r['cpu']):.3f}"),
                     ("the same frames, robe then image (`noh_frame`), wall / CPU s, median",
                      f"{statistics.median(r['serial_wall']):.3f} / {statistics.median(r['serial_cpu']):.3f}"
                      if r["serial_wall"] else "not timed (--quick)"),
                     ("performer / reflected pixels (last frame)", f"{r['performer']} / {r['reflection']}")]:
            print(f"| {k} | {v} |")
        if r["pieces"]:
            print("\n| piece (jitted alone, median of 3) | wall s | CPU s |")
            print("|---|---|---|")
            for name, w_s, c_s in r["pieces"]:
                print(f"| {name} | {w_s:.3f} | {c_s:.3f} |")
        verdict = "met" if med <= 1.0 else "missed"
        print(f"\ntarget{' (quick size: the target is for 720x480)' if args.quick else ''}: frame <= 1 s: "
              f"{verdict} ({med:.3f} s median wall, {med_cpu:.3f} s CPU)")
        rows.append(dict(
            area="noh", target=f"720x480 frame, everything redone per frame, {r['label']} motion, <= 1 s",
            measured=f"{med:.3f} s median frame wall ({min(r['wall']):.3f}-{max(r['wall']):.3f}), {med_cpu:.3f} s "
                     f"process CPU, {len(r['wall'])} frames ({r['frames']}), compile {r['compile_s']:.1f} s, setup "
                     f"{r['setup_s']:.1f} s, load {r['load']:.1f}; the same frames robe then image, alternately: "
                     f"{statistics.median(r['serial_wall'] or [float('nan')]):.3f} s wall, "
                     f"{statistics.median(r['serial_cpu'] or [float('nan')]):.3f} s CPU",
            status=verdict if r["load"] <= 2.5 else f"{verdict} at load {r['load']:.1f} (wall)",
            notes="; ".join(f"{n}: {c:.3f} s CPU" for n, _, c in r["pieces"]),
            figures={"median_frame_s": med, "median_frame_cpu_s": med_cpu, "compile_s": r["compile_s"]}))
    from _results import write_results

    write_results("noh_frame", rows, quick=args.quick)


if __name__ == "__main__":
    main()

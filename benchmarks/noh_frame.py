"""Frame time of the Noh scene (paper 004, section 4.4): a 720x480 frame of the draped garment with
20 environment + 20 fire directions and 2-lobe EM BTF levels; 20 frames of animation.

Targets (issue 5): <= 1 s per frame after compilation; 20 frames <= 20 s.

What is timed (compile time apart, `block_until_ready`, median of repeats):
- `static`: the per-sequence part (rasterized G-buffer, floor, 4 garment depth maps + PCSS,
  K_env = 20 environment samples and I_static), compiled, second call;
- `frame`: one animation frame (K_f = 20 fire samples by power, shading of every garment texel
  at two mip levels x two lobes and every floor pixel, visible flames, compositing);
- peer (same run): `frame + static`, i.e. a frame that recomputes the static part (no caching
  of I_static and shadows across the sequence), and the ratio of the two;
- `animation`: 20 consecutive frames (the default sequence), wall time, compiled;
- issue 16: the per-frame time with the per-sequence part amortised over the 20 frames
  (frame + static / 20) and with it alone each frame (frame + static), and which of the two meets
  the 1 s target; headline rows to benchmarks/results/noh_frame.json (not with --quick).
Process CPU time per frame is printed too: on a shared machine it is the stable figure (an idle
2-core machine runs a frame in about CPU time / 2 when both cores are busy).

Run: `python benchmarks/noh_frame.py` (720x480) or `--quick` (180x120, 8^2 level-0 BTFs without EM levels, 2 repeats,
3 frames: smoke run). Writes the last frame to benchmarks/figures/noh_frame.png (`--quick`: noh_frame_quick.png, not
committed).

`--moving` (issue 17): the moving garment instead, everything per frame in one jitted call
(`jaxrender.app.scenes.noh.motion.moving_frame`: 200 cloth steps, G-buffers of the garment and
of its mirror image, 4 depth maps, PCSS at the garment, reflected and half-resolution floor
points, I_static, firelight, the floor's reflection), the scene and dance of `jaxrender noh`.
Times the first call apart (compile), then `--frames` consecutive frames of the dance (default
24), each wall and process CPU, min/median/max; then the pieces of the last frame, each jitted
alone (median of 3, wall and CPU). Row "17 Noh" to benchmarks/results/noh_frame_moving.json (not with
--quick: 180x120, 128^2 depth maps, 4 frames). `python benchmarks/noh_frame.py --moving`.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import jax
import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--repeats", type=int, default=None)
    parser.add_argument("--moving", action="store_true", help="the moving garment, everything per frame (issue 17)")
    parser.add_argument("--frames", type=int, default=None, help="--moving: frames of the dance timed (default 24)")
    args = parser.parse_args()
    if args.moving:
        moving(args)
        return
    width, height = (180, 120) if args.quick else (720, 480)
    repeats = args.repeats or (2 if args.quick else 7)
    n_frames = 3 if args.quick else 20  # the smoke run: a 3-frame sequence

    from jaxrender.app.scenes import noh

    t = time.perf_counter()
    # quick: level 0 only, no EM fits (their compile was half the smoke run's; em_pyramid --quick runs the EM)
    btfs = noh.default_btfs(size=8, pyramid="none") if args.quick else noh.default_btfs(size=32, pyramid="em")
    env = noh.default_environment()
    scene = noh.noh_scene(width=width, height=height, frames=n_frames, btfs=btfs, env=env)
    setup_s = time.perf_counter() - t
    lobes_note = (f"EM levels; brocade levels 1.. two-lobe fraction "
                  f"{np.mean([float(np.mean(np.asarray(lv.weight) > 0)) for lv in btfs['brocade'][1:]]):.2f}"
                  if len(btfs["brocade"]) > 1 else "level 0 only, no EM levels")

    t = time.perf_counter()
    prep = jax.block_until_ready(noh.prepare_noh(scene, key=jax.random.key(1)))
    static_compile_s = time.perf_counter() - t
    static, static_cpu = [], []
    for i in range(max(3, repeats // 2)):
        t, c = time.perf_counter(), time.process_time()
        jax.block_until_ready(noh.prepare_noh(scene, key=jax.random.key(1)))
        static.append(time.perf_counter() - t)
        static_cpu.append(time.process_time() - c)

    frame = noh.noh_frame_jit
    t = time.perf_counter()
    jax.block_until_ready(frame(scene, prep, scene.flames[:, 0], jax.random.key(0)))
    frame_compile_s = time.perf_counter() - t
    frames, cpu = [], []
    for i in range(repeats):
        t, c = time.perf_counter(), time.process_time()
        jax.block_until_ready(frame(scene, prep, scene.flames[:, i % n_frames], jax.random.key(i)))
        frames.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    t = time.perf_counter()
    for i in range(n_frames):
        last = jax.block_until_ready(frame(scene, prep, scene.flames[:, i], jax.random.key(100 + i)))
    animation_s = time.perf_counter() - t
    # the rendered frame (cf. the paper's Fig. 13), tone mapped like the gallery
    from pathlib import Path

    from jaxrender.io import write_png

    out = Path(__file__).resolve().parent / "figures" / ("noh_frame_quick.png" if args.quick else "noh_frame.png")
    out.parent.mkdir(exist_ok=True)
    lum = (np.asarray(last).reshape(-1, 3)[np.asarray(prep.garment.index)]
           @ np.asarray([0.2126, 0.7152, 0.0722], np.float32))
    write_png(out, noh.tonemap_frames(np.asarray(last)[None], exposure=0.3 / float(np.percentile(lum, 90)))[0])

    frame_med, static_med = statistics.median(frames), statistics.median(static)
    rows = [
        ("resolution", f"{width}x{height}"),
        ("garment / floor pixels", f"{prep.garment.position.shape[0]} / {prep.floor.position.shape[0]}"),
        ("K_env + K_fire, lobes", f"20 + 20, 2 ({lobes_note})"),
        ("scene setup (cloth sim, sky, flames, BTF levels; incl. compile) s", f"{setup_s:.2f}"),
        ("static part: compile + first run s", f"{static_compile_s:.2f}"),
        ("static part (per sequence), median s", f"{static_med:.3f}"),
        ("frame: compile + first run s", f"{frame_compile_s:.2f}"),
        ("frame (static cached), median s", f"{frame_med:.3f}"),
        ("frame (static cached), median process CPU s (both cores)", f"{statistics.median(cpu):.3f}"),
        ("peer: frame recomputing the static part, s", f"{frame_med + static_med:.3f}"),
        ("ratio peer / frame", f"{(frame_med + static_med) / frame_med:.2f}x"),
        (f"{n_frames} frames of animation (compiled) s", f"{animation_s:.2f}"),
        (f"{n_frames} frames incl. static part s", f"{animation_s + static_med:.2f}"),
        (f"frame with the static part amortised over {n_frames} frames (frame + static / {n_frames}) s",
         f"{frame_med + static_med / n_frames:.3f}"),
        ("static part (per sequence), median process CPU s", f"{statistics.median(static_cpu):.3f}"),
    ]
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"# noh_frame ({'quick' if args.quick else 'full'}) on {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} cores, load average {load:.1f}, jax {jax.__version__}")
    print("| quantity | value |")
    print("|---|---|")
    for k, v in rows:
        print(f"| {k} | {v} |")
    ok_frame = frame_med <= 1.0
    ok_anim = animation_s <= 20.0
    scope = "" if not args.quick else " (quick size: the targets are for 720x480)"
    amortised, alone = frame_med + static_med / n_frames, frame_med + static_med
    print(f"\ntargets{scope}: frame <= 1 s: {'met' if ok_frame else 'MISSED'} ({frame_med:.3f} s static cached; "
          f"{amortised:.3f} s with the static part amortised over 20 frames: {'met' if amortised <= 1 else 'MISSED'}; "
          f"{alone:.3f} s recomputing it every frame: {'met' if alone <= 1 else 'MISSED'}); "
          f"20 frames <= 20 s: {'met' if ok_anim else 'MISSED'} ({animation_s:.2f} s, "
          f"{animation_s + static_med:.2f} s with the static part)")
    from _results import write_results

    cpu_f, cpu_s = statistics.median(cpu), statistics.median(static_cpu)
    verdict = "met" if amortised <= 1 else "missed"
    write_results("noh_frame", [
        dict(issue="5 Noh", target="720x480 frame, 20 env + 20 fire samples, 2 lobes, <= 1 s",
             measured=f"{frame_med:.3f} s static cached (CPU {cpu_f:.3f} s); {amortised:.3f} s with the per-sequence "
                      f"part amortised over 20 frames; {alone:.3f} s recomputing it each frame (CPU "
                      f"{cpu_f + cpu_s:.3f} s); median of {repeats}, load {load:.1f}",
             status=f"{verdict} (amortised); {'met' if alone <= 1 else 'missed'} (per-sequence part every frame)",
             notes="per-sequence part: G-buffer, floor, 4 depth maps + PCSS, environment term"),
        dict(issue="5 Noh", target="20 frames <= 20 s",
             measured=f"{animation_s:.2f} s, {animation_s + static_med:.2f} s with the per-sequence part; "
                      f"load {load:.1f}",
             status="met" if animation_s + static_med <= 20 else ("met (frames only)" if ok_anim else "missed"))],
        quick=args.quick)


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


def _pieces(scene, rig, state, emission, key) -> list[tuple[str, float, float]]:
    """The moving frame's parts, each jitted alone at the pose of `state` (what `moving_frame` does)."""
    import equinox as eqx
    import jax.numpy as jnp

    from jaxrender.app.scenes.noh import motion as mo
    from jaxrender.app.scenes.noh.frame import fire_light
    from jaxrender.app.scenes.noh.prepare import fire_visibility, garment_points
    from jaxrender.app.scenes.noh.shading import shade_garment, shared_light
    from jaxrender.fabric import mirror_mesh, rasterize
    from jaxrender.lights import sample_quad_lights
    from sims import advance_cloth, cloth_mesh

    cloth = rig.cloth
    up = jnp.asarray([0.0, 1.0, 0.0], state.x.dtype)

    def geometry(scene, rig, x):
        normals = cloth_mesh(cloth, x).normals.reshape(-1, 3)
        geo = eqx.tree_at(lambda s: (s.vertices, s.vertex_normals), scene, (x, normals))
        uv = cloth.uv.reshape(-1, 2)
        gb = rasterize(rig.pinhole, x, cloth.triangles, uv, window=rig.window)
        garment = (gb.hit > 0) & (gb.distance < rig.t_floor)
        points = garment_points(rig.pinhole, geo, gb, mo._compact(garment, rig.capacity)[1])
        mv, mn, mt = mirror_mesh(x, normals, cloth.triangles, jnp.zeros(3, x.dtype), up)
        gbr = rasterize(rig.pinhole, mv, mt, uv, window=rig.window)
        reflects = (gbr.hit > 0) & (rig.floor_coat > 0) & ~garment
        mirror = eqx.tree_at(lambda s: (s.vertices, s.vertex_normals, s.triangles), scene, (mv, mn, mt))
        mirrored = mo._mirror_back(garment_points(rig.pinhole, mirror, gbr, mo._compact(
            reflects, rig.reflection_capacity)[1]), up)
        return jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), points, mirrored)

    fires = eqx.tree_at(lambda f: f.emission, scene.fires, emission)
    samples = sample_quad_lights(fires, key, 20)
    n_fires = fires.center.shape[0]
    x = state.x
    both = jax.jit(geometry)(scene, rig, x)
    maps = jax.jit(lambda r, x: mo._fire_depth_maps(r, x, cloth.triangles)[0])(rig, x)
    vis = fire_visibility(maps, both.position, rig.near)

    def shade(scene, rig, both, vis):
        light = mo._with_light(shared_light(rig.env_direction, rig.env_weight, both.position.shape[0]),
                               fire_light(samples, both.position, vis, n_fires))
        return shade_garment(scene.mats, both, light)

    n = both.position.shape[0]
    parts = [
        (f"cloth: {rig.steps} Verlet steps", jax.jit(lambda r, s: advance_cloth(cloth, s, r.motion, steps=r.steps)),
         (rig, state)),
        ("G-buffers of the garment and its mirror image, their points", jax.jit(geometry), (scene, rig, x)),
        ("4 depth maps of the garment", jax.jit(lambda r, x: mo._fire_depth_maps(r, x, cloth.triangles)[0]), (rig, x)),
        (f"PCSS x 4 fires at {n} garment + reflected points (capacities)",
         jax.jit(lambda m, p: fire_visibility(m, p, rig.near)), (maps, both.position)),
        (f"floor: PCSS x 4 at {rig.shadow_points.shape[0]} half-res points + firelight",
         jax.jit(lambda r, m: mo.floor_firelight(r, samples, fire_visibility(m, r.shadow_points, r.near))),
         (rig, maps)),
        ("garment + reflected shading (20 env + 20 fire samples, 2 levels)", jax.jit(shade), (scene, rig, both, vis)),
    ]
    return [(name, *_timed(fn, *args)) for name, fn, args in parts]


def moving(args) -> None:
    """The moving garment's frame (issue 17), see the module docstring."""
    from jaxrender.app.scenes import noh
    from jaxrender.app.scenes.noh import motion as mo
    from jaxrender.app.scenes.noh.scene import garment_rig, noh_scene
    from sims import BodyMotion

    width, height, res = (180, 120, 128) if args.quick else (720, 480, 512)
    n_frames = args.frames or (4 if args.quick else 24)
    key = jax.random.key(2024)                      # as `jaxrender noh` (its default seed)
    k_scene, k_rest = jax.random.split(key)
    k_env, k_frames = jax.random.split(k_rest)
    t = time.perf_counter()
    btfs = noh.default_btfs(size=8, pyramid="none") if args.quick else None   # quick: no EM fits
    scene = noh_scene(width=width, height=height, frames=20, key=k_scene, cloth_rows=40, cloth_cols=32, btfs=btfs)
    cloth = garment_rig(40, 32)
    rig = jax.block_until_ready(mo.prepare_motion(scene, cloth, BodyMotion(axis_z=float(cloth.capsule[1])),
                                                  key=k_env, shadow_resolution=res))
    setup_s = time.perf_counter() - t
    state, wall, cpu, compile_s, recompiles = cloth.state, [], [], None, 0
    for i in range(n_frames + 1):
        args_i = (scene, rig, state, scene.flames[:, i % scene.flames.shape[1]], jax.random.fold_in(k_frames, i))
        t, c = time.perf_counter(), time.process_time()
        image, new_state, counts = jax.block_until_ready(mo.moving_frame_jit(*args_i))
        bigger = mo.grown(rig, counts)
        if bigger is not None:   # a buffer overflowed: the frame again with larger ones (one more compile)
            print(f"frame {i}: buffers grown", {k: getattr(bigger, k) for k in ("capacity", "reflection_capacity",
                  "window", "large_window", "large_capacity") if getattr(bigger, k) != getattr(rig, k)})
            rig, recompiles = bigger, recompiles + 1
            image, new_state, counts = jax.block_until_ready(mo.moving_frame_jit(scene, rig, *args_i[2:]))
        if i == 0:
            compile_s = time.perf_counter() - t
        else:
            wall.append(time.perf_counter() - t)
            cpu.append(time.process_time() - c)
        state = new_state
    pieces = _pieces(scene, rig, state, scene.flames[:, 0], jax.random.key(0))
    load = os.getloadavg()[0]
    med, med_cpu = statistics.median(wall), statistics.median(cpu)
    print(f"# noh_frame --moving ({'quick' if args.quick else 'full'}) {width}x{height}, {res}^2 depth maps, "
          f"{os.cpu_count()} cores, load average {load:.1f}, jax {jax.__version__}")
    print("| quantity | value |")
    print("|---|---|")
    for k, v in [("scene + rig setup s", f"{setup_s:.2f}"), ("first frame (compile + run) s", f"{compile_s:.2f}"),
                 ("recompiles (a buffer grew)", str(recompiles)),
                 (f"frame wall s, min / median / max of {len(wall)}", f"{min(wall):.3f} / {med:.3f} / {max(wall):.3f}"),
                 ("frame process CPU s (both cores), min / median / max",
                  f"{min(cpu):.3f} / {med_cpu:.3f} / {max(cpu):.3f}"),
                 ("garment / reflected pixels (last frame)", f"{int(counts.garment)} / {int(counts.reflection)}")]:
        print(f"| {k} | {v} |")
    print("\n| piece (jitted alone, median of 3) | wall s | CPU s |")
    print("|---|---|---|")
    for name, w_s, c_s in pieces:
        print(f"| {name} | {w_s:.3f} | {c_s:.3f} |")
    verdict = "met" if med <= 1.0 else "missed"
    print(f"\ntarget{' (quick size: the target is for 720x480)' if args.quick else ''}: frame <= 1 s: "
          f"{verdict.upper() if verdict == 'missed' else verdict} ({med:.3f} s median wall, {med_cpu:.3f} s CPU)")
    from _results import write_results

    write_results("noh_frame_moving", [
        dict(issue="17 Noh", target="moving garment, 720x480, shadow maps + PCSS + mip selection every frame, <= 1 s",
             measured=f"{med:.3f} s median frame wall ({min(wall):.3f}-{max(wall):.3f}), {med_cpu:.3f} s process CPU, "
                      f"{len(wall)} frames of the dance, compile {compile_s:.1f} s, load {load:.1f}",
             status=verdict, notes="; ".join(f"{n}: {c:.3f} s CPU" for n, _, c in pieces),
             figures={"median_frame_s": med, "median_frame_cpu_s": med_cpu, "compile_s": compile_s})],
        quick=args.quick)


if __name__ == "__main__":
    main()

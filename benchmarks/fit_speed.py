"""BTF fit speed (paper 004): 128 x 128 texels x 2160 light directions x RGB.

    python benchmarks/fit_speed.py            # the full case, both core settings, 5 interleaved runs
    python benchmarks/fit_speed.py --quick    # 16 x 16 x 100 lights, 2 runs, one process: a smoke run
    python benchmarks/fit_speed.py --solvers optimistix,native,jaxopt --repeats 7 --scipy-texels 192

Steps, timed apart:
1. synthesis + HDR merge in memory (`fitting.synth_maps`, `fitting.synth_observations`: 6 exposures,
   8-bit codes with shot and read noise, merged as `fitting fit` merges a capture directory);
2. the fit (`fitting.fit_maps`, chunks of 4096 texels, method "plain": per-texel least squares, the
   peers' objective; the default "robust" method of real captures is benchmarks/real_captures.py's)
   of every texel: compilation (the first chunk's shape) apart; optimistix by default, native and
   jaxopt with --solvers;
3. the peers on a random subset of texels (default 96; the naive one is too slow for the whole map:
   ~370 s), ratios in texels per second: `scipy.optimize.least_squares` per texel as a user would
   write it (a Python loop, all 10 parameters, default method 'trf' and 2-point Jacobian, a float64
   numpy model, the same starting values), and the strong one a user who knows scipy writes
   (benchmarks/_fit_varpro_scipy.py: rho_d and rho_s projected out, 4 parameters, analytic Jacobian,
   the same start).
Every method runs --repeats times, interleaved (ours, varpro, naive, ours, ...) so that the load of
the shared machine falls on all; wall and CPU time (the pool workers' CPU included), min / median /
max, ratios at the medians with the worst-best range (`_compare.ratio`). Costs are the fit's
objective 0.5 * sum w (R - model)^2 on the subset for every method.

Equal cores: the default run measures twice, in child processes: `--cores 1` (all pinned
to core 0, JAX and BLAS at one thread, the scipy loops in this process) and `--cores 2` (JAX's
default pools on both cores; each scipy peer's texel loop split over a 2-process pool of one-thread
workers).
"""

from __future__ import annotations

import sys

from _compare import equal_cores  # noqa: I001  (first: thread counts are set before numpy / jax load)

CORES = equal_cores() if "--cores" in sys.argv else None

import argparse  # noqa: E402
import json  # noqa: E402
import multiprocessing  # noqa: E402
import os  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import scipy.optimize  # noqa: E402
from _compare import Stats, load  # noqa: E402
from _compare import ratio as speed_ratio  # noqa: E402
from _fit_varpro_scipy import varpro_fit  # noqa: E402

from fitting import (  # noqa: E402
    LIGHT_DIRECTIONS,
    FitSettings,  # noqa: E402
    stratified_light_subset,
    synth_maps,
    synth_observations,
)
from fitting.fit import fit_maps  # noqa: E402
from fitting.lm import basis, initial_theta, project_rho, texel_cost, theta_to_geometry  # noqa: E402
from jaxrender.brdf import SIGMA_FLOOR  # noqa: E402

S_MIN, S_MAX = -12.0, 3.0


def numpy_model(x, light_dirs, view_dir):
    """R (L x 3) of the reciprocal model for x = (rho_d 3, rho_s 3, p, q, s_x, s_y): what a user
    would write in numpy (checked against jaxrender.brdf.reflectance below)."""
    rho_d, rho_s = x[:3], x[3:6]
    n = np.array([x[6], x[7], 1.0])
    n /= np.linalg.norm(n)
    sx = SIGMA_FLOOR + np.exp(np.clip(x[8], S_MIN, S_MAX))
    sy = SIGMA_FLOOR + np.exp(np.clip(x[9], S_MIN, S_MAX))
    t = np.array([1.0, 0.0, 0.0]) - n[0] * n
    t /= np.linalg.norm(t)
    b = np.cross(n, t)
    h = light_dirs + view_dir
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    hn, ht, hb = h @ n, h @ t, h @ b
    cos_i, cos_r = light_dirs @ n, view_dir @ n
    front = hn > 1e-6
    e = ((ht / sx) ** 2 + (hb / sy) ** 2) / np.where(front, hn, 1.0) ** 2
    d = np.where(front, np.exp(-np.minimum(e, 80.0)), 0.0)
    lit = (cos_i > 0) & (cos_r > 0)
    spec = np.where(lit, d / max(cos_r, 1e-4), 0.0)
    geo = (light_dirs[:, 2] > 0) & (view_dir[2] > 0)
    return np.where(geo[:, None], np.outer(np.maximum(cos_i, 0.0), rho_d) + np.outer(spec, rho_s), 0.0)


def scipy_fit(ratio, weight, light_dirs, view_dir, x0):
    w = weight / np.mean(weight[weight > 0]) if np.any(weight > 0) else weight
    sw = np.sqrt(w)[:, None]

    def residuals(x):
        return (sw * (ratio - numpy_model(x, light_dirs, view_dir))).ravel()

    return scipy.optimize.least_squares(residuals, x0)


@jax.jit
def _start_vector(r, w, light_dirs, view_dir):
    th = initial_theta(r, w, light_dirs, view_dir)
    n, sx, sy = theta_to_geometry(th)
    valid = w > 0  # weights over their mean on the used lights, as the peers normalise them
    mean = jnp.sum(jnp.where(valid, w, 0.0)) / jnp.maximum(jnp.sum(valid), 1)
    wn = jnp.where(valid, w / jnp.where(mean > 0, mean, 1.0), 0.0)
    rd, rs = project_rho(basis(n, sx, sy, light_dirs, view_dir), r.T, wn)
    return jnp.concatenate([rd, rs, th])


def start_vector(ratio, weight, light_dirs, view_dir):
    """The solver's starting point (rho projected at the starting geometry) as the peers' 10-vector;
    one compiled program for every texel (eager, each call re-traced its vmaps: ~4 s a texel)."""
    x = _start_vector(jnp.asarray(ratio), jnp.asarray(weight), jnp.asarray(light_dirs), jnp.asarray(view_dir))
    return np.asarray(x).astype(np.float64)


def _peer_texel(job) -> dict:
    """One texel by one scipy peer (a top-level function: it runs in pool workers too)."""
    kind, ratio, weight, d64, v64, x0 = job
    c0 = time.process_time()
    sol = scipy_fit(ratio, weight, d64, v64, x0) if kind == "naive" else varpro_fit(ratio, weight, d64, v64, x0)[1]
    return {"cost": float(sol.cost), "nfev": int(sol.nfev), "cpu_s": time.process_time() - c0}


def _warm_worker(job) -> int:
    """One texel and a pause (so that the next task goes to the other worker); the worker's pid."""
    _peer_texel(job)
    time.sleep(0.2)
    return os.getpid()


def compile_fit(obs, solver, chunk) -> float:
    """Seconds to compile `solver`'s fit: the first chunk's shape (every chunk is padded to it)."""
    h, w = obs.size
    total = h * w
    first = min(chunk, total)
    t0 = time.perf_counter()
    sub = type(obs)(ratio=obs.ratio.reshape((total,) + obs.ratio.shape[2:])[:first][None],
                    weight=obs.weight.reshape((total,) + obs.weight.shape[2:])[:first][None],
                    light_dirs=obs.light_dirs, view_dir=obs.view_dir,
                    n_valid=obs.n_valid.reshape(-1)[:first][None],
                    n_saturated=obs.n_saturated.reshape(-1)[:first][None],
                    n_dark=obs.n_dark.reshape(-1)[:first][None])
    fit_maps(sub, FitSettings(method="plain", solver=solver, chunk=chunk), progress=False)
    return time.perf_counter() - t0


def _per_texel(stats: Stats, texels: int) -> Stats:
    return Stats(stats.compile_s, [w / texels for w in stats.wall], [c / texels for c in stats.cpu])


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="16 x 16 texels x 100 lights, 2 runs, optimistix only")
    parser.add_argument("--size", type=int, default=None)
    parser.add_argument("--lights", type=int, default=None, help="number of lights (default all 2160)")
    parser.add_argument("--scipy-texels", type=int, default=None, help="the peers' subset (default 96)")
    parser.add_argument("--repeats", type=int, default=None, help="interleaved runs of every method (default 5)")
    parser.add_argument("--chunk", type=int, default=4096)
    parser.add_argument("--solvers", default="optimistix", help="comma-separated: optimistix,native,jaxopt")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--cores", type=int, default=None, help="child run in one core setting (see above)")
    args = parser.parse_args(argv)
    size = args.size or (16 if args.quick else 128)
    n_lights = args.lights or (100 if args.quick else 2160)
    n_scipy = args.scipy_texels or (4 if args.quick else 96)
    repeats = args.repeats or (2 if args.quick else 5)
    solvers = args.solvers.split(",")
    key = jax.random.key(0)
    k_maps, k_obs, k_sel = jax.random.split(key, 3)
    ids = (np.arange(len(LIGHT_DIRECTIONS)) if n_lights >= len(LIGHT_DIRECTIONS)
           else stratified_light_subset(k_sel, n_lights))
    dirs = jnp.asarray(LIGHT_DIRECTIONS[ids], jnp.float32)
    print(f"# fit speed: {size}x{size} texels x {len(ids)} lights x RGB; {CORES or 'default'} core(s); "
          f"devices {jax.devices()}; {platform.processor() or platform.machine()}", flush=True)

    t0 = time.perf_counter()
    maps_true = synth_maps(k_maps, (size, size))
    obs = synth_observations(k_obs, maps_true, dirs, progress=False)
    jax.block_until_ready(obs.ratio)
    synth_s = time.perf_counter() - t0
    print(f"synthesis + merge (in memory): {synth_s:.1f} s", flush=True)

    # the model the scipy peer uses is the toolkit's model
    from jaxrender.brdf import BTFTexel, reflectance
    x_chk = np.array([0.3, 0.2, 0.1, 0.6, 0.5, 0.4, 0.1, -0.2, np.log(0.1), np.log(0.2)])
    n_chk, sx_chk, sy_chk = theta_to_geometry(jnp.asarray(x_chk[6:], jnp.float32))
    tex = BTFTexel.single(jnp.asarray(x_chk[:3], jnp.float32), jnp.asarray(x_chk[3:6], jnp.float32), n_chk, sx_chk,
                          sy_chk)
    ref = np.asarray(jax.vmap(lambda wi: reflectance(tex, wi, obs.view_dir))(dirs))
    np.testing.assert_allclose(numpy_model(x_chk, np.asarray(dirs, np.float64), np.array([0, 0, 1.0])), ref,
                               rtol=2e-4, atol=2e-5)

    # the peers' subset and starting values (computed outside every timing)
    total = size * size
    subset = np.sort(np.random.default_rng(1).choice(total, n_scipy, replace=False))
    ratio = np.asarray(obs.ratio, np.float32).reshape(total, len(ids), 3)
    weight = np.asarray(obs.weight, np.float32).reshape(total, len(ids))
    d64, v64 = np.asarray(dirs, np.float64), np.array([0.0, 0.0, 1.0])
    x0s = [start_vector(ratio[i], weight[i], dirs, obs.view_dir) for i in subset]
    jobs = {kind: [(kind, ratio[i].astype(np.float64), weight[i].astype(np.float64), d64, v64, x0)
                   for i, x0 in zip(subset, x0s)] for kind in ("varpro", "naive")}

    if CORES == 2:  # two worker processes of one BLAS / OpenMP thread each (they inherit this environment)
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
            os.environ[var] = "1"
    pool = multiprocessing.get_context("spawn").Pool(2) if CORES == 2 else None
    stats, maps, peer_out = {}, {}, {}
    try:
        # compile / start-up apart: each solver's first chunk; every pool worker has imported everything and fit
        # a texel of each peer
        for solver in solvers:
            stats[solver] = Stats(compile_fit(obs, solver, args.chunk), [], [])
            print(f"{solver}: compile + first chunk {stats[solver].compile_s:.1f} s", flush=True)
        for kind in ("varpro", "naive"):
            t0 = time.perf_counter()
            if pool:
                pids = set()
                while len(pids) < 2:
                    pids |= set(pool.map(_warm_worker, [jobs[kind][0]] * 2, chunksize=1))
            else:
                _peer_texel(jobs[kind][0])
            stats[kind] = Stats(time.perf_counter() - t0, [], [])

        def run(name):
            t0, c0 = time.perf_counter(), time.process_time()
            if name in solvers:
                maps[name] = fit_maps(obs, FitSettings(method="plain", solver=name, chunk=args.chunk), progress=False)
                jax.block_until_ready(maps[name].rho_d)
                worker_cpu = 0.0
            else:
                out = pool.map(_peer_texel, jobs[name]) if pool else [_peer_texel(j) for j in jobs[name]]
                peer_out[name] = out
                worker_cpu = sum(o["cpu_s"] for o in out) if pool else 0.0
            stats[name].wall.append(time.perf_counter() - t0)
            stats[name].cpu.append(time.process_time() - c0 + worker_cpu)

        load0 = load()
        for r in range(repeats):  # interleaved: the machine's load falls on every method alike
            for name in [*solvers, "varpro", "naive"]:
                run(name)
            print(f"run {r + 1}/{repeats}: " + ", ".join(f"{k} {s.wall[-1]:.2f} s" for k, s in stats.items())
                  + f" (load {load():.1f})", flush=True)
        load1 = load()
    finally:
        if pool:
            pool.close()

    def subset_costs(m):
        out = []
        for i in subset:
            r, c = divmod(int(i), size)
            out.append(float(texel_cost(m.rho_d[r, c], m.rho_s[r, c], m.normal[r, c], m.sigma_x[r, c],
                                        m.sigma_y[r, c], ratio[i], weight[i], dirs, obs.view_dir)))
        return out

    texels = {**{s: total for s in solvers}, "varpro": n_scipy, "naive": n_scipy}
    per_texel = {k: _per_texel(s, texels[k]) for k, s in stats.items()}
    costs = {**{s: subset_costs(maps[s]) for s in solvers},
             **{k: [o["cost"] for o in peer_out[k]] for k in ("varpro", "naive")}}
    labels = {**{s: f"{s} LM (vmapped, chunks of {args.chunk})" for s in solvers},
              "varpro": "scipy least_squares, variable projection (4 params, analytic Jacobian)",
              "naive": "scipy least_squares per texel (trf, 2-point, 10 params)"}
    mmm = lambda xs: "/".join(f"{x:.3g}" for x in (min(xs), np.median(xs), max(xs)))  # noqa: E731
    print(f"\n{CORES or 'default'} core(s){', scipy peers in a 2-process pool' if pool else ''}; {repeats} interleaved "
          f"runs; peers on a subset of {n_scipy} of the {total} texels; load {load0:.1f}-{load1:.1f}")
    print("| method | texels | compile / start s | wall s (min/med/max) | CPU s (min/med/max) | "
          "texels/s (wall, median) | median cost (subset) | median nfev |")
    print("|---|---:|---:|---|---|---:|---:|---:|")
    for k, s in stats.items():
        nfev = np.median([o["nfev"] for o in peer_out[k]]) if k in peer_out else float("nan")
        print(f"| {labels[k]} | {texels[k]} | {s.compile_s:.1f} | {mmm(s.wall)} | {mmm(s.cpu)} | "
              f"{texels[k] / np.median(s.wall):.1f} | {np.median(costs[k]):.5g} | {nfev:.0f} |")
    ratios = {}
    print("\n| ours | peer | texels/s ratio, wall median (worst-best) | by CPU median (worst-best) |")
    print("|---|---|---|---|")
    for s in solvers:
        for peer in ("varpro", "naive"):
            w, c = speed_ratio(per_texel[peer], per_texel[s]), speed_ratio(per_texel[peer], per_texel[s], "cpu")
            ratios[f"{s}/{peer}"] = {"wall": w, "cpu": c}
            print(f"| {s} | {peer} | {w[0]:.1f}x ({w[1]:.1f}-{w[2]:.1f}x) | {c[0]:.1f}x ({c[1]:.1f}-{c[2]:.1f}x) |")
    print(f"\nsynthesis + merge (in memory, apart from the fit): {synth_s:.1f} s; naive scipy scaled to all {total} "
          f"texels: {total * np.median(per_texel['naive'].wall):.0f} s (wall)")
    record = {"size": size, "lights": len(ids), "cores": CORES, "repeats": repeats, "subset_texels": n_scipy,
              "load": [load0, load1], "synth_merge_s": synth_s, "ratios": ratios,
              "methods": {k: {"label": labels[k], "texels": texels[k], "compile_s": s.compile_s, "wall": s.wall,
                              "cpu": s.cpu, "median_cost_subset": float(np.median(costs[k]))}
                          for k, s in stats.items()},
              "peer_per_texel_cpu": {k: [o["cpu_s"] for o in peer_out[k]] for k in ("varpro", "naive")}}
    if args.json:
        args.json.write_text(json.dumps(record, indent=1))
    return record


def headline(records: dict, quick: bool) -> None:
    """The summary row from the records of each core setting (`records[cores]`)."""
    from _results import write_results

    parts, met = [], True
    for cores, rec in records.items():
        r = rec["ratios"]["optimistix/varpro"]
        n = rec["ratios"]["optimistix/naive"]
        where = f"{cores} core{'s' if cores != 1 else ''}" if cores else "default cores"
        parts.append(f"{where}: {r['wall'][0]:.1f}x wall ({r['wall'][1]:.1f}-{r['wall'][2]:.1f}), "
                     f"{r['cpu'][0]:.1f}x CPU vs varpro scipy; {n['wall'][0]:.0f}x wall ({n['wall'][1]:.0f}-"
                     f"{n['wall'][2]:.0f}), {n['cpu'][0]:.0f}x CPU vs naive (load {rec['load'][0]:.1f}-"
                     f"{rec['load'][1]:.1f})")
        met = met and r["wall"][0] >= 50 and r["cpu"][0] >= 50
    rec = next(iter(records.values()))
    write_results("fit_speed", [dict(
        area="fitting", target=">= 50x scipy least_squares texels/s at equal cost",
        measured=f"optimistix LM, {rec['size']}x{rec['size']}x{rec['lights']}: " + "; ".join(parts),
        status="met" if met else "missed",
        notes=f"strongest peer: variable projection + analytic Jacobian (benchmarks/_fit_varpro_scipy.py); "
              f"texels/s ratios, median (worst-best) of {rec['repeats']} interleaved runs; ours fits all "
              f"{rec['size'] ** 2} texels, the scipy peers a random subset of {rec['subset_texels']} (same starts, "
              f"same median cost); 1 core: all pinned to core 0; 2 cores: scipy in a 2-process pool",
        figures={str(c): rec_c["ratios"]["optimistix/varpro"] for c, rec_c in records.items()})], quick=quick)


def equal_cores_runs(argv: list[str]) -> int:
    """The default run: both core settings in child processes, then the headline rows."""
    records = {}
    for cores in (1, 2):
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "fit.json"
            subprocess.run([sys.executable, __file__, "--cores", str(cores), "--json", str(path), *argv], check=True)
            records[cores] = json.loads(path.read_text())
    headline(records, quick=False)
    return 0


if __name__ == "__main__":
    if "--quick" in sys.argv:  # a smoke run: one process, the default cores, nothing written
        headline({None: main()}, quick=True)
    elif CORES is None and "--json" not in sys.argv:
        sys.exit(equal_cores_runs(sys.argv[1:]))
    else:
        main()

"""Fitting a measured stack at scale: ingest and fit apart, memory of every process.
Every fit here is `--method plain` (per-texel least squares of the paper's dense captures; the robust
default of real captures costs about three solves a texel and is benchmarks/real_captures.py's).

    python benchmarks/capture_scale.py                  # 1024x1024 and 256x256, 540 lights x 2 exposures
    python benchmarks/capture_scale.py --sizes 256      # the 256x256 part only
    python benchmarks/capture_scale.py --quick          # 32x32 x 60 lights: a smoke run, nothing recorded
                                                        # (ingest and fit: no pyramid, no speed comparison,
                                                        # no Dask)

A synthetic capture as a user of the paper's rig has (8-bit PNG, 2 exposures: 1/640 s and 1/125 s, 540 of
the paper's light directions, `fitting.synth` maps and sensor) is written once under --root and
reused. Every step runs as its own command (`fitting ingest`, `fitting fit`, or a short Python
program for today's in-memory path) under `/usr/bin/time` (the OS's own wall, CPU and peak
resident memory of the command) while psutil polls every process of the command's tree (Dask
workers included) for its peak resident memory. Steps, per size:
1. `fitting ingest` (float16, the default) and `fitting fit STORE` with the EM pyramid;
2. at 256x256 also: today's in-memory path (`merge_capture` + `fit_observations`, no pyramid)
   against `fitting ingest --dtype float32` + `fitting fit STORE --no-pyramid` (same devices,
   compiled programs loaded from one persistent cache so compile time is out of the rate; the
   maps must be bit-identical), the float16 store's maps against the float32 store's and the
   truth, and the fit on a local Dask cluster of 1 and 2 workers (`--dask-workers`).
The machine is shared: the load average is recorded before and after each step.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import psutil

sys.path.insert(0, str(Path(__file__).parent))
from _results import write_results  # noqa: E402

EXPOSURES = (0.0015625, 0.008)
FITTING = [sys.executable, "-m", "jaxrender.app.cli.programs", "fitting"]
FIT_PLAIN = [*FITTING, "fit", "--method", "plain"]  # the dense captures' per-texel fit (module docstring)


def write_capture(root: Path, size: int, n_lights: int, *, batch: int = 4) -> Path:
    """A synthetic 8-bit PNG capture (2 exposures) and its true maps (`truth.npz`); reused when present."""
    from fitting import LIGHT_DIRECTIONS, Sensor, paper_light_angles, stratified_light_subset, synth_maps
    from fitting.synth import synth_codes, synth_white_codes
    from jaxrender.io import write_png

    cap = root / f"capture_{size}_{n_lights}"
    if (cap / "capture.json").is_file():
        return cap
    shutil.rmtree(cap, ignore_errors=True)
    (cap / "images").mkdir(parents=True)
    k_maps, k_obs, k_white, k_sel = jax.random.split(jax.random.key(12), 4)
    ids = stratified_light_subset(k_sel, n_lights)
    texels = synth_maps(k_maps, (size, size))
    np.savez(cap / "truth.npz", rho_d=np.asarray(texels.rho_d), normal=np.asarray(texels.lobe0.normal))
    sensor = Sensor(bits=8)
    exposures = jnp.asarray(EXPOSURES, jnp.float32)
    view = jnp.asarray([0.0, 0.0, 1.0], jnp.float32)
    dirs = jnp.asarray(LIGHT_DIRECTIONS[ids], jnp.float32)
    angles = paper_light_angles()[ids]
    white = np.asarray(synth_white_codes(k_white, jnp.full(3, 0.95, jnp.float32), exposures, size=(size, size),
                                         sensor=sensor))
    names = [f"images/white_e{e}.png" for e in range(len(EXPOSURES))]
    for e, name in enumerate(names):
        write_png(cap / name, white[e], srgb=False)
    lights = []
    t0 = time.perf_counter()
    with concurrent.futures.ThreadPoolExecutor(max_workers=2) as pool:
        for start in range(0, n_lights, batch):
            idx = jnp.arange(start, start + batch)
            codes = np.asarray(synth_codes(k_obs, texels, dirs[jnp.minimum(idx, n_lights - 1)], idx, view, exposures,
                                           sensor=sensor))
            futures = []
            for b in range(min(batch, n_lights - start)):
                files = [f"images/l{start + b:04d}_e{e}.png" for e in range(len(EXPOSURES))]
                futures += [pool.submit(write_png, cap / f, codes[b, e], srgb=False) for e, f in enumerate(files)]
                lights.append({"theta_deg": float(angles[start + b, 0]), "phi_deg": float(angles[start + b, 1]),
                               "images": files})
            for future in futures:
                future.result()
            if start % (batch * 25) == 0:
                print(f"  capture {size}: {start + batch}/{n_lights} lights, {time.perf_counter() - t0:.0f} s",
                      flush=True)
    manifest = {"format": "jaxrender-capture", "version": 1, "size": [size, size], "response": "linear",
                "exposures_s": list(EXPOSURES), "view": {"theta_deg": 0.0, "phi_deg": 0.0},
                "white": {"reflectance": 0.95, "images": names}, "lights": lights}
    (cap / "capture.json").write_text(json.dumps(manifest))
    return cap


def measure(name: str, cmd: list[str], env: dict) -> dict:
    """Run `cmd` under /usr/bin/time; poll the peak RSS of every process of its tree."""
    load_before = os.getloadavg()
    with tempfile.NamedTemporaryFile("w+", suffix=".err") as err, tempfile.NamedTemporaryFile("w+") as out:
        t0 = time.perf_counter()
        proc = subprocess.Popen(["/usr/bin/time", "-f", "TIME %M %e %U %S", *cmd], stdout=out, stderr=err, env=env)
        peaks: dict[int, dict] = {}
        root = psutil.Process(proc.pid)
        while proc.poll() is None:
            try:
                family = [root, *root.children(recursive=True)]
            except psutil.NoSuchProcess:
                break
            for p in family[1:]:  # not /usr/bin/time itself
                try:
                    rss = p.memory_info().rss
                    cpu = sum(p.cpu_times()[:2])
                    entry = peaks.setdefault(p.pid, {"cmd": " ".join(p.cmdline()[1:4])[:80], "rss": 0, "cpu": 0.0})
                    entry["rss"], entry["cpu"] = max(entry["rss"], rss), cpu
                except (psutil.NoSuchProcess, psutil.AccessDenied):
                    pass
            time.sleep(0.2)
        wall = time.perf_counter() - t0
        err.seek(0)
        text = err.read()
        out.seek(0)
        stdout = out.read()
    if proc.returncode != 0:
        raise RuntimeError(f"{name}: exit {proc.returncode}\n{text[-3000:]}")
    line = [x for x in text.splitlines() if x.startswith("TIME ")][-1].split()
    result = {"step": name, "wall_s": float(line[2]), "cpu_s": float(line[3]) + float(line[4]),
              "peak_rss_gb": int(line[1]) * 1024 / 2**30, "load_before": [round(x, 2) for x in load_before],
              "load_after": [round(x, 2) for x in os.getloadavg()], "poll_wall_s": wall,
              "processes": sorted(({"cmd": v["cmd"], "peak_rss_gb": v["rss"] / 2**30, "cpu_s": v["cpu"]}
                                   for v in peaks.values()), key=lambda d: -d["peak_rss_gb"]),
              "stdout": stdout.strip()[-300:]}
    procs = ", ".join(f"{p['peak_rss_gb']:.2f}" for p in result["processes"])
    print(f"{name:<34} wall {result['wall_s']:8.1f} s  cpu {result['cpu_s']:8.1f} s  "
          f"peak RSS {result['peak_rss_gb']:.2f} GB (every process: {procs} GB)  "
          f"load {result['load_before'][0]:.1f} -> {result['load_after'][0]:.1f}",
          flush=True)
    return result


IN_MEMORY = """
import sys, time
from fitting import FitSettings, fit_observations, load_capture, merge_capture
t0 = time.perf_counter()
obs = merge_capture(load_capture(sys.argv[1]), progress=False)
print("merge_s", time.perf_counter() - t0)
fit_observations(obs, sys.argv[2], FitSettings(method="plain"), pyramid=False, progress=False)
"""


RATE = """
import json, sys, time
import numpy as np
from fitting import load_capture, merge_capture, open_store
from fitting import FitSettings
from fitting.fit import fit_maps, fit_store_maps
PLAIN = FitSettings(method="plain")
obs = merge_capture(load_capture(sys.argv[1]), progress=False)
store = open_store(sys.argv[2])
fit_maps(obs, PLAIN, progress=False)  # compile (or load) the tile program once
out = {"in-memory": [], "store": []}
for rep, path in enumerate(["in-memory", "store", "store", "in-memory", "in-memory", "store"]):
    t0, c0 = time.perf_counter(), time.process_time()
    if path == "store":
        maps = fit_store_maps(store, PLAIN, partial_dir=sys.argv[3] + f"/partial{rep}", progress=False)
    else:
        maps = fit_maps(obs, PLAIN, progress=False)
    out[path].append([time.perf_counter() - t0, time.process_time() - c0])
    out.setdefault("maps_" + path, maps.rho_d)
same = np.array_equal(out.pop("maps_store"), out.pop("maps_in-memory"))
print(json.dumps({**out, "same_maps": bool(same)}))
"""


def rate_compare(cap: Path, store32: Path, work: Path, env: dict) -> dict:
    """Fit rate of the store path vs the in-memory path in one process, alternating (A B B A A B),
    compile done first: wall and CPU seconds of each fit of every texel."""
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    load = os.getloadavg()
    proc = subprocess.run([sys.executable, "-c", RATE, str(cap), str(store32), str(work)], env=env,
                          capture_output=True, text=True, check=True)
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out["load_before"], out["load_after"] = load, os.getloadavg()
    return out


def _btf(path: Path):
    from jaxrender.io import read_btf

    manifest, levels = read_btf(path)
    return manifest, levels[0]


def _angle_deg(a, b):
    na = np.stack([a[f"normal.{x}"] for x in "XYZ"], -1)
    nb = np.stack([b[f"normal.{x}"] for x in "XYZ"], -1) if isinstance(b, dict) and "normal.X" in b else b
    return np.degrees(np.arccos(np.clip(np.sum(na * nb, -1), -1, 1)))


def compare_maps(a: dict, b: dict) -> dict:
    """Differences of fitted maps a vs b (level-0 channel dicts), over texels both fits converged."""
    ok = (a["converged"] > 0) & (b["converged"] > 0)
    ang = _angle_deg(a, b)[ok]
    rho = np.abs(np.stack([a[f"rho_d.{c}"] - b[f"rho_d.{c}"] for c in "RGB"], -1))[ok]
    sig = np.abs(a["sigma_x"] / b["sigma_x"] - 1)[ok]
    return {"texels": int(ok.sum()), "normal_deg_median": float(np.median(ang)),
            "normal_deg_p99": float(np.percentile(ang, 99)),
            "rho_d_abs_median": float(np.median(rho)), "rho_d_abs_p99": float(np.percentile(rho, 99)),
            "sigma_x_rel_median": float(np.median(sig)), "sigma_x_rel_p99": float(np.percentile(sig, 99))}


def compare_truth(a: dict, truth) -> dict:
    ok = a["converged"] > 0
    ang = _angle_deg(a, np.asarray(truth["normal"]))[ok]
    rho = np.abs(np.stack([a[f"rho_d.{c}"] for c in "RGB"], -1) - truth["rho_d"])[ok]
    return {"normal_deg_median": float(np.median(ang)), "normal_deg_p99": float(np.percentile(ang, 99)),
            "rho_d_abs_median": float(np.median(rho))}


def run_size(root: Path, size: int, n_lights: int, env: dict, *, speed: bool, dask: tuple[int, ...],
             steps: list, pyramid: bool = True) -> dict:
    t0 = time.perf_counter()
    cap = write_capture(root, size, n_lights)
    print(f"capture {size}x{size}x{n_lights}: {cap} ({time.perf_counter() - t0:.0f} s to write or find)", flush=True)
    disk = sum(p.stat().st_size for p in (cap / "images").iterdir())
    out = {"size": size, "lights": n_lights, "capture_bytes": disk}
    tag = f"{size}x{size}x{n_lights}"
    store16, btf16 = root / f"store16_{size}", root / f"btf16_{size}"
    for path in (store16, btf16):
        shutil.rmtree(path, ignore_errors=True)
    steps.append(measure(f"{tag} ingest float16", [*FITTING, "ingest", str(cap), "--store", str(store16)], env))
    out["store16_bytes"] = sum(p.stat().st_size for p in store16.rglob("*") if p.is_file())
    steps.append(measure(f"{tag} fit store" + (" (+pyramid)" if pyramid else " (no pyramid)"),
                         [*FIT_PLAIN, str(store16), "--out", str(btf16)] + ([] if pyramid else ["--no-pyramid"]),
                         env))
    manifest, level16 = _btf(btf16)
    out["fit_seconds"] = manifest["fit"]["seconds"]
    out["fit_cpu_seconds"] = manifest["fit"].get("cpu_seconds")
    out["ingest_step"], out["fit_step"] = steps[-2]["step"], steps[-1]["step"]
    out["texels_per_s"] = size * size / manifest["fit"]["seconds"]
    truth = np.load(cap / "truth.npz")
    out["float16_vs_truth"] = compare_truth(level16, truth)
    if speed:
        store32, btf32, btfmem = root / f"store32_{size}", root / f"btf32_{size}", root / f"btfmem_{size}"
        for path in (store32, btf32, btfmem):
            shutil.rmtree(path, ignore_errors=True)
        steps.append(measure(f"{tag} ingest float32", [*FITTING, "ingest", str(cap), "--store", str(store32),
                                                       "--dtype", "float32"], env))
        steps.append(measure(f"{tag} fit float32 store", [*FIT_PLAIN, str(store32), "--out", str(btf32),
                                                          "--no-pyramid"], env))
        steps.append(measure(f"{tag} in-memory merge+fit", [sys.executable, "-c", IN_MEMORY, str(cap), str(btfmem)],
                             env))
        m32, level32 = _btf(btf32)
        mmem, levelmem = _btf(btfmem)
        out["store32_fit_s"], out["inmemory_fit_s"] = m32["fit"]["seconds"], mmem["fit"]["seconds"]
        out["store_vs_inmemory_rate"] = mmem["fit"]["seconds"] / m32["fit"]["seconds"]
        out["float32_store_bit_identical"] = all(np.array_equal(level32[k], levelmem[k]) for k in levelmem)
        out["float16_vs_float32"] = compare_maps(level16, level32)
        out["float32_vs_truth"] = compare_truth(level32, truth)
        out["rate"] = rate_compare(cap, store32, root / f"rate_{size}", env)
        med = {k: np.median(np.asarray(out["rate"][k]), axis=0) for k in ("in-memory", "store")}
        out["store_over_inmemory_wall"] = float(med["store"][0] / med["in-memory"][0])
        out["store_over_inmemory_cpu"] = float(med["store"][1] / med["in-memory"][1])
        print(f"  rate, same process alternating: store/in-memory time {out['store_over_inmemory_wall']:.3f} wall, "
              f"{out['store_over_inmemory_cpu']:.3f} CPU (medians of 3); runs {out['rate']}", flush=True)
        print(f"  store vs in-memory fit: {m32['fit']['seconds']:.1f} s vs {mmem['fit']['seconds']:.1f} s "
              f"(rate ratio {out['store_vs_inmemory_rate']:.3f}); bit-identical: {out['float32_store_bit_identical']}")
        print(f"  float16 vs float32 store: {out['float16_vs_float32']}")
    for n in dask:
        btf = root / f"btf_dask{n}_{size}"
        shutil.rmtree(btf, ignore_errors=True)
        steps.append(measure(f"{tag} fit store dask x{n}", [*FIT_PLAIN, str(store16), "--out", str(btf),
                                                           "--no-pyramid", "--dask-workers", str(n)], env))
        md, leveld = _btf(btf)
        out[f"dask{n}_fit_s"] = md["fit"]["seconds"]
        out[f"dask{n}_same_maps"] = all(np.array_equal(leveld[k], level16[k]) for k in leveld if k in level16)
        print(f"  dask x{n}: fit {md['fit']['seconds']:.1f} s, "
              f"same maps as one process: {out[f'dask{n}_same_maps']}")
    return out


PAPER = {"texels": 3888 * 2529, "lights": 2160, "exposures": 6}  # paper 004's capture


def paper_projection(r: dict, steps: list) -> dict:
    """The paper's capture from the figures measured at one size, scaled by the work:
    ingest by image pixels read, the fit by texel x light (its cost is a sum over lights)."""
    by_name = {s["step"]: s for s in steps}
    ingest, fit = by_name[r["ingest_step"]], by_name[r["fit_step"]]
    measured_pixels = (r["lights"] + 1) * len(EXPOSURES) * r["size"] ** 2
    paper_pixels = (PAPER["lights"] + 1) * PAPER["exposures"] * PAPER["texels"]
    fit_cpu_per = r["fit_cpu_seconds"] / (r["size"] ** 2 * r["lights"])
    pyramid_cpu_per = max(fit["cpu_s"] - r["fit_cpu_seconds"], 0.0) / r["size"] ** 2  # + startup: pessimistic
    stored_per = r["store16_bytes"] / (r["size"] ** 2 * r["lights"])
    out = {
        "images": (PAPER["lights"] + 1) * PAPER["exposures"],
        "decoded_bytes_8bit": paper_pixels * 3, "decoded_bytes_16bit": paper_pixels * 6,
        "store_bytes_raw": PAPER["texels"] * PAPER["lights"] * 7,
        "store_bytes_compressed": PAPER["texels"] * PAPER["lights"] * stored_per,
        "ingest_cpu_h": ingest["cpu_s"] / measured_pixels * paper_pixels / 3600,
        "ingest_wall_h_as_measured": ingest["wall_s"] / measured_pixels * paper_pixels / 3600,
        "fit_cpu_h": fit_cpu_per * PAPER["texels"] * PAPER["lights"] / 3600,
        "pyramid_cpu_h": pyramid_cpu_per * PAPER["texels"] / 3600,
        "maps_bytes_level0": PAPER["texels"] * 100,
    }
    out["fit_wall_h_one_2core_machine"] = out["fit_cpu_h"] / 2
    out["fit_wall_h_on_workers"] = {n: out["fit_cpu_h"] / (2 * n) for n in (1, 4, 16, 64)}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1024, 256])
    parser.add_argument("--lights", type=int, default=540)
    parser.add_argument("--root", type=Path, default=Path(tempfile.gettempdir()) / "capture_scale")
    parser.add_argument("--quick", action="store_true",
                        help="32x32 x 60 lights, ingest + fit (no pyramid) only, nothing recorded")
    args = parser.parse_args()
    sizes, n_lights = ([32], 60) if args.quick else (args.sizes, args.lights)
    args.root.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    env.pop("JAX_ENABLE_X64", None)
    # one persistent compilation cache: every measured command loads the compiled tile program
    env["JAX_COMPILATION_CACHE_DIR"] = str(args.root / "jax-cache")
    env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    print(f"{platform.node()} {os.cpu_count()} cores, {psutil.virtual_memory().total / 2**30:.0f} GiB; "
          f"load {os.getloadavg()}; shared machine", flush=True)
    steps: list = []
    results = []
    for size in sizes:
        small = size <= 256
        # quick (a smoke run; each step is a process that imports JAX): ingest and fit only, no EM pyramid (its
        # compile was most of the quick run; em_pyramid --quick runs the EM, tests/test_dask_fit.py the Dask fit)
        results.append(run_size(args.root, size, n_lights, env, speed=small and not args.quick,
                                dask=(1, 2) if small and not args.quick else (), steps=steps,
                                pyramid=not args.quick))
    report = {"sizes": results, "steps": steps, "load_end": os.getloadavg()}
    big = max(results, key=lambda r: r["size"])
    if big.get("fit_cpu_seconds"):
        report["paper_projection"] = paper_projection(big, steps)
        print("paper's capture, projected from", big["size"], json.dumps(report["paper_projection"], indent=1))
    (args.root / "capture_scale.json").write_text(json.dumps(report, indent=1))
    print(json.dumps(results, indent=1))
    rows = []
    for r in results:
        mem = max(s["peak_rss_gb"] for s in steps if s["step"].startswith(f"{r['size']}x"))
        procs = max(p["peak_rss_gb"] for s in steps if s["step"].startswith(f"{r['size']}x") for p in s["processes"])
        target = f"{r['size']}x{r['size']}x{r['lights']}: every process <= 3 GB"
        rows.append(dict(area="fitting", target=target,
                         measured=f"peak RSS {max(mem, procs):.2f} GB; fit {r['texels_per_s']:.0f} texels/s",
                         status="met" if max(mem, procs) <= 3 else "missed", figures=r))
    if "paper_projection" in report:
        rows[0]["figures"] = {**rows[0]["figures"], "paper_projection": report["paper_projection"]}
    previous = Path(__file__).parent / "results" / "capture_scale.json"
    if previous.is_file() and not args.quick:  # keep the rows of sizes not measured in this run
        targets = {row["target"] for row in rows}
        rows += [row for row in json.loads(previous.read_text()).get("rows", []) if row.get("target") not in targets]
    write_results("capture_scale", rows, quick=args.quick)


if __name__ == "__main__":
    main()

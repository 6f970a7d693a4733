"""EM multi-resolution BTF (paper 004, section 3.2): rendering error of the coarse levels, speed
against a batched numpy implementation of the same EM, and agreement with scikit-learn.

(a) Error. Coarse texels whose 4 children have two distinct specular directions: relative RMS of
    R (jaxrender.brdf.reflectance) of the coarse texel against the average of its children's R
    over light/view pairs concentrated around the specular peaks, for the 2-lobe EM level, a
    one-lobe moment-matched level (LEAN/Toksvig-style) and the ordinary mip (every parameter
    averaged). Also on the synthetic woven BTF (fitting.synth_maps, 256x256): every level of each
    pyramid against the box-filtered rendering of level 0 over the level's footprint.
(b) Speed. The whole 256x256 pyramid (8 levels) by fitting.pyramid.pyramid_levels (jit, vmap,
    float32) vs benchmarks/_em_numpy.py (the same algorithm vectorized over texels in numpy,
    float32); compile time apart; equal accuracy checked level by level from the same input.
(c) scikit-learn. GaussianMixture(2, covariance_type='diag') with the same initialization on the
    same samples: final log-likelihood and parameters.

    python benchmarks/em_pyramid.py [--quick]
    python benchmarks/em_pyramid.py --speed-runs 5   # only (b) on the woven BTF: 5 measurements
                                                     # and the time per level
    python benchmarks/em_pyramid.py --equal-cores    # only (d): JAX vs numpy at equal cores
    python benchmarks/em_pyramid.py --profile --cores 1   # where the time goes, pinned to one core

(d) Equal cores. (b) lets JAX use both cores while the numpy peer runs one thread. Here
    the whole woven pyramid is timed twice, interleaved with the peer, wall and CPU, min / median /
    max: pinned to core 0 with every library at one thread (JAX's CPU pools included), and free on
    both cores with the numpy peer split over two processes (benchmarks/_em_numpy.py,
    `pyramid_numpy_pool`: each level's texels halved between a 2-process pool). Part of the default run.
"""

from __future__ import annotations

# ruff: noqa: E402  (the thread counts are set by equal_cores before numpy / jax are imported)
import sys

from _compare import equal_cores  # noqa: I001  (first: thread counts are set before numpy / jax load)

CORES = equal_cores() if "--cores" in sys.argv else None

import argparse
import json
import os
import subprocess
import tempfile
import time
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from _em_numpy import em_texels_numpy, gather_children_numpy, pyramid_numpy, pyramid_numpy_pool  # noqa: E402
from _results import cpu_description, write_results  # noqa: E402

from fitting.em import (  # noqa: E402
    GaussianMixture,
    em_downsample,
    em_fit,
    em_texels,
    gather_children,
    mip_texel,
    moment_matched_texel,
)
from fitting.pyramid import pyramid_levels, pyramid_sizes  # noqa: E402
from fitting.synth import synth_maps  # noqa: E402
from jaxrender.brdf import BTFTexel, reflectance  # noqa: E402

FIGURES = Path(__file__).parent / "figures"


# ---------------------------------------------------------------------------------------------
# Inputs


def _direction(tilt, azimuth):
    return np.stack([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)], -1)


def two_direction_children(seed, n, *, specular_only=False):
    """`n` coarse texels, children split 2+2 or 3+1 between two directions >= 25 degrees apart,
    each child jittered around its direction (the generator of tests/test_pyramid.py)."""
    rng = np.random.default_rng(seed)
    tilt_a, az_a = rng.uniform(np.radians(10), np.radians(30), n), rng.uniform(0, 2 * np.pi, n)
    tilt_b = rng.uniform(np.radians(10), np.radians(30), n)
    az_b = az_a + rng.choice([-1, 1], n) * rng.uniform(np.radians(100), np.radians(180), n)
    which = np.array([[0, 1, 0, 1], [0, 0, 0, 1], [1, 0, 1, 1], [0, 1, 1, 0]])[np.arange(n) % 4]  # n 4
    pick = lambda a: np.take_along_axis(a, which.reshape(which.shape + (1,) * (a.ndim - 2)), axis=1)  # noqa: E731
    # Each child jitters around its direction: 2 degrees of tilt, 5 of azimuth, 15 % in sigma and rho_s.
    tilt = pick(np.stack([tilt_a, tilt_b], 1)) + rng.normal(0, np.radians(2), (n, 4))
    azimuth = pick(np.stack([az_a, az_b], 1)) + rng.normal(0, np.radians(5), (n, 4))
    normal = _direction(tilt, azimuth)
    jitter = lambda shape: rng.uniform(0.85, 1.15, shape)  # noqa: E731
    sx = pick(rng.uniform(0.04, 0.2, (n, 2))) * jitter((n, 4))
    sy = pick(rng.uniform(0.04, 0.2, (n, 2))) * jitter((n, 4))
    rho_s = pick(rng.uniform(0.2, 1.0, (n, 2, 3))) * jitter((n, 4, 1))
    rho_d = rng.uniform(0.02, 0.3, (n, 4, 3)) * (0.0 if specular_only else 1.0)
    f = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    return BTFTexel.single(f(rho_d), f(rho_s), f(normal), f(sx), f(sy))


def light_view_pairs(seed, n, *, max_theta_deg=60.0, cone_deg=40.0):
    """Half vector uniform in a 40-degree cone, view uniform within 60 degrees, light = mirror of
    the view about h; pairs with the light beyond 60 degrees dropped (as in the test)."""
    u = np.random.default_rng(seed).uniform(size=(n, 4))
    h = _direction(np.arccos(1 - u[:, 0] * (1 - np.cos(np.radians(cone_deg)))), 2 * np.pi * u[:, 1])
    cos_max = np.cos(np.radians(max_theta_deg))
    wo = _direction(np.arccos(1 - u[:, 2] * (1 - cos_max)), 2 * np.pi * u[:, 3])
    wi = 2 * np.sum(wo * h, -1, keepdims=True) * h - wo
    keep = (wi[:, 2] > cos_max) & (wo[:, 2] > cos_max)
    return jnp.asarray(wi[keep], jnp.float32), jnp.asarray(wo[keep], jnp.float32)


def two_direction_level0(seed, size):
    """A 256x256 level 0 where every 2x2 block mixes two random directions (EM runs everywhere)."""
    h, w = size
    n = (h // 2) * (w // 2)
    c = two_direction_children(seed, n)
    # children N 4 -> blocks: (i, j) offsets in gather order (0,0), (1,0), (0,1), (1,1)
    def place(a):
        a = a.reshape((h // 2, w // 2, 2, 2) + a.shape[2:])  # child k = 2 * col_offset + row_offset
        a = jnp.swapaxes(a, 2, 3)                             # ... row_offset, col_offset
        a = jnp.moveaxis(a, 2, 1)                             # h/2, row_offset, w/2, col_offset
        return a.reshape((h, w) + a.shape[4:])
    return jax.tree.map(place, c)


# ---------------------------------------------------------------------------------------------
# (a) errors


@jax.jit
def _render(texels: BTFTexel, wi, wo):
    def one(texel):
        b = jax.tree.map(lambda a: jnp.broadcast_to(a, (wi.shape[0],) + a.shape), texel)
        return reflectance(b, wi, wo)
    return jax.vmap(one)(texels)


def _render_batched(texels: BTFTexel, wi, wo, *, batch=1024):
    n = texels.weight.shape[0]
    out = []
    for s in range(0, n, batch):
        idx = np.minimum(np.arange(s, s + batch), n - 1)
        out.append(np.asarray(_render(jax.tree.map(lambda a: a[idx], texels), wi, wo))[: min(batch, n - s)])
    return np.concatenate(out)


def coarse_methods(children: BTFTexel) -> dict[str, BTFTexel]:
    return {"EM 2-lobe": em_texels(children)[0], "moment 1-lobe": jax.jit(jax.vmap(moment_matched_texel))(children),
            "mip": jax.jit(jax.vmap(mip_texel))(children)}


def errors_two_direction(n_texels, n_pairs, *, specular_only=False):
    children = two_direction_children(1, n_texels, specular_only=specular_only)
    wi, wo = light_view_pairs(2, n_pairs)
    flat = lambda c: jax.tree.map(lambda a: a[:, c], children)  # noqa: E731
    reference = sum(_render_batched(flat(c), wi, wo) for c in range(4)) / 4
    out = {}
    for name, texel in coarse_methods(children).items():
        r = _render_batched(texel, wi, wo)
        out[name] = float(np.linalg.norm(r - reference) / np.linalg.norm(reference))
    return out, int(wi.shape[0])


def _flatten(level: BTFTexel) -> BTFTexel:
    return jax.tree.map(lambda a: a.reshape((-1,) + a.shape[2:]), level)


def _box(r: np.ndarray) -> np.ndarray:
    """Average 2x2 blocks (edge-padded), as jaxrender.textures.downsample2, of an H W ... array."""
    h, w = r.shape[:2]
    r = np.pad(r, ((0, h % 2), (0, w % 2)) + ((0, 0),) * (r.ndim - 2), mode="edge")
    return 0.25 * (r[0::2, 0::2] + r[1::2, 0::2] + r[0::2, 1::2] + r[1::2, 1::2])


def errors_synth_pyramid(size, n_pairs):
    """Per level: relative RMS of each pyramid's rendering vs the box-filtered level-0 rendering."""
    level0 = synth_maps(jax.random.PRNGKey(0), size)
    wi, wo = light_view_pairs(3, n_pairs)
    truth = _render_batched(_flatten(level0), wi, wo).reshape(size + (wi.shape[0], 3))
    em_levels, _ = pyramid_levels(level0)
    pyramids = {"EM 2-lobe": em_levels, "moment 1-lobe": [], "mip": []}
    for name, fn in (("moment 1-lobe", moment_matched_texel), ("mip", mip_texel)):
        current = level0
        step = jax.jit(lambda lv, fn=fn: jax.vmap(jax.vmap(fn))(gather_children(lv)))
        while max(current.weight.shape) > 1:
            current = step(current)
            pyramids[name].append(current)
    rows = []
    box = truth
    for level, _ in enumerate(em_levels, start=1):
        box = _box(box)
        row = {"level": level, "size": box.shape[:2]}
        for name, levels in pyramids.items():
            r = _render_batched(_flatten(levels[level - 1]), wi, wo).reshape(box.shape)
            row[name] = float(np.linalg.norm(r - box) / np.linalg.norm(box))
        row["two-lobe texels"] = float(np.mean(np.asarray(em_levels[level - 1].weight) > 0))
        rows.append(row)
    return rows, level0, pyramids, truth, (wi, wo)


def figure(rows, level0, pyramids, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    # One light/view near a specular peak: view 30 deg, light mirrored through a normal tilted 10 deg.
    wo = np.array([[np.sin(np.radians(30)), 0.0, np.cos(np.radians(30))]], np.float32)
    h = _direction(np.radians(10.0), np.radians(90.0))[None].astype(np.float32)
    wi = 2 * np.sum(wo * h, -1, keepdims=True) * h - wo
    wi, wo = jnp.asarray(wi), jnp.asarray(wo)
    shape = level0.weight.shape
    truth = _render_batched(_flatten(level0), wi, wo).reshape(shape + (3,))
    level = max(1, len(rows) - 3)  # 256x256: level 5 (8x8), where a texel spans warp and weft
    box = truth
    for _ in range(level):
        box = _box(box)
    panels = [("level 0 box-filtered (truth)", box)]
    for name, levels in pyramids.items():
        panels.append((name, _render_batched(_flatten(levels[level - 1]), wi, wo).reshape(box.shape)))
    scale = np.percentile(box, 99.5)
    fig, axes = plt.subplots(1, 5, figsize=(17, 4.3))
    for ax, (title, img) in zip(axes[:4], panels):
        ax.imshow(np.clip(img / scale, 0, 1) ** (1 / 2.2), interpolation="nearest")
        ax.set_title(f"{title}\nlevel {level} ({box.shape[0]}x{box.shape[1]})", fontsize=9)
        ax.axis("off")
    ax = axes[4]
    for name, marker in (("EM 2-lobe", "o"), ("moment 1-lobe", "s"), ("mip", "^")):
        ax.plot([r["level"] for r in rows], [r[name] for r in rows], marker=marker, label=name)
    ax.set_xlabel("pyramid level")
    ax.set_ylabel("relative RMS vs box-filtered level 0")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---------------------------------------------------------------------------------------------
# (b) speed


def _as_dict(t: BTFTexel) -> dict:
    d = {"rho_d": np.asarray(t.rho_d), "weight": np.asarray(t.weight)}
    for k in ("lobe0", "lobe1"):
        lobe = getattr(t, k)
        d[k] = {f: np.asarray(getattr(lobe, f)) for f in ("rho_s", "normal", "sigma_x", "sigma_y")}
    return d


def _render_dict(d: dict, wi, wo) -> np.ndarray:
    from jaxrender.brdf import Lobe

    lobe = lambda k: Lobe(*(jnp.asarray(d[k][f]) for f in ("rho_s", "normal", "sigma_x", "sigma_y")))  # noqa: E731
    texel = BTFTexel(jnp.asarray(d["rho_d"]), lobe("lobe0"), lobe("lobe1"), jnp.asarray(d["weight"]))
    return _render_batched(_flatten(texel) if texel.weight.ndim == 2 else texel, wi, wo)


def _timed(fn, repeats):
    """Median wall and CPU (process) seconds of `repeats` calls."""
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return float(np.median(wall)), float(np.median(cpu))


def speed(level0: BTFTexel, repeats: int, numpy_repeats: int):
    t0 = time.perf_counter()
    levels, _ = pyramid_levels(level0)
    jax.block_until_ready(levels)
    first = time.perf_counter() - t0
    jax_time, jax_cpu = _timed(lambda: jax.block_until_ready(pyramid_levels(level0)[0]), repeats)
    levels, stats = pyramid_levels(level0)
    d0 = _as_dict(level0)
    numpy_time, numpy_cpu = _timed(lambda: pyramid_numpy(d0), numpy_repeats)
    # Equal accuracy: each level from the SAME input (the JAX level above), compared by rendering
    # (lobe order may swap where the two weights tie at 1/2).
    wi, wo = light_view_pairs(4, 256)
    worst = 0.0
    previous = level0
    for lv in levels[:3]:
        ours = _render_dict(_as_dict(lv), wi, wo)
        hh, ww = lv.weight.shape
        theirs_flat = em_texels_numpy(gather_children_numpy(_as_dict(previous)))
        theirs = _render_dict({k: theirs_flat[k] for k in ("rho_d", "lobe0", "lobe1", "weight")}, wi, wo)
        worst = max(worst, float(np.linalg.norm(ours - theirs) / np.linalg.norm(ours)))
        previous = lv
    two = [s["two_lobe_fraction"] for s in stats]
    return {"compile_s": first - jax_time, "jax_s": jax_time, "numpy_s": numpy_time, "speedup": numpy_time / jax_time,
            "jax_cpu": jax_cpu, "numpy_cpu": numpy_cpu,
            "accuracy": worst, "two_lobe_level1": two[0], "max_iterations": max(s["max_iterations"] for s in stats)}


# ---------------------------------------------------------------------------------------------
# (c) scikit-learn


def sklearn_agreement(n_problems, n_samples):
    from sklearn.mixture import GaussianMixture as SkGM

    rows = []
    with jax.enable_x64(True):
        fit = jax.jit(lambda x, w, init: em_fit(x, w, init, iterations=5000, tol=1e-12, var_floor=1e-12))
        for seed in range(n_problems):
            rng = np.random.default_rng(100 + seed)
            means = rng.uniform(-0.5, 0.5, (2, 2))
            std = rng.uniform(0.03, 0.2, (2, 2))
            wt = rng.uniform(0.2, 0.8)
            comp = (rng.uniform(size=n_samples) > wt).astype(int)
            x = means[comp] + std[comp] * rng.normal(size=(n_samples, 2))
            init_means = means + rng.normal(0, 0.1, (2, 2))
            init = GaussianMixture(jnp.array([0.5, 0.5]), jnp.asarray(init_means), jnp.full((2, 2), 0.02))
            gmm, loglik, iters, conv = fit(jnp.asarray(x), jnp.ones(n_samples), init)
            sk = SkGM(2, covariance_type="diag", tol=1e-12, max_iter=5000, reg_covar=1e-12, weights_init=[0.5, 0.5],
                      means_init=init_means, precisions_init=np.full((2, 2), 1 / 0.02), random_state=0)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                sk.fit(x)
            rows.append({"loglik_rel": abs(float(loglik) - sk.score(x)) / abs(sk.score(x)),
                         "param": float(max(np.max(np.abs(np.asarray(gmm.means) - sk.means_)),
                                            np.max(np.abs(np.asarray(gmm.variances) - sk.covariances_)),
                                            np.max(np.abs(np.asarray(gmm.weights) - sk.weights_)))),
                         "iters": int(iters), "sk_iters": int(sk.n_iter_), "converged": bool(conv) and sk.converged_})
    return rows


# ---------------------------------------------------------------------------------------------


def speed_runs(runs: int, size=(256, 256)):
    """(b) on the woven BTF only, `runs` times (each a median of 31 JAX / 7 numpy calls), then the
    time of every level alone (each from the same JAX input level)."""
    level0 = synth_maps(jax.random.PRNGKey(0), size)
    print(f"## Woven {size[0]}x{size[1]} pyramid, {runs} measurements "
          f"(load average at start {os.getloadavg()[0]:.1f})\n")
    print("| run | JAX wall (s) | numpy wall (s) | speed-up (wall) | speed-up (CPU) |\n|---|---|---|---|---|")
    ratios = []
    for run in range(runs):
        s = speed(level0, 31, 7)
        ratios.append(s["speedup"])
        print(f"| {run + 1} | {s['jax_s']:.4f} | {s['numpy_s']:.4f} | {s['speedup']:.1f}x | "
              f"{s['numpy_cpu'] / s['jax_cpu']:.1f}x |", flush=True)
    print(f"\nmedian {np.median(ratios):.1f}x, range {min(ratios):.1f}-{max(ratios):.1f}x\n")
    print("| level | size | JAX (s) | numpy (s) | speed-up |\n|---|---|---|---|---|")
    levels = [level0] + pyramid_levels(level0)[0]
    for i, (fine, coarse) in enumerate(zip(levels[:-1], levels[1:])):
        ours, _ = _timed(lambda: jax.block_until_ready(em_downsample(fine)), 15)
        d = gather_children_numpy(_as_dict(fine))
        theirs, _ = _timed(lambda: em_texels_numpy(d), 5)
        h, w = coarse.weight.shape
        print(f"| {i + 1} | {h}x{w} | {ours:.4f} | {theirs:.4f} | {theirs / ours:.1f}x |")


def profile(size=(256, 256), repeats: int = 31) -> None:
    """Where the time of the woven pyramid goes: every level alone, then level 1's 4096-texel
    chunk kernel, one of its 2048-texel blocks and that block's pieces (the nodes, the lobe
    conversion; the rest is the moments, the ISE of the 1-or-2 rule and the EM initialization),
    each jitted and timed apart (CPU and wall medians), and XLA's cost analysis of the chunk kernel
    against the time. Run it pinned for one core: `--profile --cores 1`."""
    import fitting.em as em

    def timed(fn, n=repeats):
        fn()
        wall, cpu = [], []
        for _ in range(n):
            w0, c0 = time.perf_counter(), time.process_time()
            jax.block_until_ready(fn())
            wall.append(time.perf_counter() - w0)
            cpu.append(time.process_time() - c0)
        return 1e3 * float(np.median(cpu)), 1e3 * float(np.median(wall))

    level0 = synth_maps(jax.random.PRNGKey(0), size)
    print(f"## Profile, woven {size[0]}x{size[1]} (load {os.getloadavg()[0]:.1f}, cores {CORES or 'all'})\n")
    print("| piece | CPU ms (median) | wall ms (median) |\n|---|---|---|")
    row = lambda name, t: print(f"| {name} | {t[0]:.3f} | {t[1]:.3f} |")  # noqa: E731
    row("whole pyramid", timed(lambda: pyramid_levels(level0)[0]))
    levels = [level0] + pyramid_levels(level0)[0]
    for i, (fine, coarse) in enumerate(zip(levels[:-1], levels[1:])):
        row(f"level {i + 1} ({coarse.weight.shape[0]}x{coarse.weight.shape[1]})", timed(lambda: em_downsample(fine)))
    lobes, rho_d = em._split_level(level0, 4096, True)[0]
    row("level 1: split into chunks", timed(lambda: em._split_level(level0, 4096, True)))
    chunk = lambda: em._em_blocks_jit(lobes, rho_d, em.DEFAULT_ORDER, em.DEFAULT_ITERATIONS, None, 2)  # noqa: E731
    row("level 1: one 4096-texel chunk", timed(chunk))
    block = jax.tree.map(lambda a: a[..., :2048], lobes)
    normal, rho_s, sigma_x, sigma_y, child_mass = block
    kernel = jax.jit(lambda b, r: em._texels_kernel(b, r, em.DEFAULT_ORDER, em.DEFAULT_ITERATIONS, None, 2))
    row("one 2048-texel block", timed(lambda: kernel(block, rho_d[:2048])))
    nodes = jax.jit(lambda nrm, sx, sy: em._lobe_nodes(nrm, sx, sy, em.DEFAULT_ORDER))
    row("  nodes (frames, half vectors, slopes)", timed(lambda: nodes(normal, sigma_x, sigma_y)))
    h, _, _, q = nodes(normal, sigma_x, sigma_y)
    mass = 0.25 * child_mass * jnp.pi * sigma_x * sigma_y * sum(rho_s) / 3   # the kernel's lobe energies (sigmas
    e = tuple(0.25 * child_mass * jnp.pi * sigma_x * sigma_y * c for c in rho_s)   # are above the floor here)
    w = q[None, :, None] * mass[:, None, :]
    ones = jnp.ones_like(mass[0])
    convert = jax.jit(lambda h, w, e: em._component_lobes(h, w, e, jnp.ones_like(w[:, 0]), 0 * ones, 0 * ones, ones))
    row("  lobe conversion (4 recentring steps + moments)", timed(lambda: convert(h, w, e)))
    compiled = em._em_blocks_jit.lower(lobes, rho_d, em.DEFAULT_ORDER, em.DEFAULT_ITERATIONS, None, 2).compile()
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, list) else cost
    hlo = compiled.as_text()
    best = timed(chunk, 15)[0]
    print(f"\nchunk kernel: {cost['flops'] / 1e6:.1f} MFLOP, {cost.get('transcendentals', 0) / 1e6:.2f} M "
          f"transcendentals, {cost['bytes accessed'] / 1e6:.0f} MB buffer traffic, {hlo.count(' fusion(')} fusions, "
          f"{hlo.count(' while(')} while loops; at the median CPU time {best:.2f} ms: "
          f"{cost['flops'] / best / 1e6:.1f} GFLOP/s, {cost['bytes accessed'] / best / 1e6:.0f} GB/s")


def equal_cores_speed(size, repeats: int) -> dict:
    """(d) in this process's core setting (`--cores`): the woven pyramid, JAX vs the numpy peer
    (one process at 1 core, a 2-process pool at 2 cores), interleaved."""
    import multiprocessing

    from _compare import compare, load

    level0 = synth_maps(jax.random.PRNGKey(0), size)
    d0 = _as_dict(level0)
    if CORES == 2:  # two worker processes of one BLAS / OpenMP thread each (they inherit this environment)
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
            os.environ[var] = "1"
    pool = multiprocessing.get_context("spawn").Pool(2) if CORES == 2 else None
    try:
        worker_cpu = []  # the pool workers' CPU seconds per call, added to the parent's below
        peer = (lambda: pyramid_numpy_pool(d0, pool, 2, worker_cpu=worker_cpu)) if pool else (lambda: pyramid_numpy(d0))
        if pool:  # the pool's peer computes what the one-process peer does
            a, b = pyramid_numpy(d0), peer()
            assert all(np.allclose(x["rho_d"], y["rho_d"]) and np.array_equal(x["weight"] > 0, y["weight"] > 0)
                       for x, y in zip(a, b))
        load0 = load()
        worker_cpu.clear()
        stats = compare({"jax": lambda: pyramid_levels(level0)[0], "numpy": peer}, repeats)
        if pool:  # worker_cpu[0] is compare's first (warm-up) call
            stats["numpy"].cpu = [c + w for c, w in zip(stats["numpy"].cpu, worker_cpu[1:])]
    finally:
        if pool:
            pool.close()
    return {"cores": CORES, "size": list(size), "load": [load0, load()], "peer": "numpy, 2 processes" if pool
            else "numpy, 1 process", **{k: {"wall": s.wall, "cpu": s.cpu, "compile_s": s.compile_s}
                                         for k, s in stats.items()}}


def equal_cores_report(records: list[dict]) -> dict:
    """Print (d)'s table; its result row."""
    mmm = lambda xs: f"{min(xs):.3f} / {np.median(xs):.3f} / {max(xs):.3f}"  # noqa: E731
    print("\n## (d) Equal cores: whole woven pyramid, interleaved runs\n")
    print("| cores | peer | JAX wall s (min / med / max) | peer wall s | ratio wall (median; worst-best) | "
          "JAX CPU s | peer CPU s | ratio CPU (median) | load |")
    print("|---|---|---|---|---|---|---|---|---|")
    parts = []
    ok = True
    for r in records:
        jw, pw, jc, pc = r["jax"]["wall"], r["numpy"]["wall"], r["jax"]["cpu"], r["numpy"]["cpu"]
        med = np.median(pw) / np.median(jw)
        worst, best = min(pw) / max(jw), max(pw) / min(jw)
        cpu = np.median(pc) / np.median(jc)
        print(f"| {r['cores']} | {r['peer']} | {mmm(jw)} | {mmm(pw)} | {med:.1f}x ({worst:.1f}-{best:.1f}x) | "
              f"{mmm(jc)} | {mmm(pc)} | {cpu:.1f}x | {r['load'][0]:.1f}-{r['load'][1]:.1f} |")
        parts.append(f"{r['cores']} core{'s' if r['cores'] > 1 else ''} ({r['peer']}): {med:.1f}x wall "
                     f"({worst:.1f}-{best:.1f}), {cpu:.1f}x CPU (JAX {np.median(jc) * 1e3:.1f} ms, "
                     f"numpy {np.median(pc) * 1e3:.0f} ms CPU)")
        ok = ok and med >= 10 and cpu >= 10  # met only if the CPU time (robust to the load) agrees
    return dict(
        area="fitting", target=">= 10x batched numpy over a 256x256 pyramid",
        measured=f"woven {records[0]['size'][0]}^2: " + "; ".join(parts), status="met" if ok else "missed",
        notes="met only if wall median and CPU ratio both reach 10x; 1 core: both pinned to core 0, one thread "
              "each; 2 cores: JAX's pools vs numpy in 2 one-thread processes; where the time goes: RESULTS.md, "
              "EM section (d), `--profile --cores 1`")


def error_row(two_direction: dict, n_texels: int, woven: list[dict], figure: Path) -> dict:
    """(a)'s result row: on the coarse texels whose children have two directions, the 2-lobe EM level's
    rendering error must be <= 1/3 of the ordinary mip's and below the moment-matched level's, for the
    full R and for its specular part alone."""
    ok = all(e["EM 2-lobe"] <= e["mip"] / 3 and e["EM 2-lobe"] < e["moment 1-lobe"] for e in two_direction.values())
    parts = [f"{label.split(' (')[0]}: EM {e['EM 2-lobe']:.3f}, {e['EM 2-lobe'] / e['mip']:.3f}x mip, "
             f"{e['EM 2-lobe'] / e['moment 1-lobe']:.3f}x moment" for label, e in two_direction.items()]
    worse = [r["level"] for r in woven if r["EM 2-lobe"] > r["moment 1-lobe"] * (1 + 1e-3)]
    versus = f"above moment-matched at levels {worse}" if worse else "at or below moment-matched at every level"
    top = woven[-1]
    return dict(area="fitting", target="2-lobe error <= 1/3 of the ordinary mip, < moment-matched",
                measured="; ".join(parts) + f" (relative RMS of R, {n_texels} coarse texels with two directions)",
                status="met" if ok else "missed",
                notes=f"woven {woven[0]['size'][0] * 2}^2 pyramid vs box-filtered level 0: EM "
                      + versus
                      + f"; at {top['size'][0]}x{top['size'][1]} EM {top['EM 2-lobe']:.3f}, moment "
                        f"{top['moment 1-lobe']:.3f}, mip {top['mip']:.3f}; figure {figure}",
                figures={"two_direction": two_direction, "woven": [{k: v for k, v in r.items() if k != "size"}
                                                                   for r in woven]})


def sklearn_row(rows: list[dict], n_problems: int, n_samples: int) -> dict:
    """(c)'s result row: our EM's final log-likelihood equal to scikit-learn's (float64, tol 1e-12)
    within 1e-9 relative on every problem, both converged."""
    worst, param = max(r["loglik_rel"] for r in rows), max(r["param"] for r in rows)
    ok = worst <= 1e-9 and all(r["converged"] for r in rows)
    return dict(area="fitting", target="log-likelihood equal to scikit-learn GaussianMixture",
                measured=f"max relative difference {worst:.1e} over {n_problems} problems of {n_samples} samples "
                         f"(max parameter difference {param:.1e}); "
                         + ("all converged" if all(r["converged"] for r in rows) else "not all converged"),
                status="met" if ok else "missed",
                notes="GaussianMixture(2, 'diag'), same initialization, float64, tol 1e-12; met within 1e-9 relative",
                figures={"loglik_rel_max": worst, "param_max": param})


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes: a smoke run (compile dominates)")
    parser.add_argument("--speed-runs", type=int, default=0, metavar="N",
                        help="only the woven pyramid's speed, N measurements, and the time per level")
    parser.add_argument("--equal-cores", action="store_true", help="only (d), both core settings")
    parser.add_argument("--cores", type=int, default=None, help="(d) in one core setting only (child run)")
    parser.add_argument("--emit", type=Path, default=None, help="(d) child: write the raw record here")
    parser.add_argument("--profile", action="store_true", help="only the time per level and per kernel piece")
    args = parser.parse_args(argv)
    if args.profile:
        profile(*(((64, 64), 3) if args.quick else ()))
        return
    eq_size, eq_repeats = ((32, 32), 1) if args.quick else ((256, 256), 7)
    if args.cores is not None:
        rec = equal_cores_speed(eq_size, eq_repeats)
        if args.emit:
            args.emit.write_text(json.dumps(rec))
        return
    results = []  # the result rows
    if args.equal_cores or not args.quick:
        records = []
        for cores in (1, 2):
            with tempfile.TemporaryDirectory() as tmp:
                path = Path(tmp) / "rec.json"
                subprocess.run([sys.executable, __file__, "--cores", str(cores), "--emit", str(path)]
                               + (["--quick"] if args.quick else []), check=True)
                records.append(json.loads(path.read_text()))
        results.append(equal_cores_report(records))
        if args.equal_cores:  # this row alone: the accuracy rows of the last full run stay
            write_results("em_pyramid", results, quick=args.quick, update=True)
            return
    if args.speed_runs:
        speed_runs(args.speed_runs)
        write_results("em_pyramid", results, quick=args.quick, update=True)  # (d)'s row, the others stay
        return
    quick = args.quick
    n_texels, n_pairs = (64, 500) if quick else (4096, 8000)
    size = (16, 16) if quick else (256, 256)
    load = os.getloadavg()[0]
    print(f"# EM multi-resolution BTF benchmark ({cpu_description()}, {jax.devices()[0].platform}, "
          f"jax {jax.__version__}, {'quick' if quick else 'full'})\n")

    repeats, np_repeats = (2, 1) if quick else (31, 7)
    synth0 = synth_maps(jax.random.PRNGKey(0), size)
    speed_rows = [(label, speed(lv0, repeats, np_repeats)) for label, lv0 in
                  (("synth_maps (woven)", synth0),
                   ("two directions in every 2x2 block", two_direction_level0(5, size)))]

    print(f"## (a) Rendering error, {n_texels} coarse texels with two distinct directions\n")
    print("| R compared | pairs | EM 2-lobe | moment 1-lobe | mip | EM / mip | EM / moment |")
    print("|---|---|---|---|---|---|---|")
    two_direction = {}
    for label, spec in (("full R (rho_d + specular)", False), ("specular only (rho_d = 0)", True)):
        err, pairs = errors_two_direction(n_texels, n_pairs, specular_only=spec)
        em, mo, mip = err["EM 2-lobe"], err["moment 1-lobe"], err["mip"]
        two_direction[label] = err
        print(f"| {label} | {pairs} | {em:.2e} | {mo:.2e} | {mip:.2e} | {em / mip:.3f} | {em / mo:.3f} |")

    n_pairs_synth = 16 if quick else 256
    rows, level0, pyramids, _, _ = errors_synth_pyramid(size, n_pairs_synth)
    print(f"\nSynthetic woven BTF {size[0]}x{size[1]} (fitting.synth_maps), every level vs the box-filtered "
          f"level-0 rendering, {n_pairs_synth} pairs drawn as above:\n")
    print("| level | size | EM 2-lobe | moment 1-lobe | mip | two-lobe texels |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['level']} | {r['size'][0]}x{r['size'][1]} | {r['EM 2-lobe']:.4f} | {r['moment 1-lobe']:.4f} | "
              f"{r['mip']:.4f} | {100 * r['two-lobe texels']:.0f} % |")
    fig_path = FIGURES / ("em_pyramid_quick.png" if quick else "em_pyramid.png")  # the committed figure is the full one
    figure(rows, level0, pyramids, fig_path)
    results.append(error_row(two_direction, n_texels, rows, fig_path.relative_to(Path(__file__).parent.parent)))
    print(f"\nfigure: {fig_path.relative_to(Path(__file__).parent.parent)}")

    print(f"\n## (b) Speed: whole {size[0]}x{size[1]} pyramid ({len(pyramid_sizes(size)) - 1} levels), float32, "
          f"median of {repeats} (JAX) / {np_repeats} (numpy) runs; load average at start {load:.1f}\n")
    print("| level 0 | JAX compile (s) | JAX wall (s) | numpy wall (s) | speed-up (wall) | JAX CPU (s) | numpy CPU (s) "
          "| speed-up (CPU) | rel. diff of renders | two-lobe texels, level 1 | max EM iterations |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for label, s in speed_rows:
        compile_s = f"{s['compile_s']:.1f}" if s["compile_s"] > 0.5 else "(compiled above)"
        print(f"| {label} | {compile_s} | {s['jax_s']:.3f} | {s['numpy_s']:.3f} | {s['speedup']:.1f}x | "
              f"{s['jax_cpu']:.3f} | {s['numpy_cpu']:.3f} | {s['numpy_cpu'] / s['jax_cpu']:.1f}x | "
              f"{s['accuracy']:.1e} | {100 * s['two_lobe_level1']:.0f} % | {s['max_iterations']} |")

    n_problems, n_samples = (2, 200) if quick else (20, 2000)
    rows = sklearn_agreement(n_problems, n_samples)
    results.append(sklearn_row(rows, n_problems, n_samples))
    write_results("em_pyramid", results, quick=quick)
    print(f"\n## (c) scikit-learn GaussianMixture(2, 'diag'), same init, {n_problems} problems x {n_samples} "
          "samples, float64\n")
    print("| max rel. log-likelihood diff | max param diff | our iterations (median) | sklearn iterations (median) "
          "| all converged |")
    print("|---|---|---|---|---|")
    print(f"| {max(r['loglik_rel'] for r in rows):.1e} | {max(r['param'] for r in rows):.1e} | "
          f"{int(np.median([r['iters'] for r in rows]))} | {int(np.median([r['sk_iters'] for r in rows]))} | "
          f"{all(r['converged'] for r in rows)} |")


if __name__ == "__main__":
    main()

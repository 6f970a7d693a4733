"""Light shafts: our sample-plane renderer against Mitsuba 3 (`llvm_ad_rgb`, volpath max_depth 2) on the
same scene (a sphere under one spot light in fog, a floor; 720 x 480), at equal error.

Mitsuba's LLVM backend needs an LLVM newer than Debian 12's 14/15 on AVX-512 CPUs
(`sh benchmarks/system_packages.sh`, which README's test command runs, installs libllvm19; the
script finds it). Every Mitsuba render runs in a child process (`_peers.ChildPeer`): if
`llvm_ad_rgb` cannot render, `scalar_rgb` is used, and if Mitsuba dies the peer is reported as
unavailable with the reason while our own figures still count.

    python benchmarks/shafts_vs_mitsuba.py [--quick]

1. Agreement: Mitsuba converged (many samples, low resolution: the camera scaled down 6x, 120 x 80) against
   our ray march and sample planes (float, 30 x 6) rendered at 6x6 samples per Mitsuba pixel and
   box-averaged (Mitsuba's box filter averages a pixel's area); 4x4 block means must agree
   within 5 standard errors of Mitsuba's block means (estimated from independent seeds) plus 4 %.
2. Speed at equal error, each against its own converged result, relative RMS over all pixels and
   channels (design.md):
   - ours: the error of a few plane/sub-plane settings against a 1000-sample ray march (the exact
     integral), and their frame times; ours = the fastest setting with error <= 2 %;
   - Mitsuba: it is unbiased, so its error against its own converged image is its noise; measured
     at several sample counts from two renders with different seeds, e(N) = ||a - b|| / sqrt(2) /
     ||(a + b)/2||, timed; fitted e = c / sqrt(t) (slope checked), so the time to 2 % is (c / 0.02)^2.
"""

from __future__ import annotations

import argparse
import functools
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _shafts_common as C  # noqa: E402
from _peers import ChildPeer, PeerUnavailable, mitsuba_variant  # noqa: E402

TARGET = 0.02


def mitsuba_render(scene: dict, spp: int, seed: int, variant: str):
    import mitsuba as mi
    import numpy as np
    from mitsuba_scene import mitsuba_scene_dict

    mi.set_variant(variant)
    m = mi.load_dict(mitsuba_scene_dict(scene, spp=spp))
    t0 = time.perf_counter()
    img = mi.render(m, spp=spp, seed=seed)
    out = np.array(img, dtype=np.float64)[..., :3]  # forces evaluation (llvm is lazy)
    return out, time.perf_counter() - t0


def rel_rms(x, ref) -> float:
    import numpy as np

    return float(np.linalg.norm(np.asarray(x) - ref) / np.linalg.norm(ref))


def agreement(peer: ChildPeer, variant: str, w: int, h: int, quick: bool, exact, planes_img) -> list[list[str]]:
    """Rows of the converged-image check: ours (ray march, planes) box-averaged vs Mitsuba's block means."""
    import numpy as np
    from mitsuba_scene import block_means

    down = 8 if quick else 6  # Mitsuba's check image: 12 x 8 (quick) or 120 x 80
    wl, hl = w // down, h // down
    check_spp, check_seeds = (128, 2) if quick else (2048, 4)
    reps = np.stack([peer.call(mitsuba_render, C.sphere_scene(wl, hl), check_spp, 100 + k, variant)[0]
                     for k in range(check_seeds)])
    mi_mean = reps.mean(axis=0)
    mi_var = reps.var(axis=0, ddof=1) / check_seeds
    b = 4
    se = np.sqrt(mi_var.reshape(hl // b, b, wl // b, b, 3).sum(axis=(1, 3))) / (b * b)
    rows = []
    for name, img in [("ray march", exact), ("planes 30 x 6 float", planes_img)]:
        ours = np.asarray(img, dtype=np.float64).reshape(hl, down, wl, down, 3).mean(axis=(1, 3))
        d = np.abs(block_means(ours, b) - block_means(mi_mean, b))
        ref_blocks = np.abs(block_means(mi_mean, b))
        tol = 5.0 * se + 0.04 * ref_blocks + 1e-4
        lit = ref_blocks > 1e-3 * ref_blocks.max()  # z-scores where Mitsuba has signal (noise-free black excluded)
        z = float((d[lit] / np.maximum(se[lit], 1e-12)).max())
        rows.append([name, f"{wl} x {hl}", f"{check_seeds} x {check_spp}", f"{z:.1f}", f"{(d / tol).max():.2f}",
                     "yes" if (d <= tol).all() else "NO", f"{ours.mean() / mi_mean.mean():.4f}"])
    return rows


def ours_at_2_percent(scene_full, exact, quick: bool):
    """(table rows, best (name, seconds, error) or None): plane settings timed, error vs the exact ray march."""
    import equinox as eqx
    import numpy as np

    from jaxrender.shafts import render_planes

    settings = [(10, 2)] if quick else [(10, 2), (20, 3), (30, 6)]
    rows, best = [], None
    for n, m in settings:
        fn = eqx.filter_jit(functools.partial(render_planes, planes=n, subplanes=m))
        img, comp, t = C.timed(fn, scene_full, repeats=3)
        err = rel_rms(img, np.asarray(exact))
        rows.append([f"planes {n} x {m}, float", f"{100 * err:.2f} %", f"{comp:.1f}", f"{t:.3f}"])
        if err <= TARGET and (best is None or t < best[1]):
            best = (f"planes {n} x {m}", t, err)
    return rows, best


def mitsuba_noise_law(peer: ChildPeer, variant: str, scene_dict: dict, spps: list[int]) -> dict:
    """Mitsuba's error against its own converged image (two seeds) and time at each sample count, and
    the fitted law error = c / sqrt(t) extrapolated to 2 %."""
    import numpy as np

    peer.call(mitsuba_render, scene_dict, 1, 0, variant)  # warm-up: the LLVM backend compiles its kernels once
    rows, errs, secs = [], [], []
    for spp in spps:
        a, ta = peer.call(mitsuba_render, scene_dict, spp, 1, variant)
        bb, tb = peer.call(mitsuba_render, scene_dict, spp, 2, variant)
        e = float(np.linalg.norm(a - bb) / np.sqrt(2.0) / np.linalg.norm(0.5 * (a + bb)))
        errs.append(e)
        secs.append(0.5 * (ta + tb))
        rows.append([spp, f"{secs[-1]:.2f}", f"{100 * e:.1f} %"])
        print(f"  Mitsuba {spp} spp: {secs[-1]:.2f} s, error {100 * e:.1f} %", flush=True)
    slope = float(np.polyfit(np.log(secs), np.log(errs), 1)[0])
    c = float(np.exp(np.mean(np.log(errs) + 0.5 * np.log(secs))))
    # cross-check: error = c_s / sqrt(spp) and time = t0 + k spp (separates the per-render overhead)
    c_s = float(np.exp(np.mean(np.log(errs) + 0.5 * np.log(spps))))
    k, t0 = np.polyfit(spps, secs, 1)
    spp_target = (c_s / TARGET) ** 2
    return dict(rows=rows, errs=errs, secs=secs, slope=slope, c=c, t_target=(c / TARGET) ** 2,
                spp_target=spp_target, t_target_spp_fit=float(max(t0, 0.0) + k * spp_target), c_s=c_s, k=k, t0=t0,
                each=[t * (e / TARGET) ** 2 for t, e in zip(secs, errs)])


def plot(law: dict, ours_best, variant: str, w: int, h: int, quick: bool):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    fig, ax = plt.subplots(figsize=(6.4, 4))
    secs, errs, c = law["secs"], law["errs"], law["c"]
    ax.loglog(secs, errs, "o", label=f"Mitsuba 3 {variant}")
    tt = np.logspace(np.log10(min(secs) / 3), np.log10(max(law["t_target"], max(secs)) * 1.5), 50)
    ax.loglog(tt, c / np.sqrt(tt), "--", label="fit c / sqrt(t)")
    if ours_best is not None:
        ax.loglog([ours_best[1]], [ours_best[2]], "s", color="C3", label=f"ours ({ours_best[0]})")
    ax.axhline(TARGET, color="gray", lw=0.8)
    ax.set_xlabel("seconds per image")
    ax.set_ylabel("relative RMS error vs own converged image")
    ax.legend()
    ax.set_title(f"Light shafts, {w} x {h}: time to equal error")
    return C.save_figure(fig, "shafts_vs_mitsuba.png", quick=quick)


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="96 x 64, fewer samples and settings (smoke run)")
    parser.add_argument("--spps", default=None, help="Mitsuba sample counts for the noise law (default 4,16,64,256)")
    args = parser.parse_args(argv)

    variant, note = mitsuba_variant()
    C.mitsuba_path()
    import equinox as eqx

    from jaxrender.shafts import render_planes, render_raymarch

    w, h = (96, 64) if args.quick else (C.PAPER_W, C.PAPER_H)
    print(f"# light shafts vs Mitsuba 3, {w} x {h}; {note}; {C.machine()}")
    scene_full = C.load(C.sphere_scene(w, h))
    march_ref = eqx.filter_jit(functools.partial(render_raymarch, samples=200 if args.quick else 1000))
    exact = C.timed(march_ref, scene_full, repeats=0)[0]
    planes_img = C.timed(eqx.filter_jit(functools.partial(render_planes, planes=30, subplanes=6)), scene_full,
                         repeats=0)[0]
    ours_rows, ours_best = ours_at_2_percent(scene_full, exact, args.quick)
    print(C.table(["ours", "rel. RMS error vs exact (1000-sample ray march)", "compile + 1st run s",
                   "median frame s"], ours_rows))

    spps = [int(x) for x in args.spps.split(",")] if args.spps else ([1, 4, 16] if args.quick else [4, 16, 64, 256])
    law, unavailable = None, note if variant is None else None
    if variant is not None:
        with ChildPeer(f"Mitsuba {variant}") as peer:
            try:
                print(C.table(["ours", "resolution", "Mitsuba seeds x spp", "max |diff| / SE (lit blocks)",
                               "max |diff| / tolerance", "agree", "image mean ours / Mitsuba"],
                              agreement(peer, variant, w, h, args.quick, exact, planes_img)))
                law = mitsuba_noise_law(peer, variant, C.sphere_scene(w, h), spps)
            except PeerUnavailable as error:
                unavailable = f"peer unavailable: {error.reason}"
    from _results import write_results

    if law is None:
        print(f"Mitsuba: {unavailable}; ours: {ours_best}")
        write_results("shafts_vs_mitsuba", [dict(
            area="shafts", target=">= 1000x Mitsuba 3 (llvm_ad_rgb) at 2 % error",
            measured=f"not measured: {unavailable}; ours {ours_best}", status="not measured (peer unavailable)")],
            quick=args.quick)
        return {"ratio": float("nan"), "unavailable": unavailable, "ours": ours_best}

    print(C.table(["Mitsuba spp", "render s", "rel. RMS error vs own converged"], law["rows"]))
    t_mi = law["t_target"]
    print(f"fit: error = {law['c']:.3f} / sqrt(t)  (free log-log slope {law['slope']:.3f}; -0.5 expected) -> "
          f"{100 * TARGET:.0f} % at {t_mi:.0f} s")
    print(f"cross-check: error = {law['c_s']:.3f} / sqrt(spp), time = {law['t0']:.3f} s + {law['k']:.4f} s x spp -> "
          f"{100 * TARGET:.0f} % at {law['spp_target']:.0f} spp, {law['t_target_spp_fit']:.0f} s")
    each = law["each"]
    print("time to 2 % extrapolated from each sample count alone: "
          + ", ".join(f"{spp} spp -> {t:.0f} s" for spp, t in zip(spps, each)))
    if ours_best is None:
        summary, ratio = [["ours", "no setting reached 2 %", "-", "-"]], float("nan")
    else:
        ratio = t_mi / ours_best[1]
        summary = [[f"ours: {ours_best[0]}", f"{100 * ours_best[2]:.2f} %", f"{ours_best[1]:.3f}", "1x"],
                   [f"Mitsuba 3 {variant} volpath", f"{100 * TARGET:.0f} % (fit)", f"{t_mi:.0f}",
                    f"{ratio:.0f}x slower"]]
    print(C.table(["renderer", "rel. RMS error", "seconds", "vs ours"], summary))
    print(f"ours is {ratio:.0f}x faster at <= {100 * TARGET:.0f} % error (target >= 1000x)")
    if ours_best is not None:
        errs, secs = law["errs"], law["secs"]
        measured = (f"{ratio:.0f}x (extrapolated): Mitsuba measured {spps[0]}-{spps[-1]} spp, "
                    f"{100 * errs[0]:.1f}-{100 * errs[-1]:.1f} % in {secs[0]:.1f}-{secs[-1]:.0f} s; fitted error = "
                    f"{law['c']:.3f} / sqrt(t) (free slope {law['slope']:.3f}) -> 2 % at {t_mi:.0f} s; from each "
                    f"count alone {min(each):.0f}-{max(each):.0f} s "
                    f"({min(each) / ours_best[1]:.0f}-{max(each) / ours_best[1]:.0f}x); "
                    f"ours {ours_best[0]} at {100 * ours_best[2]:.2f} % in {ours_best[1]:.3f} s; {note}")
        write_results("shafts_vs_mitsuba", [dict(
            area="shafts", target=">= 1000x Mitsuba 3 (llvm_ad_rgb) at 2 % error", measured=measured,
            status=("met" if ratio >= 1000 else "missed") + " (Mitsuba's 2 % extrapolated from its measured noise law)",
            notes="Mitsuba uses both cores (LLVM backend), ours XLA's default pools: equal cores")], quick=args.quick)
    path = plot(law, ours_best, variant, w, h, args.quick)
    print(f"figure: {path.relative_to(C.REPO)}")
    return {"ratio": ratio, "t_mitsuba": t_mi, "t_mitsuba_spp_fit": law["t_target_spp_fit"], "ours": ours_best,
            "slope": law["slope"]}


if __name__ == "__main__":
    main()

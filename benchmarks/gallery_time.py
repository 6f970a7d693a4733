"""The main job's time: `jaxrender gallery --out DIR` as a user runs it, each run a fresh process on
the same machine: from an empty compile cache (compilation included) with the sections one after
the other (`--jobs 1`, the peer), then as it runs by default (sections side by side, one process
per core), from an empty compile cache and once more loading the programs that run compiled (the
commands' compile cache, README "Compile time"). Wall and CPU time of each, the load before and
after; the compile cache's one-off check of the machine is made before, untimed. The images of the
runs are compared file by file.

    python benchmarks/gallery_time.py            # the whole gallery, three times (about 20 min on 2 cores)
    python benchmarks/gallery_time.py --quick    # `--quick --only fit,desert`: a smoke run
"""

from __future__ import annotations

import argparse
import filecmp
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
from _commands import run_command
from _results import cpu_description, write_results

from jaxrender.app.cli.compile_cache import CACHE_ENV
from jaxrender.app.cli.compile_cache import usable as compile_cache_usable
from jaxrender.io import read_exr

TARGET_S = 300.0   # the gallery on 2 cores in <= 5 minutes, quiet
JAXRENDER = [sys.executable, "-m", "jaxrender.app.cli.programs", "jaxrender"]


def run_gallery(out: Path, cache: Path, extra: list[str]) -> dict:
    """One `jaxrender gallery` in a fresh process with its compile cache in `cache` (JAX's own
    $JAX_COMPILATION_CACHE_DIR, set when the test suite runs this, wins over it)."""
    return run_command([*JAXRENDER, "gallery", "--out", str(out), *extra], env={**os.environ, CACHE_ENV: str(cache)})


def differing(first: Path, second: Path) -> tuple[list[str], list[str], float]:
    """How the image files of `first` differ from `second`'s: (PNGs that differ or are missing,
    EXRs that do, the largest relative difference of an EXR value)."""
    pngs, exrs, largest = [], [], 0.0
    for path in sorted(p for p in first.rglob("*") if p.suffix in (".png", ".exr")):
        other = second / path.relative_to(first)
        if other.is_file() and filecmp.cmp(path, other, shallow=False):
            continue
        name = str(path.relative_to(first))
        if path.suffix == ".png" or not other.is_file():
            pngs.append(name)
            continue
        exrs.append(name)
        a, b = read_exr(path), read_exr(other)
        for channel in a:
            x, y = np.asarray(a[channel], np.float64), np.asarray(b[channel], np.float64)
            largest = max(largest, float(np.max(np.abs(x - y) / np.maximum(np.abs(x), 1e-6))))
    return pngs, exrs, largest


def compared(*pairs: tuple[Path, Path]) -> str:
    """The images of the pairs of runs compared, in words."""
    pngs, exrs, largest = set(), set(), 0.0
    for first, second in pairs:
        p, e, r = differing(first, second)
        pngs, exrs, largest = pngs | set(p), exrs | set(e), max(largest, r)
    text = f"PNGs differing: {', '.join(sorted(pngs)) or 'none'} (the fit figure's title prints its time)"
    if exrs:
        text += (f"; {len(exrs)} EXRs differing by rounding (largest relative difference {largest:.1e}: XLA's "
                 "CPU backend splits some sums by the number of threads, which a section's share of the cores "
                 "changes; the Noh robe's simulation carries such a difference on from frame to frame)")
    return text


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="`--quick --only fit,desert`: a smoke run")
    args = parser.parse_args()
    extra = ["--quick", "--only", "fit,desert"] if args.quick else []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        # the compile cache's check of the machine, made before and untimed in both caches
        cache_ok = all([compile_cache_usable(work / "cache_one_by_one"), compile_cache_usable(work / "cache_default")])
        one_by_one = run_gallery(work / "one_by_one", work / "cache_one_by_one", [*extra, "--jobs", "1"])
        first, second = (run_gallery(work / f"default{i}", work / "cache_default", extra) for i in (1, 2))
        changed = compared((work / "one_by_one", work / "default1"), (work / "default1", work / "default2"))
    ratio = one_by_one["wall_s"] / first["wall_s"]
    print(f"{cpu_description()}: one section at a time {one_by_one['wall_s']:.1f} s wall ({one_by_one['cpu_s']:.1f} s "
          f"CPU); side by side {first['wall_s']:.1f} s ({first['cpu_s']:.1f} s CPU), {ratio:.2f}x; run again "
          f"{second['wall_s']:.1f} s ({second['cpu_s']:.1f} s CPU); compile cache usable: {cache_ok}; "
          f"{changed}")
    second_text = (f"run again, its programs loaded from the compile cache: {second['wall_s']:.0f} s wall "
                   f"({second['cpu_s']:.0f} s CPU)" if cache_ok else
                   "the compile cache is not usable on this machine (jax-ml/jax#38445): no second-run figure")
    row = dict(area="tools", target="`jaxrender gallery --out DIR` <= 5 min on 2 cores, quiet",
               measured=(f"{first['wall_s']:.0f} s wall ({first['cpu_s']:.0f} s CPU, load {first['load']:.1f}) from "
                         f"an empty compile cache, compilation included, the sections side by side (the default: "
                         f"{os.cpu_count()} at once); one after the other (`--jobs 1`), same run: "
                         f"{one_by_one['wall_s']:.0f} s wall ({one_by_one['cpu_s']:.0f} s CPU), {ratio:.2f}x the "
                         f"time; {second_text}; images of the runs compared: {changed}"),
               status="met" if first["wall_s"] <= TARGET_S else "missed (compilation included)",
               figures={"first_wall_s": first["wall_s"], "second_wall_s": second["wall_s"],
                        "first_cpu_s": first["cpu_s"], "second_cpu_s": second["cpu_s"],
                        "one_by_one_wall_s": one_by_one["wall_s"], "one_by_one_cpu_s": one_by_one["cpu_s"]})
    write_results("gallery_time", [row], quick=args.quick)


if __name__ == "__main__":
    main()

"""Generated documents through the installed command lines, as users run them (float32, a process
each): scene files, BVH motions, capture directories and DiLiGenT-format folders drawn from each
format's description (tests/format_documents.py). A valid document must give exit code 0 and a
finite output; a broken one exit code 2, one `COMMAND: error: ...` line per problem naming the
file, and nothing written. Real motion captures with their rotation channels relabelled (another
order, the same numbers: a pose no one captured) must render or be refused in one line, never crash.
Every outcome else is a finding, printed and counted in the result row.

    python benchmarks/format_fuzz.py            # the full budget (about half an hour on 2 cores)
    python benchmarks/format_fuzz.py --quick    # a few documents of each kind
    python benchmarks/format_fuzz.py --seed 7   # another draw
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))   # the strategies live beside the tests that use them

from _results import write_results  # noqa: E402
from format_documents import (  # noqa: E402
    broken_bvh_documents,
    broken_capture_documents,
    broken_diligent_documents,
    broken_scene_documents,
    bvh_documents,
    capture_documents,
    diligent_documents,
    scene_documents,
)
from hypothesis import HealthCheck, given, seed, settings  # noqa: E402

SCRIPTS = Path(sys.executable).parent
MOCAP = Path(os.environ.get("JAXRENDER_MOCAP", ROOT.parent / "shared" / "data" / "mocap"))
TIMEOUT_S = 900   # a hung command is a finding, not a hang of the benchmark


def run(tool: str, *args) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    try:
        return subprocess.run([str(SCRIPTS / tool), *map(str, args)], capture_output=True, text=True, env=env,
                              timeout=TIMEOUT_S)
    except subprocess.TimeoutExpired:
        return subprocess.CompletedProcess(args, -1, "", f"timed out after {TIMEOUT_S} s")


class Tally:
    def __init__(self):
        self.counts: dict[str, int] = {}
        self.findings: list[str] = []

    def check(self, kind: str, ok: bool, what: str) -> None:
        self.counts[kind] = self.counts.get(kind, 0) + 1
        if not ok:
            self.findings.append(f"{kind}: {what}")
            print(f"FINDING {kind}: {what}", flush=True)


def refusal_ok(proc, command: str, named: Path, written: Path) -> tuple[bool, str]:
    lines = proc.stderr.strip().splitlines()
    errors = [line for line in lines if not line.startswith(f"{command}: warning: ")]
    ok = (proc.returncode == 2 and bool(errors) and all(line.startswith(f"{command}: error: ") for line in errors)
          and any(str(named) in line for line in errors) and not written.exists())
    return ok, f"exit {proc.returncode}, {len(lines)} lines: {proc.stderr.strip()[-300:]!r}"


def finite_exr(path: Path) -> bool:
    from jaxrender.io import read_exr

    return path.is_file() and all(np.all(np.isfinite(c)) for c in read_exr(path).values())


def explore(strategy, n: int, draw_seed: int, body) -> None:
    """Run `body(document, folder)` on `n` documents of `strategy` (hypothesis draws them; a finding is
    recorded by `body`, never raised, so the run goes on)."""
    @seed(draw_seed)
    @settings(max_examples=n, deadline=None, database=None, suppress_health_check=list(HealthCheck))
    @given(strategy)
    def each(document):
        with tempfile.TemporaryDirectory() as name:
            body(document, Path(name))

    each()


def relabelled_motions(tally: Tally, n: int, seed: int) -> None:
    """Real clips with their rotation channels renamed to another order (and BOM / CRLF / units):
    `jaxrender noh` renders them or refuses them in one line."""
    clips = sorted(MOCAP.glob("*.bvh"))
    if not clips:
        tally.check("noh relabelled motion", False, f"no BVH files in {MOCAP} (set JAXRENDER_MOCAP)")
        return
    orders = ["Xrotation Yrotation Zrotation", "Yrotation Xrotation Zrotation", "Zrotation Yrotation Xrotation",
              "Xrotation Zrotation Yrotation", "Yrotation Zrotation Xrotation"]
    rng = np.random.default_rng(seed)
    for i in range(n):
        clip = clips[i % len(clips)]
        lines = clip.read_text().splitlines()
        order = orders[rng.integers(len(orders))]
        text = "\n".join(line.replace("Zrotation Xrotation Yrotation", order) for line in lines[:400]) + "\n"
        frames = sum(1 for line in text.splitlines()[text.splitlines().index("MOTION") + 3:] if line.strip())
        text = text.replace(next(line for line in text.splitlines() if line.startswith("Frames:")),
                            f"Frames: {frames}")
        eol = "\r\n" if rng.random() < 0.5 else "\n"
        with tempfile.TemporaryDirectory() as name:
            path, out = Path(name) / "motion.bvh", Path(name) / "out"
            path.write_bytes(("\ufeff" if rng.random() < 0.5 else "").encode() + text.replace("\n", eol).encode())
            proc = run("jaxrender", "noh", "--out", out, "--motion", path, "--frames", 3, "--width", 48,
                       "--height", 32, "--no-video")
            ok = proc.returncode == 0 and all(finite_exr(p) for p in out.glob("frame_*.exr"))
            ok = ok or refusal_ok(proc, "jaxrender noh", path, out)[0]
            tally.check("noh relabelled motion", ok, f"{clip.name} as {order}: exit {proc.returncode} "
                                                     f"{proc.stderr.strip()[-300:]!r}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a few documents of each kind")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    def n(full: int, quick: int) -> int:
        return quick if args.quick else full

    tally, start = Tally(), time.perf_counter()

    def valid_scene(doc, where):
        path, out = doc.write(where), where / "out.exr"
        proc = run("jaxrender", "shafts", path, "--out", out, "--width", 6, "--height", 4)
        tally.check("scene, valid", proc.returncode == 0 and finite_exr(out),
                    f"exit {proc.returncode}: {proc.stderr.strip()[-300:]!r}\n{path.read_text()[:2000]}")

    def broken_scene(doc, where):
        path, out = doc.write(where), where / "out.exr"
        ok, said = refusal_ok(run("jaxrender", "shafts", path, "--out", out), "jaxrender shafts", path, out)
        tally.check("scene, broken", ok, f"{doc.breaks}: {said}")

    def valid_bvh(doc, where):
        from jaxrender.io import read_bvh
        from sims import pose_motion

        path = doc.write(where)
        try:
            motion = pose_motion(read_bvh(path))
            ok, said = bool(np.all(np.isfinite(np.asarray(motion.positions)))), "positions not finite"
        except Exception as error:   # a finding: recorded, the run goes on
            ok, said = False, f"{type(error).__name__}: {error}"
        tally.check("BVH, valid", ok, said)

    def broken_bvh(doc, where):
        path, out = doc.write(where), where / "out"
        ok, said = refusal_ok(run("jaxrender", "noh", "--out", out, "--motion", path), "jaxrender noh", path, out)
        tally.check("BVH, broken", ok, f"{doc.breaks}: {said}")

    def valid_capture(doc, where):
        path, store = doc.write(where / "capture"), where / "store"
        proc = run("fitting", "ingest", path, "--store", store)
        tally.check("capture, valid", proc.returncode == 0 and (store / "store.json").is_file(),
                    f"exit {proc.returncode}: {proc.stderr.strip()[-300:]!r}")

    def broken_capture(doc, where):
        path, store = doc.write(where / "capture"), where / "store"
        ok, said = refusal_ok(run("fitting", "ingest", path, "--store", store), "fitting ingest", path, store)
        tally.check("capture, broken", ok, f"{doc.breaks}: {said}")

    def valid_folder(doc, where):
        source, out = doc.write(where / "object"), where / "capture" / "capture.json"
        proc = run("fitting", "manifest", source, "--out", out)
        ok = proc.returncode == 0
        if ok:
            proc = run("fitting", "ingest", out.parent, "--store", where / "store")
            ok = proc.returncode == 0
        tally.check("DiLiGenT folder, valid", ok, f"exit {proc.returncode}: {proc.stderr.strip()[-300:]!r}")

    def broken_folder(doc, where):
        source, out = doc.write(where / "object"), where / "capture" / "capture.json"
        ok, said = refusal_ok(run("fitting", "manifest", source, "--out", out), "fitting manifest", source,
                              out.parent)
        tally.check("DiLiGenT folder, broken", ok, f"{doc.breaks}: {said}")

    plan = [(scene_documents(renderable=True), n(40, 1), valid_scene), (broken_scene_documents(), n(60, 2),
                                                                         broken_scene),
            (bvh_documents(max_joints=200, max_frames=30), n(300, 5), valid_bvh),
            (broken_bvh_documents(), n(40, 2), broken_bvh),
            (capture_documents(), n(20, 1), valid_capture), (broken_capture_documents(), n(40, 2), broken_capture),
            (diligent_documents(), n(20, 1), valid_folder), (broken_diligent_documents(), n(40, 2), broken_folder)]
    for strategy, count, body in plan:
        explore(strategy, count, args.seed, body)
        print(f"{body.__name__}: {count} documents, {len(tally.findings)} findings so far", flush=True)
    relabelled_motions(tally, n(6, 0), args.seed)
    seconds = time.perf_counter() - start
    total = sum(tally.counts.values())
    print(f"\n{total} documents in {seconds:.0f} s: " + ", ".join(f"{k} {v}" for k, v in tally.counts.items()))
    print(f"{len(tally.findings)} findings" + "".join(f"\n  {f}" for f in tally.findings))
    write_results("format_fuzz", [dict(
        area="tools", target="generated documents: valid ones give exit 0 and finite output, broken ones "
                                "one line per problem and exit 2 with nothing written",
        measured=f"{total} documents (seed {args.seed}), {len(tally.findings)} findings",
        status="met" if not tally.findings else "missed",
        notes="; ".join(tally.findings[:5]), figures={"documents": total, "findings": len(tally.findings),
                                                       **{k: v for k, v in tally.counts.items()}})],
        quick=args.quick)


if __name__ == "__main__":
    main()

"""The robe against the performer's body as rendered, on triangles, over whole dances: how many
robe triangles go through the body per frame and how deep (`tests/robe_contact.py`: segment-triangle
and winding-number tests in float64, nothing of the simulator's capsules), the robe's largest
move per frame (it still moves freely), and what the check costs per frame.

The robe is simulated as `jaxrender noh` simulates it (float32 unless JAX_ENABLE_X64=1), 0.1 s a
frame: the whole built-in dance (6 s, 60 frames), the whole captured dance
(dance-short_normal_001.bvh, 63 s, 633 frames), and two captured motions the robe was not developed
on: a bow (bow_normal_001.bvh, 4.5 s) and a walk (walk_normal_001.bvh, 6.4 s). Rows "Noh robe" to
benchmarks/results/noh_collision.json.

The counts are chaotic: a change at the rounding level (the same arithmetic in another order)
changes which tangle forms and persists. `--perturb K` adds K runs of each motion with every free
vertex of the settled robe moved 1 micrometre in a random direction (seeds 1..K; no velocity
added) and reports the spread of the count.

Run: `python benchmarks/noh_collision.py [--perturb K] [--motions built-in,dance,bow,walk]`
(`--quick`: 0.5 s of the built-in and the captured dance, nothing written).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from _results import cpu_description, write_results  # noqa: E402
from robe_contact import BodyShape, contact, dance_performer, performer_frames  # noqa: E402

from jaxrender.io import read_bvh  # noqa: E402
from sims import noh_dance  # noqa: E402

MOCAP = Path(os.environ.get("JAXRENDER_MOCAP", Path(__file__).resolve().parents[2] / "shared" / "data" / "mocap"))
CAPTURED = "dance-short_normal_001.bvh"
# the captured motions beside the built-in dance: the dance the robe was developed on, then a bow and a
# walk it was not (each whole)
OTHERS = (("captured dance", CAPTURED), ("captured bow", "bow_normal_001.bvh"),
          ("captured walk", "walk_normal_001.bvh"))
FRAME_DT = 0.1
PERTURBATION = 1e-6   # m: `--perturb`'s move of each free vertex
MOTIONS = {"built-in": "built-in dance", "dance": "captured dance", "bow": "captured bow", "walk": "captured walk"}


def part_names(performer, shape: BodyShape, t: float) -> list[str]:
    """Each closed part of the body's mesh named after the body volume (capsule) nearest its
    vertices at time `t`; the open one is the mask."""
    import jax.numpy as jnp

    body = performer.costume.body
    a, b = (np.asarray(e, np.float64) for e in body.ends(*performer.motion.at(jnp.asarray(t))))
    ab, names = b - a, []
    for k in range(len(shape.closed)):
        x = shape.vertices[np.unique(shape.triangles[shape.part == k])]
        s = np.clip(np.einsum("nbk,bk->nb", x[:, None] - a[None], ab) / np.maximum(np.sum(ab * ab, -1), 1e-12), 0, 1)
        dist = np.linalg.norm(x[:, None] - (a[None] + s[..., None] * ab[None]), axis=-1) - np.asarray(body.radius)
        names.append(body.names[int(np.argmin(np.mean(np.abs(dist), axis=0)))] if shape.closed[k] else "mask")
    return names


def perturbed(performer, seed: int, size: float = PERTURBATION):
    """The performer with every free vertex of its robe's state moved `size` m in a random direction."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    state = performer.costume.state
    u = jax.random.normal(jax.random.PRNGKey(seed), state.x.shape, state.x.dtype)
    move = size * u / jnp.linalg.norm(u, axis=-1, keepdims=True) * performer.costume.inverse_mass[:, None]
    return eqx.tree_at(lambda p: (p.costume.state.x, p.costume.state.x_prev), performer,
                       (state.x + move, state.x_prev + move))


def measure(label: str, performer, duration: float) -> dict:
    frames = int(round(duration / FRAME_DT))
    shape, previous, rows, seconds, by_part = None, None, [], [], 0
    for body, robe in performer_frames(performer, frames, FRAME_DT):
        t0, c0 = time.perf_counter(), time.process_time()
        shape = BodyShape(body.vertices, body.triangles) if shape is None else shape.moved(body.vertices)
        c = contact(robe.vertices, robe.triangles, shape)
        seconds.append((time.perf_counter() - t0, time.process_time() - c0))
        by_part = by_part + c.by_part
        if len(rows) == 0:
            names = part_names(performer, shape, FRAME_DT)
        move = 0.0 if previous is None else float(np.linalg.norm(robe.vertices - previous, axis=-1).max())
        previous = robe.vertices
        rows.append((c.triangles, c.depth, c.crossing_edges, c.inside_vertices, move))
    a = np.asarray(rows)
    wall, cpu = np.median(np.asarray(seconds[1:] or seconds), axis=0)
    out = dict(label=label, frames=frames, robe_triangles=len(robe.triangles), body_triangles=len(body.triangles),
               closed_parts=int(shape.closed.sum()), through_total=int(a[:, 0].sum()),
               through_max=int(a[:, 0].max()), frames_with=int((a[:, 0] > 0).sum()), deepest_m=float(a[:, 1].max()),
               largest_move_m=float(a[:, 4].max()), check_wall_s=float(wall), check_cpu_s=float(cpu),
               load=os.getloadavg()[0],
               through_by_part={n: int(k) for n, k in sorted(zip(names, by_part), key=lambda nk: -nk[1]) if k})
    print(out, flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="0.5 s of the built-in and the captured dance, nothing written")
    parser.add_argument("--perturb", type=int, default=0, help="runs of each motion with the robe perturbed")
    parser.add_argument("--motions", default=",".join(MOTIONS), help=f"some of {','.join(MOTIONS)}")
    args = parser.parse_args()
    chosen = [m for m in args.motions.split(",") if m]
    if not chosen or set(chosen) - set(MOTIONS) or args.perturb < 0:
        parser.error(f"--motions: some of {', '.join(MOTIONS)}; --perturb: >= 0")
    wanted = {MOTIONS[m] for m in chosen}
    motions = [("built-in dance", noh_dance(), 0.5 if args.quick else 6.0)] if "built-in dance" in wanted else []
    for label, name in (("captured dance", CAPTURED),) if args.quick else OTHERS:
        if label in wanted:
            bvh = read_bvh(MOCAP / name)
            whole = bvh.motion.shape[0] * bvh.frame_time
            motions.append((label, bvh, 0.5 if args.quick else FRAME_DT * int(whole / FRAME_DT)))
    runs = []
    for label, bvh, duration in motions:
        performer = dance_performer(bvh, duration=duration)   # dressed and settled once
        run = measure(label, performer, duration)
        run["perturbed_through"] = [measure(label, perturbed(performer, seed), duration)["through_total"]
                                    for seed in range(1, args.perturb + 1)]
        runs.append(run)
    rows = []
    for r in runs:
        status = "met" if r["through_total"] == 0 and not any(r["perturbed_through"]) else "missed"   # every run
        most = list(r["through_by_part"].items())[:5]
        parts = f"; through the {', '.join(f'{n} {k}' for n, k in most)}" if most else ""
        spread = r["perturbed_through"]
        if spread:
            parts += (f"; robe perturbed by 1 um, {len(spread)} runs: {min(spread)}-{int(np.median(spread))}-"
                      f"{max(spread)} (min-median-max)")
        rows.append(dict(
            area="noh", target=f"0 robe triangles through the body as rendered, {r['label']}",
            measured=f"{r['through_total']} triangles through over {r['frames']} frames (most in a frame "
                     f"{r['through_max']}, deepest {1000 * r['deepest_m']:.1f} mm{parts}); robe's largest move per "
                     f"frame {100 * r['largest_move_m']:.1f} cm; check {r['check_cpu_s']:.2f} s CPU per frame, load "
                     f"{r['load']:.1f}, {cpu_description()}",
            status=status, figures=r))
    write_results("noh_collision", rows, quick=args.quick, update=set(chosen) != set(MOTIONS))


if __name__ == "__main__":
    main()

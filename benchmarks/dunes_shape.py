"""Dune shape and migration vs. the creep coefficient D (paper 001 eqs. 5-6; D is not given by
the paper): mean lee slope / mean windward slope and the downwind speed, 4 fields of 48x96 from
depths uniform in [1, 2) and [2, 4), 1500 steps, paper parameters L0 = 7, q0 = 1.5, b = b' = 2.

    python benchmarks/dunes_shape.py [--quick]
"""

from __future__ import annotations

import argparse

import numpy as np


def _slope_ratio(fields):
    s = 0.5 * (np.roll(fields, -1, -1) - np.roll(fields, 1, -1))
    out = []
    for si in s:
        steep = np.abs(si) > 0.05
        out.append(-si[(si < 0) & steep].mean() / si[(si > 0) & steep].mean())
    return np.array(out)


def _speed(before, after, steps):
    w = before.shape[-1]
    shifts = np.arange(-(w // 2), w // 2)
    corr = [np.sum(np.roll(before, s, axis=-1) * after) for s in shifts]
    return shifts[int(np.argmax(corr))] / steps


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 fields, 800 steps")
    args = parser.parse_args(argv)
    import jax

    from sims import DuneParams, init_dunes, simulate_dunes

    batch, steps = (2, 800) if args.quick else (4, 1500)
    print(f"dunes {batch} x 48x96, {steps} steps, L0=7 q0=1.5 b=2 b'=2, split hop, wind +x")
    print()
    print("| D | initial depth | lee / windward mean slope (per field) | max height "
          "| speed (cells/step, + = downwind) |")
    print("|---|---|---|---|---|")
    for D in (0.1, 0.2, 0.3, 0.5, 0.8):
        for lo, hi in ((1.0, 2.0), (2.0, 4.0)):
            p = DuneParams(D=D)
            h = simulate_dunes(init_dunes(jax.random.key(7), (batch, 48, 96), low=lo, high=hi), p, steps=steps)
            later = simulate_dunes(h, p, steps=5)
            a, b = np.asarray(h), np.asarray(later)
            ratio = _slope_ratio(a)
            speed = np.mean([_speed(a[i], b[i], 5) for i in range(batch)])
            print(f"| {D} | {lo:g}-{hi:g} | {' '.join(f'{r:.2f}' for r in ratio)} | {a.max():.1f} | {speed:+.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

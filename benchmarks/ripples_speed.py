"""Ripple automaton speed (paper 001 eqs. 1-4, issue 3 section 4): ours (sims.simulate_ripples,
jitted scan, float32; also float64, the peer's dtype) vs a vectorized numpy implementation of the same rules (np.bincount
deposit, np.roll creep) vs numba loops, on 256x256, split hop along +x, paper parameters.
Also the gather (sum of rolls) formulation that sims._transport does not use, for the record.

    python benchmarks/ripples_speed.py [--quick] [--size N] [--steps S]

Compile time is reported apart; run times are medians of repeats after a warm-up, per step.
The fields are first grown for 500 steps so the hop range is that of developed ripples.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))

from _ripples_ref import make_jax_roll_gather, make_numba_steps, numpy_step  # noqa: E402


def _median_time(fn, repeats):
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="128x128, fewer steps and repeats")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--steps", type=int, default=200, help="steps per timed run of the jitted versions")
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args(argv)
    if args.quick:
        args.size, args.steps, args.repeats = 128, 50, 3

    import jax

    jax.config.update("jax_enable_x64", True)  # float64 only for the agreement check; timed runs are float32
    import jax.numpy as jnp

    from sims import RippleParams, init_ripples, simulate_ripples

    n, steps, reps = args.size, args.steps, args.repeats
    params = RippleParams()
    h0 = simulate_ripples(init_ripples(jax.random.key(0), (n, n), dtype=jnp.float32), params, steps=500)
    h0.block_until_ready()
    h0_np = np.asarray(h0, dtype=np.float64)

    # ours: compile apart
    t = time.perf_counter()
    compiled = jax.jit(simulate_ripples, static_argnames=("steps",)).lower(h0, params, steps=steps).compile()
    compile_s = time.perf_counter() - t
    compiled(h0, params).block_until_ready()
    # like with like: ours in float64, the numpy peer's dtype (np.bincount always sums in float64)
    h0_64 = jnp.asarray(h0_np)
    compiled64 = jax.jit(simulate_ripples, static_argnames=("steps",)).lower(h0_64, params, steps=steps).compile()
    compiled64(h0_64, params).block_until_ready()

    # numpy: same rules, float64; timed interleaved with ours so both see the same machine load
    np_steps = max(10, steps // 4)

    def run_numpy():
        h = h0_np
        for _ in range(np_steps):
            h = numpy_step(h)
        return h

    run_numpy()
    ours_times, numpy_times, ours_cpu, numpy_cpu, ours64_times, ours64_cpu = [], [], [], [], [], []
    for _ in range(reps):
        c = time.process_time()
        ours_times.append(_median_time(lambda: compiled(h0, params).block_until_ready(), 1) / steps)
        ours_cpu.append((time.process_time() - c) / steps)
        c = time.process_time()
        ours64_times.append(_median_time(lambda: compiled64(h0_64, params).block_until_ready(), 1) / steps)
        ours64_cpu.append((time.process_time() - c) / steps)
        c = time.process_time()
        numpy_times.append(_median_time(run_numpy, 1) / np_steps)
        numpy_cpu.append((time.process_time() - c) / np_steps)
    ours_s, numpy_s = statistics.median(ours_times), statistics.median(numpy_times)
    pair_ratio = statistics.median(b / a for a, b in zip(ours_times, numpy_times))
    cpu_ratio = statistics.median(numpy_cpu) / statistics.median(ours_cpu)
    cpu_ratio64 = statistics.median(numpy_cpu) / statistics.median(ours64_cpu)
    ours64_s = statistics.median(ours64_times)

    # agreement with numpy: ours in float64 over all steps (same rules), ours in float32 over 10 steps
    # (the automaton is unstable: float32 rounding differences grow with the ripples)
    h_np = h0_np
    for _ in range(steps):
        h_np = numpy_step(h_np)
    agree64 = float(np.max(np.abs(np.asarray(simulate_ripples(jnp.asarray(h0_np), params, steps=steps)) - h_np)))
    h10 = h0_np
    for _ in range(10):
        h10 = numpy_step(h10)
    agree32 = float(np.max(np.abs(np.asarray(simulate_ripples(h0, params, steps=10), dtype=np.float64) - h10)))

    # numba
    try:
        run_numba = make_numba_steps()
        t = time.perf_counter()
        run_numba(h0_np, 1, 7.3, 0.6, 2.0, 0.8)
        numba_compile = time.perf_counter() - t
        numba_s = _median_time(lambda: run_numba(h0_np, steps, 7.3, 0.6, 2.0, 0.8), max(3, reps // 2)) / steps
        numba_agree = float(np.max(np.abs(run_numba(h0_np, steps, 7.3, 0.6, 2.0, 0.8) - h_np)))
    except ImportError:
        numba_compile = numba_s = numba_agree = float("nan")

    # gather formulation (not used): for the record
    gather = make_jax_roll_gather()
    t = time.perf_counter()
    gather(h0, steps).block_until_ready()
    gather_first = time.perf_counter() - t
    gather_s = _median_time(lambda: gather(h0, steps).block_until_ready(), max(3, reps // 2)) / steps

    rows = [
        ("ours: sims.simulate_ripples (scatter hop, float32)", ours_s, compile_s, agree32),
        ("ours in float64 (like with like)", ours64_s, float("nan"), agree64),
        ("numpy vectorized (bincount + roll, float64)", numpy_s, 0.0, 0.0),
        ("numba loops (float64)", numba_s, numba_compile, float("nan")),
        ("jax gather: sum of rolls over the hop range (float32)", gather_s, gather_first - gather_s * steps, float("nan")),
    ]
    print(f"ripple automaton {n}x{n}, split hop, L0=7.3 q=0.6 b=2.0 D=0.8, developed ripples (500 steps grown); "
          f"{steps} steps per timed run, median of {reps}; jax {jax.__version__}, backend {jax.default_backend()}")
    print()
    print("| implementation | ms / step | speed-up vs numpy | compile s | max abs diff vs numpy |")
    print("|---|---|---|---|---|")
    for name, s, c, diff in rows:
        print(f"| {name} | {s * 1e3:.3f} | {numpy_s / s:.1f}x | {c:.2f} | {diff:.2e} |")
    print()
    print(f"agreement: ours float32 vs numpy after 10 steps {agree32:.1e}; ours float64 vs numpy after {steps} steps "
          f"{agree64:.1e}; numba after {steps} steps {numba_agree:.1e}")
    print(f"ours vs numpy, median of the per-repeat wall-clock ratios (interleaved runs): {pair_ratio:.1f}x")
    print(f"ours vs numpy by process CPU time (less sensitive to other load; XLA threads counted): "
          f"{statistics.median(ours_cpu) * 1e3:.3f} vs {statistics.median(numpy_cpu) * 1e3:.3f} ms/step = {cpu_ratio:.1f}x "
          f"(least of the repeats: {min(ours_cpu) * 1e3:.3f} vs {min(numpy_cpu) * 1e3:.3f} ms/step = "
          f"{min(numpy_cpu) / min(ours_cpu):.1f}x)")
    print(f"like with like (both float64), by CPU time: {statistics.median(ours64_cpu) * 1e3:.3f} vs "
          f"{statistics.median(numpy_cpu) * 1e3:.3f} ms/step = {cpu_ratio64:.1f}x")
    target = 20.0
    ratio = pair_ratio
    print(f"target >= {target:.0f}x numpy: wall clock {'met' if ratio >= target else 'MISSED'} ({ratio:.1f}x), "
          f"CPU time {'met' if cpu_ratio >= target else 'MISSED'} ({cpu_ratio:.1f}x)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

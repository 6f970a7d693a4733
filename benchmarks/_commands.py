"""A command as a user runs it, timed: `run_command(argv, env)` runs it in a fresh process (its
output discarded, a failure raised) and returns its wall and CPU seconds and the machine's load
before and after (the machine may be shared)."""

from __future__ import annotations

import os
import resource
import subprocess
import time


def run_command(argv: list[str], env: dict | None = None) -> dict:
    """{wall_s, cpu_s, load, load_after} of `argv` run to completion in a child process."""
    before, load = resource.getrusage(resource.RUSAGE_CHILDREN), os.getloadavg()[0]
    t0 = time.perf_counter()
    subprocess.run(argv, check=True, stdout=subprocess.DEVNULL, env=env)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"wall_s": round(wall, 2), "cpu_s": round(cpu, 2), "load": round(load, 2),
            "load_after": round(os.getloadavg()[0], 2)}

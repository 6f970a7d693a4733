"""JAX's persistent compilation cache for the command-line programs: a command's second run (and a
fit of the next object) loads the programs its first run compiled instead of compiling them again.

Where: `$JAXRENDER_COMPILE_CACHE` if set (`0`, `off`, `no` or `false`: no cache), else
`$XDG_CACHE_HOME/jaxrender/compile-<key>` (`~/.cache` by default), one directory per kind of CPU
(model and instruction-set flags) and JAX version, so that a home directory shared between machines
never offers one a program compiled for another's instructions. `$JAX_COMPILATION_CACHE_DIR`, JAX's
own setting, wins over both. Delete the directory at will.

Before a directory is first used, two child processes check that JAX reads back on this machine what
it wrote: on some CPUs JAX 0.10 rejects every cached CPU program it wrote itself, with an error line
for each (jax-ml/jax#38445). Where the check fails, the directory is marked and no command uses it.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
import sys
from importlib import metadata
from pathlib import Path

CACHE_ENV = "JAXRENDER_COMPILE_CACHE"
_OFF = ("0", "off", "no", "false")
PROBE_FILE = "probe.json"   # {"usable": bool, "why": str}: the two-process check's outcome
PROBE_TIMEOUT_S = 120

# A child compiles a small program with the cache on, then prints the cache hits it saw; the first
# child writes the entry, the second must read it back, silently.
_PROBE_CHILD = """
import sys
import jax, jax.numpy as jnp
from jax import monitoring
hits = []
monitoring.register_event_listener(lambda event, **kw: hits.append(event) if event.endswith("cache_hits") else None)
jax.config.update("jax_compilation_cache_dir", sys.argv[1])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
x = jnp.linspace(0.0, 1.0, 64).reshape(8, 8)
jax.jit(lambda a: jnp.sin(a) @ jnp.cos(a).T + jnp.take(a, jnp.arange(3), axis=0).sum())(x).block_until_ready()
print(len(hits))
"""


def machine_key() -> str:
    """A short hash of the CPU (model name and flags) and the installed jax and jaxlib versions."""
    try:
        info = Path("/proc/cpuinfo").read_text()
        cpu = next((line for line in info.splitlines() if line.startswith("model name")), "")
        cpu += next((line for line in info.splitlines() if line.startswith("flags")), "")
    except OSError:
        cpu = ""
    versions = []
    for name in ("jax", "jaxlib"):
        try:
            versions.append(metadata.version(name))
        except metadata.PackageNotFoundError:
            versions.append("-")
    text = f"{platform.machine()} {platform.processor()} {cpu} {' '.join(versions)}"
    return hashlib.sha256(text.encode()).hexdigest()[:12]


def cache_dir(environ=None) -> Path | None:
    """The directory the commands cache compiled programs in, or None: no cache of ours (switched off,
    or `$JAX_COMPILATION_CACHE_DIR` set: JAX then uses that one itself)."""
    environ = os.environ if environ is None else environ
    if environ.get("JAX_COMPILATION_CACHE_DIR"):
        return None
    value = environ.get(CACHE_ENV)
    if value is not None:
        return None if value.strip().lower() in _OFF or not value.strip() else Path(value).expanduser()
    base = Path(environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "jaxrender" / f"compile-{machine_key()}"


def _run_probe(path: Path) -> tuple[bool | None, str]:
    """(usable, why): the first child writes a program into `path/probe`, the second must read it back
    with nothing on stderr. usable is None where the check itself did not finish (asked again next
    time)."""
    probe = path / "probe"
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    outputs = []
    for _ in range(2):
        try:
            child = subprocess.run([sys.executable, "-c", _PROBE_CHILD, str(probe)], capture_output=True, text=True,
                                   env=env, timeout=PROBE_TIMEOUT_S)
        except (OSError, subprocess.TimeoutExpired) as error:
            return None, f"the check did not run: {error}"
        if child.returncode != 0:
            return None, f"the check failed: {(child.stderr.strip().splitlines() or [''])[-1]}"
        outputs.append(child)
    second = outputs[1]
    errors = [line for line in second.stderr.splitlines() if line.strip()]
    if errors:
        return False, f"JAX rejects its own cached programs here: {errors[0][:200]}"
    if not second.stdout.strip().isdigit() or int(second.stdout) == 0:
        return False, "the second process read nothing from the cache"
    return True, "a program written by one process was read back by another"


def usable(path: Path) -> bool:
    """Whether `path` can be used: made if missing, writable, and checked once (`PROBE_FILE`)."""
    try:
        path.mkdir(parents=True, exist_ok=True)
        if not os.access(path, os.W_OK):
            return False
        marker = path / PROBE_FILE
        try:
            return bool(json.loads(marker.read_text())["usable"])
        except (OSError, ValueError, KeyError, TypeError):
            pass
        ok, why = _run_probe(path)
        if ok is None:
            return False
        partial = marker.with_name(f".{PROBE_FILE}.{os.getpid()}")
        partial.write_text(json.dumps({"usable": ok, "why": why}))
        partial.replace(marker)
        return ok
    except OSError:
        return False


def use_compile_cache(environ=None) -> Path | None:
    """Turn the cache on for this process and the processes it starts (Dask workers); the directory
    used, or None. Every program is kept, however quick to compile (a command compiles a few hundred
    small ones), unless `$JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS` says otherwise."""
    environ = os.environ if environ is None else environ
    path = cache_dir(environ)
    if path is None or not usable(path):
        return None
    environ["JAX_COMPILATION_CACHE_DIR"] = str(path)
    environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    if "jax" in sys.modules:   # imported with the command's module: its configuration is read already
        import jax

        jax.config.update("jax_compilation_cache_dir", str(path))
        jax.config.update("jax_persistent_cache_min_compile_time_secs",
                          float(environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"]))
    return path

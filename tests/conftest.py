"""Test configuration in the style of optimistix: float64 references, no silent rank or dtype
promotion, warnings are errors (pyproject.toml).

One persistent compilation cache for every run on this machine (every xdist worker, and through
the environment every command, notebook kernel and benchmark script the tests start): the same
program compiled by two processes, or by two runs, is compiled once, so a run between edits
compiles only what the edit changed (`_compile_cache`). A fresh CI runner starts it empty; to time
a run as one, point $JAX_COMPILATION_CACHE_DIR at an empty directory. Tests that check the cache
itself set their own."""

import gc
import os
import tempfile
from pathlib import Path

from jaxrender.app.cli.compile_cache import machine_key  # imports no jax: the settings below come first


def _compile_cache() -> Path:
    """$XDG_CACHE_HOME/jaxrender-tests-<key> (~/.cache by default; the temporary directory where
    that cannot be written): one directory per kind of CPU (its model and instruction-set flags)
    and JAX version (the commands' own cache's key, `compile_cache.machine_key`), so that a home
    directory shared between machines never offers one a program compiled for another's
    instructions (JAX would reject it, loudly). It grows by what each edit recompiles (a full run
    from empty: about 150 MB); delete it at will."""
    key = machine_key()
    for base in (os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache", tempfile.gettempdir()):
        path = Path(base) / f"jaxrender-tests-{key}"
        try:  # a home directory one cannot write to: the temporary directory instead
            path.mkdir(parents=True, exist_ok=True)
        except OSError:
            continue
        if os.access(path, os.W_OK):
            return path
    return path


os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=true")
if "JAX_COMPILATION_CACHE_DIR" not in os.environ:
    os.environ["JAX_COMPILATION_CACHE_DIR"] = str(_compile_cache())
# every program, however quick to compile: the commands and scripts the tests start compile the
# same few hundred small programs each (measured: a Noh benchmark's second run 29 s CPU with them
# cached, 44 s with only those over a second)
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")

# The inner loop (`python -m pytest -m quick -n 2`, two to five minutes on 2 cores from an empty
# compilation cache by the CPU, one to two once the cache holds its programs; README): every area's kernels
# and file formats against their references, without the end-to-end commands, notebooks, brute-force
# frames and benchmark runs that make up most of the full suite's time.
QUICK_MODULES = {
    "test_architecture", "test_atomic", "test_brdf", "test_btf_io", "test_bvh", "test_capture",
    "test_capture_formats", "test_capture_limits", "test_desert_shadows", "test_dunes", "test_dust",
    "test_envmap", "test_fields", "test_fire_cloth", "test_floor_reflection",
    "test_foundation", "test_fusion", "test_gallery", "test_geometry", "test_hdr", "test_horizon_sweep",
    "test_manifest", "test_pcss", "test_ripples", "test_shadow_map", "test_sky", "test_spot",
    "test_varpro",
}
# The longest tests start first, so that under `-n 2` neither worker is left running one alone at the end.
LONGEST_FIRST = ("test_noh_bruteforce.py", "test_user_runs.py::TestGallery", "test_user_runs.py::TestNohCommand",
                 "test_benchmarks_quick.py::TestNohScripts", "test_benchmarks_quick.py::TestShaftsScripts",
                 "test_dask_fit.py", "test_shafts_adaptive.py", "test_user_runs.py",
                 "test_benchmarks_quick.py")
# Under xdist (`--dist loadscope`, pyproject.toml) the tests of a module (or of a class) run on one
# worker, so that its module fixtures and compiled functions are made once, not once per worker;
# test_benchmarks_quick and test_user_runs put their independent runs in classes to share them out.


def pytest_collection_modifyitems(config, items):
    for item in items:
        if item.path.stem in QUICK_MODULES:
            item.add_marker("quick")
    rank = {i: next((k for k, key in enumerate(LONGEST_FIRST) if key in item.nodeid), len(LONGEST_FIRST))
            for i, item in enumerate(items)}
    order = sorted(range(len(items)), key=lambda i: rank[i])  # stable: the rest keep their order
    items[:] = [items[i] for i in order]


@pytest.fixture(autouse=True, scope="module")
def _drop_compiled_programs():
    """After each module its compiled programs are dropped, so that a worker's memory does not grow
    with the suite (without it, 6-7 GB per worker two thirds in); a later module that needs one again
    loads it from the persistent cache."""
    yield
    jax.clear_caches()
    gc.collect()

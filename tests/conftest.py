"""Test configuration in the style of optimistix: float64 references, no silent rank or dtype
promotion, warnings are errors (pyproject.toml).

One persistent compilation cache for the whole run (every xdist worker, and through the
environment every command, notebook kernel and benchmark script the tests start): the same
program compiled by two processes is compiled once. It starts empty, as on a fresh CI runner, and
lives in the temporary directory of this run only; tests that check the cache itself set their own."""

import os
import tempfile
from pathlib import Path

os.environ.setdefault("XLA_FLAGS", "--xla_cpu_multi_thread_eigen=true")
_RUN = os.environ.get("PYTEST_XDIST_TESTRUNUID") or f"pid{os.getpid()}"
_CACHE = Path(tempfile.gettempdir()) / f"jaxrender-tests-jax-cache-{_RUN}"
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(_CACHE))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "1")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")

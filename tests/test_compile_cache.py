"""The command-line programs' compile cache (`jaxrender.app.cli.compile_cache`): where it is, the
one-off check that JAX reads back on this machine what it wrote, and a command's second run
loading its programs instead of compiling them again."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from jaxrender.app.cli import compile_cache
from jaxrender.app.cli.compile_cache import CACHE_ENV, PROBE_FILE, cache_dir, usable


def test_the_directory_follows_the_environment(tmp_path):
    assert cache_dir({"JAX_COMPILATION_CACHE_DIR": "/a", CACHE_ENV: "/b"}) is None   # JAX's own setting wins
    for off in ("0", "off", "No", "false", ""):
        assert cache_dir({CACHE_ENV: off}) is None
    assert cache_dir({CACHE_ENV: str(tmp_path / "c")}) == tmp_path / "c"
    default = cache_dir({"XDG_CACHE_HOME": str(tmp_path)})
    assert default.parent == tmp_path / "jaxrender" and default.name.startswith("compile-")
    assert len(default.name) == len("compile-") + 12 and default == cache_dir({"XDG_CACHE_HOME": str(tmp_path)})


@pytest.mark.parametrize("stdout, stderr, expected", [
    ("3", "", True),                                             # read back, silently
    ("3", "E cpu_aot_loader.cc:195] Target machine feature +prefer-no-gather is not supported", False),
    ("0", "", False),                                            # nothing read back
])
def test_the_check_marks_the_directory(tmp_path, monkeypatch, stdout, stderr, expected):
    """The check's verdict from its second child (here a stand-in printing what JAX's would), kept in
    the directory: the next command reads it and runs no check."""
    child = f"import sys; print({stdout!r}); print({stderr!r}, file=sys.stderr)"
    monkeypatch.setattr(compile_cache, "_PROBE_CHILD", child)
    path = tmp_path / "cache"
    assert usable(path) is expected
    marker = json.loads((path / PROBE_FILE).read_text())
    assert marker["usable"] is expected and (expected or marker["why"])
    if stderr:
        assert "prefer-no-gather" in marker["why"]
    monkeypatch.setattr(compile_cache, "_run_probe", lambda path: pytest.fail("checked twice"))
    assert usable(path) is expected


def test_a_check_that_does_not_finish_is_made_again(tmp_path, monkeypatch):
    """A child that fails (or does not start) decides nothing: no cache this time, no verdict kept."""
    monkeypatch.setattr(compile_cache, "_PROBE_CHILD", "raise SystemExit(1)")
    path = tmp_path / "cache"
    assert usable(path) is False and not (path / PROBE_FILE).exists()
    monkeypatch.setattr(compile_cache, "_PROBE_CHILD", "print(1)")
    assert usable(path) is True and json.loads((path / PROBE_FILE).read_text())["usable"] is True


def test_a_directory_that_cannot_be_made_is_not_used(tmp_path, monkeypatch):
    monkeypatch.setattr(compile_cache, "_run_probe", lambda path: pytest.fail("no check without a directory"))
    (tmp_path / "file").write_text("")
    assert usable(tmp_path / "file" / "cache") is False
    env = {CACHE_ENV: str(tmp_path / "file" / "cache")}
    assert compile_cache.use_compile_cache(env) is None and "JAX_COMPILATION_CACHE_DIR" not in env


def _entries(path: Path) -> set[str]:
    return {p.name for p in path.iterdir() if p.name.endswith("-cache")}


def test_a_command_run_twice_loads_its_programs_from_the_cache(tmp_path):
    """`sims ripples` twice with the cache in a fresh directory, as a user runs it (no
    $JAX_COMPILATION_CACHE_DIR): where the machine's check passes, the first run writes its programs
    and the second writes none (it compiled nothing); where it fails, neither writes any. Either way
    nothing on stderr, and the same field."""
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_COMPILATION_CACHE_DIR",
                                                             "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS")}
    cache = tmp_path / "cache"
    env[CACHE_ENV] = str(cache)
    fields = []
    for run in range(2):
        out = tmp_path / f"field{run}.npy"
        child = subprocess.run([sys.executable, "-m", "jaxrender.app.cli.programs", "sims", "ripples", "--size", "24",
                                "--steps", "5", "--out", str(out)], capture_output=True, text=True, env=env,
                               timeout=300)
        assert child.returncode == 0 and child.stderr == "", child.stderr
        fields.append(np.load(out))
        if run == 0:
            first = _entries(cache)
    np.testing.assert_array_equal(fields[0], fields[1])
    if json.loads((cache / PROBE_FILE).read_text())["usable"]:
        assert len(first) >= 3                   # the automaton's programs, every one kept
        assert _entries(cache) == first          # the second run compiled nothing
    else:
        assert first == set() and _entries(cache) == set()

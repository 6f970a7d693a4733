"""The observation store: round trip against the in-memory merge, the fit from the store against the
in-memory fit (bit for bit with a float32 store), SIGKILL + resume of the ingest and of the fit,
pixel problems found during the pass, and the light block sized from the memory budget.

Subprocesses share a persistent JAX compilation cache (as tests/test_fit_driver.py)."""

import contextlib
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import numpy as np
import pytest
from capture_helpers import write_capture, write_foreign_exr

from fitting import (
    CaptureError,
    FitSettings,
    fit_observations,
    fit_store,
    ingest_capture,
    load_capture,
    merge_capture,
    open_store,
    synth_capture,
)
from fitting.ingest import light_block_for
from fitting.store import DARK, SATURATED, VALID
from jaxrender.io import InputError, read_btf, write_exr, write_png

SIZE = (8, 8)
CHUNK = 8          # 8 tiles of 8 texels
LIGHT_BLOCK = 7    # 60 lights -> 9 blocks, the last one partial


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return tmp_path_factory.mktemp("store")


@pytest.fixture(scope="module")
def capture(root):
    return synth_capture(root / "capture", key=jax.random.key(5), size=SIZE, lights=60, progress=False)


@pytest.fixture(scope="module")
def merged(capture):
    return merge_capture(load_capture(capture), progress=False)


@pytest.fixture(scope="module")
def store32(root, capture):
    return ingest_capture(capture, root / "store32", dtype="float32", light_block=LIGHT_BLOCK, tile=CHUNK,
                          progress=False)


def _env(root: Path) -> dict:
    env = dict(os.environ)
    env["JAX_COMPILATION_CACHE_DIR"] = str(root / "jax-cache")
    env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"
    env["JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES"] = "0"
    env.pop("JAX_ENABLE_X64", None)
    return env


@contextlib.contextmanager
def _fit_mode(root: Path):
    """float32 fits as `fitting fit` runs them, compiled into the persistent cache the subprocesses
    of this module load (one compilation of the tile program for the whole module)."""
    names = ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs",
             "jax_persistent_cache_min_entry_size_bytes")
    saved = {name: getattr(jax.config, name) for name in names}
    for name, value in zip(names, (str(root / "jax-cache"), 0.0, 0), strict=True):
        jax.config.update(name, value)
    try:
        with jax.enable_x64(False):
            yield
    finally:
        for name, value in saved.items():
            jax.config.update(name, value)


def _arrays(store_dir):
    import zarr

    group = zarr.open_group(str(store_dir), mode="r")
    return {name: np.asarray(group[name][:]) for name in ("ratio", "flags", "counts")}


def test_round_trip_float32_equals_in_memory_merge(store32, merged):
    store = open_store(store32)
    assert store.size == SIZE and store.n_lights == 60 and store.dtype == "float32"
    obs = store.observations()
    for name in ("ratio", "weight", "n_valid", "n_saturated", "n_dark"):  # the same merge, stored: bit for bit
        np.testing.assert_array_equal(np.asarray(getattr(obs, name)), np.asarray(getattr(merged, name)), err_msg=name)
    np.testing.assert_array_equal(np.asarray(obs.light_dirs), np.asarray(merged.light_dirs))
    import zarr

    group = zarr.open_group(str(store32), mode="r")
    assert group["ratio"].chunks == (CHUNK, LIGHT_BLOCK, 3) and group["flags"].chunks == (CHUNK, LIGHT_BLOCK)
    flags = np.asarray(group["flags"][:]).reshape(SIZE + (60,))
    # the flag bits against the counts the merge computed
    np.testing.assert_array_equal(((flags & SATURATED) > 0).sum(-1), np.asarray(merged.n_saturated))
    np.testing.assert_array_equal(((flags & DARK) > 0).sum(-1), np.asarray(merged.n_dark))
    np.testing.assert_array_equal(((flags & VALID) > 0).sum(-1), np.asarray(merged.n_valid))
    assert not (store32 / ".ingest").exists() and (store32 / "store.json").is_file()


def test_float16_store_is_the_rounded_merge(root, capture, merged):
    store = open_store(ingest_capture(capture, root / "store16", light_block=LIGHT_BLOCK, tile=CHUNK, progress=False))
    assert store.dtype == "float16"
    ratio, _ = store.read(0, store.n_texels)
    # numpy's own round-to-nearest float16 cast of the in-memory merge: the store adds no other error
    expected = np.asarray(merged.ratio).reshape(ratio.shape).astype(np.float16).astype(np.float32)
    np.testing.assert_array_equal(ratio, expected)


def test_fit_from_float32_store_is_bit_identical(root, store32, merged):
    with _fit_mode(root):  # the fit of float32 observations, as `fitting fit` runs it
        fit_observations(merged, root / "btf_mem", FitSettings(chunk=CHUNK), pyramid=False, progress=False)
        fit_store(store32, root / "btf_store", FitSettings(chunk=CHUNK), pyramid=False, progress=False)
    manifest, got = read_btf(root / "btf_store")
    _, ref = read_btf(root / "btf_mem")
    assert manifest["store"]["dtype"] == "float32" and not (root / "btf_store" / ".partial").exists()
    for name in ref[0]:
        np.testing.assert_array_equal(got[0][name], ref[0][name], err_msg=name)


KILL_INGEST = """
import os, signal, sys
from fitting import ingest_capture
def stop(i):
    if i == 3:
        os.kill(os.getpid(), signal.SIGKILL)
ingest_capture(sys.argv[1], sys.argv[2], dtype="float32", light_block={block}, tile={chunk}, progress=False,
               on_block=stop)
"""


def test_killed_ingest_resumes_to_the_same_store(root, capture, store32):
    out = root / "store_killed"
    code = textwrap.dedent(KILL_INGEST.format(block=LIGHT_BLOCK, chunk=CHUNK))
    proc = subprocess.run([sys.executable, "-c", code, str(capture), str(out)], env=_env(root), capture_output=True,
                          timeout=300)
    assert proc.returncode == -9, proc.stderr.decode()
    assert not (out / "store.json").exists()
    assert sorted(p.name for p in (out / ".ingest").glob("block_*")) == [f"block_{i:06d}" for i in range(4)]
    with pytest.raises(InputError, match="unfinished"):
        open_store(out)
    blocks = []
    ingest_capture(capture, out, dtype="float32", light_block=LIGHT_BLOCK, tile=CHUNK, progress=False,
                   on_block=blocks.append)
    assert blocks == list(range(4, 9))  # only the blocks not written before the kill
    got, ref = _arrays(out), _arrays(store32)
    for name in ref:
        np.testing.assert_array_equal(got[name], ref[name], err_msg=name)


KILL_FIT = """
import os, signal, sys
from fitting.checkpoint import Checkpoint
from fitting import FitSettings, fit_store
save, saved = Checkpoint.save, []
def save_then_die(self, index, fit):
    save(self, index, fit)
    saved.append(index)
    if len(saved) == 3:
        os.kill(os.getpid(), signal.SIGKILL)
Checkpoint.save = save_then_die
fit_store(sys.argv[1], sys.argv[2], FitSettings(chunk={chunk}), pyramid=False, progress=False)
"""


def test_killed_fit_resumes_bit_identical(root, store32):
    ref_dir = root / "btf_store"  # test_fit_from_float32_store_is_bit_identical's, or made here
    if not (ref_dir / "btf.json").is_file():
        with _fit_mode(root):
            fit_store(store32, ref_dir, FitSettings(chunk=CHUNK), pyramid=False, progress=False)
    out = root / "btf_store_killed"
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(KILL_FIT.format(chunk=CHUNK)), str(store32),
                           str(out)], env=_env(root), capture_output=True, timeout=600)
    assert proc.returncode == -9, proc.stderr.decode()
    assert len(list((out / ".partial").glob("chunk_*.npz"))) == 3 and not (out / "btf.json").exists()
    with _fit_mode(root):
        fit_store(store32, out, FitSettings(chunk=CHUNK), pyramid=False, progress=False)
    _, got = read_btf(out)
    _, ref = read_btf(ref_dir)
    for name in ref[0]:
        np.testing.assert_array_equal(got[0][name], ref[0][name], err_msg=name)


def _small_capture(root: Path, fmt: str) -> Path:
    """A 4 x 5 capture of 3 lights x 2 exposures with random codes (written by hand, not by synth)."""
    rng = np.random.default_rng(0)
    (root / "images").mkdir(parents=True)

    def image(name):
        codes = rng.uniform(0.1, 0.9, (4, 5, 3)).astype(np.float32)
        write_exr(root / name, codes) if fmt == "exr" else write_png(root / name, codes, srgb=False)
        return name

    return write_capture(root, image, size=(4, 5), ext=fmt, lights=3, exposures_s=[0.1, 1.0], angle_step=(10.0, 30.0))


def test_truncated_png_found_in_the_pass_leaves_no_store(tmp_path):
    cap = _small_capture(tmp_path / "cap", "png")
    data = (cap / "images/l2_e1.png").read_bytes()
    (cap / "images/l2_e1.png").write_bytes(data[:60])  # header intact, pixels cut
    load_capture(cap, headers_only=True)  # the header check passes: the pass must find it
    with pytest.raises(CaptureError) as info:
        ingest_capture(cap, tmp_path / "store", light_block=1, progress=False)
    assert info.value.problems == [f"{cap / 'images/l2_e1.png'}: " + info.value.problems[0].split(": ", 1)[1]]
    assert "not a readable image" in info.value.problems[0]
    assert not (tmp_path / "store").exists()


def test_nan_in_exr_found_in_the_pass_leaves_no_store(tmp_path):
    cap = _small_capture(tmp_path / "cap", "exr")
    bad = np.full((4, 5, 3), 0.5, np.float32)
    bad[1, 1, 0] = np.nan
    write_foreign_exr(cap / "images/l1_e0.exr", bad)
    bad[2, 2, 2] = np.inf
    write_foreign_exr(cap / "images/l1_e1.exr", bad)
    with pytest.raises(CaptureError) as info:
        ingest_capture(cap, tmp_path / "store", light_block=2, progress=False)
    assert info.value.problems == [f"{cap / 'images/l1_e0.exr'}: 1 non-finite values (NaN)",
                                   f"{cap / 'images/l1_e1.exr'}: 2 non-finite values (NaN, Inf)"]
    assert not (tmp_path / "store").exists()


def test_header_problem_writes_nothing(tmp_path):
    cap = _small_capture(tmp_path / "cap", "png")
    (cap / "images/l0_e0.png").unlink()
    with pytest.raises(CaptureError) as info:
        ingest_capture(cap, tmp_path / "store", progress=False)
    assert info.value.problems == [f"{cap / 'images/l0_e0.png'}: missing image"]
    assert not (tmp_path / "store").exists()


def test_refuses_to_overwrite_a_foreign_directory(tmp_path):
    cap = _small_capture(tmp_path / "cap", "png")
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    with pytest.raises(InputError, match="not an observation store"):
        ingest_capture(cap, tmp_path / "mine", progress=False)
    assert (tmp_path / "mine" / "notes.txt").read_text() == "keep"


def test_light_block_from_the_memory_budget():
    # 1024 x 1024, 2 exposures: (36 * 2 + 40) bytes per texel and light -> 112 MiB per light
    assert light_block_for((1024, 1024), 2, 1.0) == 9
    assert light_block_for((1024, 1024), 6, 0.1) == 1  # never below one light
    assert light_block_for((8, 8), 6, 1.0) == 2**30 // (64 * 256)

"""The fit of a store as Dask tasks: a LocalCluster of 2 worker processes gives the maps of one
process bit for bit, and a worker killed (SIGKILL) mid-run does not fail the fit."""

import json
import os
import signal
import threading
import time

import jax
import numpy as np
import pytest

distributed = pytest.importorskip("distributed")

from fitting import FitSettings, fit_store, ingest_capture, open_store, synth_capture  # noqa: E402
from fitting.fit import fit_store_maps  # noqa: E402
from jaxrender.io import InputError, read_btf, write_png  # noqa: E402

DASK_UNCONVERGED_MAX = 12
CHUNK = 8  # the 55 texels of the mask (8 x 8 texels): 7 tiles, 7 tasks


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("dask")
    capture = synth_capture(root / "capture", key=jax.random.key(11), size=(8, 8), lights=40, progress=False)
    _add_mask_and_intensities(capture)
    store = ingest_capture(capture, root / "store", dtype="float32", tile=CHUNK, progress=False)
    # One persistent compilation cache for this process and the workers (they inherit the
    # environment): the tile program is compiled once, here, and loaded by every worker.
    cache = str(root / "jax-cache")
    saved = {name: getattr(jax.config, name) for name in ("jax_compilation_cache_dir",
                                                       "jax_persistent_cache_min_compile_time_secs",
                                                       "jax_persistent_cache_min_entry_size_bytes")}
    jax.config.update("jax_compilation_cache_dir", cache)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    env = {"JAX_COMPILATION_CACHE_DIR": cache, "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
           "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": "0"}
    old_env = {name: os.environ.get(name) for name in env}
    os.environ.update(env)
    try:
        with jax.enable_x64(False):  # float32 observations, as `fitting fit` runs
            fit_store(store, root / "btf_one", FitSettings(chunk=CHUNK), pyramid=False, progress=False)
    finally:
        for name, value in saved.items():
            jax.config.update(name, value)
    _, ref = read_btf(root / "btf_one")
    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
    client = distributed.Client(cluster)
    yield root, store, ref[0], client
    client.close()
    cluster.close()
    for name, value in old_env.items():
        os.environ.pop(name) if value is None else os.environ.__setitem__(name, value)


MASK = np.ones((8, 8))
MASK[5:, :3] = 0  # 9 texels not fitted: tiles of the mask's texels, not of the image's


def _add_mask_and_intensities(capture):
    """The measured-capture extensions on the Dask path: a mask and per-light RGB intensities."""
    write_png(capture / "mask.png", MASK, srgb=False)
    manifest = json.loads((capture / "capture.json").read_text())
    manifest["mask"] = "mask.png"
    for i, light in enumerate(manifest["lights"]):
        light["intensity"] = [1.0 + 0.01 * i, 1.0, 0.9]
    (capture / "capture.json").write_text(json.dumps(manifest))


def test_mask_texels_are_not_fitted(setup):
    _, _, ref, _ = setup
    np.testing.assert_array_equal(ref["mask"], MASK)
    outside = MASK == 0
    assert np.all(ref["n_valid"][outside] == 0) and np.all(ref["rho_d.R"][outside] == 0)
    assert np.all(ref["n_valid"][~outside] > 0) and np.all(ref["converged"][outside] == 0)
    # the default (robust) method's three solves per texel, this bright capture brought down to the
    # reference level (its damping start then weighs more): 46 of the 55 texels converged within
    # max_steps when measured (54 when it was fitted at its own level); up to DASK_UNCONVERGED_MAX
    # may miss the tolerance
    assert np.sum(ref["converged"][~outside] == 1) >= np.sum(~outside) - DASK_UNCONVERGED_MAX


def _assert_same(btf_dir, ref):
    _, got = read_btf(btf_dir)
    for name in ref:
        np.testing.assert_array_equal(got[0][name], ref[name], err_msg=name)


def test_two_workers_give_the_single_process_maps(setup):
    root, store, ref, client = setup
    fit_store(store, root / "btf_two", FitSettings(chunk=CHUNK), pyramid=False, progress=False, scheduler=client)
    manifest, _ = read_btf(root / "btf_two")
    assert manifest["scheduler"].startswith("dask client")
    _assert_same(root / "btf_two", ref)


def test_a_killed_worker_does_not_fail_the_fit(setup):
    root, store, ref, client = setup
    out = root / "btf_killed"
    pids = client.run(os.getpid)  # worker address -> pid
    victim = sorted(pids.values())[0]
    errors = []

    def run():
        try:
            fit_store(store, out, FitSettings(chunk=CHUNK), pyramid=False, progress=False, scheduler=client)
        except BaseException as error:  # reported below
            errors.append(error)

    thread = threading.Thread(target=run)
    thread.start()
    deadline = time.monotonic() + 300
    while not list((out / ".partial").glob("chunk_*.npz")) and time.monotonic() < deadline and thread.is_alive():
        time.sleep(0.01)
    assert len(list((out / ".partial").glob("chunk_*.npz"))) < 7, "the fit finished before the kill"
    os.kill(victim, signal.SIGKILL)
    thread.join(600)
    assert not thread.is_alive() and not errors, errors
    assert victim not in client.run(os.getpid).values()  # that worker is gone (the nanny started another)
    _assert_same(out, ref)


def test_rerun_on_the_cluster_resumes_from_the_tiles_written(setup):
    """The whole cluster died after 3 tiles (here: a local run stopped after 3): a rerun on the
    cluster submits only the other 5 and the maps are the same."""
    root, store_dir, ref, client = setup
    out = root / "btf_resumed"

    def stop(i):
        if i == 2:
            raise InputError(None, "stopped")

    with jax.enable_x64(False), pytest.raises(InputError):
        fit_store_maps(open_store(store_dir), FitSettings(chunk=CHUNK), partial_dir=out / ".partial", progress=False,
                       on_chunk=stop)
    before = {p.name: p.stat().st_mtime_ns for p in (out / ".partial").glob("chunk_*.npz")}
    assert len(before) == 3
    fitted = []
    fit_store_maps(open_store(store_dir), FitSettings(chunk=CHUNK), partial_dir=out / ".partial", progress=False,
                   scheduler=client, on_chunk=fitted.append)
    n_tiles = -(-int(MASK.sum()) // CHUNK)  # tiles of the mask's 55 texels
    assert sorted(fitted) == sorted(set(range(n_tiles)) - {int(name[6:12]) for name in before})
    assert all((out / ".partial" / name).stat().st_mtime_ns == t for name, t in before.items())
    fit_store(store_dir, out, FitSettings(chunk=CHUNK), pyramid=False, progress=False, scheduler=client)
    _assert_same(out, ref)

"""Synthetic captures: light directions, stratified subsets, the woven maps, the simulated camera,
and the written capture directory (it validates, and merges to the model's reflectance)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fitting import (
    LIGHT_DIRECTIONS,
    Sensor,
    load_capture,
    merge_capture,
    paper_light_angles,
    stratified_light_subset,
    synth_capture,
    synth_maps,
    synth_observations,
)
from fitting.synth import EXPOSURES_S, synth_codes
from jaxrender.brdf import reflectance
from jaxrender.io import read_btf, read_image

SIZE = (12, 12)  # thread width 3: four threads each way
N_LIGHTS = 24
KEY = jax.random.PRNGKey(7)

EXACT_TOL = 1e-9  # noise-free float codes, float64: the white board cancels gain and falloff exactly
DISK_TOL = 2e-5  # disk (float32 codes, float32 merge) vs in memory (float64): float32 rounding
NOISY_MEDIAN_TOL = 0.03  # 8-bit, shot noise of a 20000 e- well: ~1.3% at a code of 0.3, plus the board's ~1%


_one_light = jax.jit(reflectance)  # one compilation for every light of the loop below


def truth_reflectance_loop(texels, dirs):
    """R of every texel under each light, one light at a time (reference for the vmapped renderer)."""
    out = []
    view = jnp.broadcast_to(jnp.asarray([0.0, 0.0, 1.0]), texels.rho_d.shape)
    for d in np.asarray(dirs):
        out.append(_one_light(texels, jnp.broadcast_to(jnp.asarray(d), texels.rho_d.shape), view))
    return np.stack([np.asarray(r) for r in out], axis=2)  # H W L 3


def test_paper_light_directions():
    angles = paper_light_angles()
    assert angles.shape == (2160, 2) and LIGHT_DIRECTIONS.shape == (2160, 3)
    assert set(angles[:, 0]) == set(range(0, 90, 3)) and set(angles[:, 1]) == set(range(0, 360, 5))
    np.testing.assert_allclose(np.linalg.norm(LIGHT_DIRECTIONS, axis=1), 1.0, rtol=1e-15)
    i = np.flatnonzero((angles[:, 0] == 87) & (angles[:, 1] == 355))[0]
    t, p = np.radians(87), np.radians(355)
    np.testing.assert_allclose(LIGHT_DIRECTIONS[i], [np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


@pytest.mark.parametrize("n", [5, 300, 2000])
def test_stratified_subset(n):
    ids = stratified_light_subset(jax.random.PRNGKey(1), n)
    assert len(ids) == n and len(np.unique(ids)) == n and np.all(np.diff(ids) > 0)
    np.testing.assert_array_equal(ids, stratified_light_subset(jax.random.PRNGKey(1), n))
    assert not np.array_equal(ids, stratified_light_subset(jax.random.PRNGKey(2), n))
    counts = np.bincount(ids // 72, minlength=30)
    assert counts.max() <= 72
    if n == 300:  # jittered systematic sampling: each ring within two of its solid-angle share
        # (the strata wholly inside a ring's interval count exactly; one partial stratum at each end)
        theta = np.radians(np.arange(0, 90, 3))
        edges = np.clip(np.concatenate([theta - np.radians(1.5), [theta[-1] + np.radians(1.5)]]), 0, np.pi / 2)
        share = np.cos(edges[:-1]) - np.cos(edges[1:])
        assert np.all(np.abs(counts - n * share / share.sum()) < 2)
    if n == 5:  # a small subset spreads over elevations (two may share a ring at a stratum edge)
        rings = ids // 72
        assert len(np.unique(rings)) >= 4 and rings.max() - rings.min() >= 10


def test_woven_maps():
    texels = synth_maps(KEY, SIZE)
    assert texels.rho_d.shape == SIZE + (3,) and texels.lobe0.sigma_x.shape == SIZE
    leaves = jax.tree_util.tree_leaves(texels)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in leaves)
    n = np.asarray(texels.lobe0.normal)
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, rtol=1e-12)
    assert np.all(n[..., 2] > 0.8) and np.abs(n[..., :2]).max() > 0.2  # tilted, upper hemisphere
    sx, sy = np.asarray(texels.lobe0.sigma_x), np.asarray(texels.lobe0.sigma_y)
    warp = sx > sy  # threads along y: broad across (x), narrow along
    assert 0.2 < warp.mean() < 0.8  # both thread directions, anisotropy axes swapped
    # Across-thread tilt is the steeper one: warp tilts in x, weft in y.
    assert np.abs(n[warp, 0]).mean() > np.abs(n[warp, 1]).mean()
    assert np.abs(n[~warp, 1]).mean() > np.abs(n[~warp, 0]).mean()
    gold = np.asarray(texels.lobe0.rho_s)[..., 0] > 1.0  # gold-like: strong, yellow specular
    rho_s = np.asarray(texels.lobe0.rho_s)
    assert gold.any() and (~gold).any() and np.all(rho_s[gold, 0] > 2 * rho_s[gold, 2])
    np.testing.assert_array_equal(np.asarray(synth_maps(KEY, SIZE).rho_d), np.asarray(texels.rho_d))
    assert not np.array_equal(np.asarray(synth_maps(jax.random.PRNGKey(8), SIZE).rho_d), np.asarray(texels.rho_d))


def test_batching_does_not_change_the_codes():
    """Per-light noise depends on (key, light id) only: the lights in one batch equal the same
    lights in two batches (padded to the same shape: one compilation, shared with the capture
    fixture), and vmapping over lights equals the loop over lights."""
    texels = synth_maps(KEY, SIZE)
    dirs = jnp.asarray(LIGHT_DIRECTIONS[stratified_light_subset(KEY, N_LIGHTS)])
    args = (jnp.asarray([0.0, 0.0, 1.0]), jnp.asarray(EXPOSURES_S))
    sensor = Sensor(bits=16)
    whole = synth_codes(KEY, texels, dirs, jnp.arange(N_LIGHTS), *args, sensor=sensor)
    assert whole.shape == (N_LIGHTS, 6) + SIZE + (3,)
    half = N_LIGHTS // 2
    for first in (0, half):
        order = jnp.concatenate([jnp.arange(first, first + half), jnp.zeros(N_LIGHTS - half, int)])
        part = synth_codes(KEY, texels, dirs[order], order, *args, sensor=sensor)
        np.testing.assert_array_equal(np.asarray(part[:half]), np.asarray(whole[first:first + half]))
    # Noise-free float codes = the model's R (loop over lights) * gain * t * falloff.
    clean = synth_codes(KEY, texels, dirs, jnp.arange(N_LIGHTS), *args, sensor=Sensor(noise=0.0, bits=0))
    truth = truth_reflectance_loop(texels, np.asarray(dirs))  # H W L 3
    t = np.asarray(EXPOSURES_S).reshape(1, -1, 1, 1, 1)
    yy, xx = np.meshgrid((np.arange(SIZE[0]) + 0.5) / SIZE[0] * 2 - 1, (np.arange(SIZE[1]) + 0.5) / SIZE[1] * 2 - 1,
                         indexing="ij")
    falloff = (1 - 0.25 * (yy**2 + xx**2) / 2)[None, None, :, :, None]
    expected = np.clip(np.moveaxis(truth, 2, 0)[:, None] * 62.5 * t * falloff, 0, 1)
    np.testing.assert_allclose(np.asarray(clean), expected, rtol=1e-12, atol=1e-15)


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "capture"
    synth_capture(out, key=KEY, size=SIZE, lights=N_LIGHTS, bits=16, progress=False)
    return out


def test_written_capture_validates_and_merges_like_memory(capture_dir):
    capture = load_capture(capture_dir)
    assert capture.size == SIZE and capture.n_lights == N_LIGHTS and capture.exposures_s == EXPOSURES_S
    # 16-bit codes survive the PNG round trip exactly.
    codes = read_image(capture.light_images[3][2], srgb=False)
    np.testing.assert_array_equal(np.round(codes * 65535), codes * 65535)
    obs = merge_capture(capture, progress=False)
    meta, levels = read_btf(capture_dir / "truth")
    ids = np.asarray(meta["light_indices"])
    np.testing.assert_allclose(capture.light_dirs, LIGHT_DIRECTIONS[ids], atol=1e-15)
    k_maps, k_lights, _ = jax.random.split(KEY, 3)
    texels = synth_maps(k_maps, SIZE)
    np.testing.assert_allclose(levels[0]["sigma_x"], np.asarray(texels.lobe0.sigma_x), rtol=1e-6)
    memory = synth_observations(k_lights, texels, LIGHT_DIRECTIONS[ids], sensor=Sensor(bits=16))
    np.testing.assert_array_equal(np.asarray(obs.weight), np.asarray(memory.weight))
    np.testing.assert_allclose(np.asarray(obs.ratio), np.asarray(memory.ratio), rtol=DISK_TOL, atol=1e-7)
    np.testing.assert_array_equal(levels[0]["n_valid"], np.asarray(obs.n_valid))
    assert obs.n_valid.min() >= N_LIGHTS // 2  # most observations are usable


def test_observations_match_the_model():
    k_maps, k_obs = jax.random.split(KEY)
    texels = synth_maps(k_maps, SIZE)
    dirs = LIGHT_DIRECTIONS[stratified_light_subset(KEY, N_LIGHTS)]
    truth = truth_reflectance_loop(texels, dirs)
    # Noise-free float codes (EXR-like): exact up to float64 rounding; vignetting cancelled.
    exact = synth_observations(k_obs, texels, dirs, sensor=Sensor(noise=0.0, bits=0))
    valid = np.asarray(exact.weight) > 0
    assert valid.mean() > 0.9
    np.testing.assert_allclose(np.asarray(exact.ratio)[valid], truth[valid], rtol=EXACT_TOL, atol=1e-12)
    # Flagged observations are those the model makes (nearly) black in some channel.
    assert np.all(truth[~valid].min(axis=-1) < 2 / 255 / 62.5 / 0.75 * 1.05)

    def median_rel_err(sensor):
        obs = synth_observations(k_obs, texels, dirs, sensor=sensor)
        ok = np.asarray(obs.weight) > 0
        return np.median(np.abs(np.asarray(obs.ratio)[ok] - truth[ok]) / truth[ok])

    noisy8 = median_rel_err(Sensor(bits=8))
    clean8 = median_rel_err(Sensor(bits=8, noise=0.0))
    clean16 = median_rel_err(Sensor(bits=16, noise=0.0))
    assert noisy8 < NOISY_MEDIAN_TOL
    assert clean16 < clean8 / 50  # 256x finer steps; /50 leaves room for the hat weights
    assert clean8 < noisy8


def test_cli_synth_bad_input_exit_2_and_no_output(tmp_path, capsys, monkeypatch):
    from jaxrender.app.cli.programs import fitting_main
    from jaxrender.io import write_png

    occupied = tmp_path / "occupied"
    occupied.mkdir()
    (occupied / "notes.txt").write_text("keep me")
    args = ["--size", str(SIZE[0]), str(SIZE[1]), "--lights", str(N_LIGHTS)]
    assert fitting_main(["synth", str(occupied), *args]) == 0   # an existing folder is used, its files kept
    assert sorted(p.name for p in occupied.iterdir()) == ["capture.json", "images", "notes.txt", "truth"]
    assert (occupied / "notes.txt").read_text() == "keep me" and load_capture(occupied).n_lights == N_LIGHTS
    capsys.readouterr()
    assert fitting_main(["synth", str(tmp_path / "new"), "--lights", "0"]) == 2   # argparse: one line, exit 2
    assert capsys.readouterr().err.count("\n") == 1 and not (tmp_path / "new").exists()

    # A failure half-way leaves nothing behind (everything goes through a temporary directory).
    import fitting.synth

    calls = []

    def failing_png(path, image, **kwargs):
        calls.append(path)
        if len(calls) > 8:  # after the white board and the first light
            raise OSError("disk full")
        return write_png(path, image, **kwargs)

    monkeypatch.setattr(fitting.synth, "write_png", failing_png)
    assert fitting_main(["synth", str(tmp_path / "half"), *args]) == 3  # a machine fault: one line, exit 3
    assert len(calls) > 8 and list(tmp_path.iterdir()) == [occupied]


def test_cli_exr_capture_and_srgb_response(tmp_path):
    """`fitting synth --format exr` writes linear float codes that merge like the in-memory
    float camera; an sRGB-encoded 8-bit camera merges to the model like the linear one."""
    from jaxrender.app.cli.programs import fitting_main

    out = tmp_path / "exr"
    assert fitting_main(["synth", str(out), "--size", str(SIZE[0]), str(SIZE[1]), "--lights", str(N_LIGHTS),
                         "--format", "exr", "--seed", "3"]) == 0
    capture = load_capture(out)
    assert all(p.suffix == ".exr" for images in capture.light_images for p in images)
    obs = merge_capture(capture, progress=False)
    k_maps, k_lights, k_sel = jax.random.split(jax.random.PRNGKey(3), 3)
    texels = synth_maps(k_maps, SIZE)
    dirs = LIGHT_DIRECTIONS[stratified_light_subset(k_sel, N_LIGHTS)]
    memory = synth_observations(k_lights, texels, dirs, sensor=Sensor(bits=0))
    np.testing.assert_array_equal(np.asarray(obs.weight), np.asarray(memory.weight))
    np.testing.assert_allclose(np.asarray(obs.ratio), np.asarray(memory.ratio), rtol=DISK_TOL, atol=1e-7)

    truth = truth_reflectance_loop(texels, dirs)
    srgb = synth_observations(k_lights, texels, dirs, sensor=Sensor(bits=8, response="srgb", noise=0.0))
    ok = np.asarray(srgb.weight) > 0
    assert ok.mean() > 0.9
    rel = np.abs(np.asarray(srgb.ratio)[ok] - truth[ok]) / truth[ok]
    # Half an 8-bit sRGB step is 1.2 / 255 / (c + 0.055) of the linear value: 0.85% at c = 0.5,
    # less for the brighter codes the bracket mostly uses; the median error stays below 1%.
    assert np.median(rel) < 0.01

"""The EM multi-resolution pyramid (fitting.pyramid): the coarse texel renders like the average of
its 4 children where the children have two distinct specular directions (far better than the
ordinary mip and than a one-lobe moment-matched level), and `build_pyramid` / `fitting pyramid`
write every channel of every level with btf.json last."""

import json
import logging
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from fitting.em import (
    _chunk_size,
    compile_ahead,
    em_downsample,
    em_texels,
    gather_children,
    mip_texel,
    moment_matched_texels,
)
from fitting.pyramid import build_pyramid, pyramid_levels
from jaxrender import brdf
from jaxrender.app.cli.programs import fitting_main
from jaxrender.brdf import BTFTexel, reflectance
from jaxrender.io import LOBE_CHANNELS, read_btf, write_btf

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from _em_numpy import em_texels_numpy, gather_children_numpy  # noqa: E402

# The numpy peer of the speed benchmark runs the same arithmetic in float32 in another order; the EM
# amplifies rounding a little through its |change of log-likelihood| < 1e-5 stop (measured: 2.3e-6
# on normals, < 1e-6 elsewhere, on the levels below).
PEER_RTOL = 2e-5
# The target: the two-lobe EM level's rendering error is at most a third of the mip's.
EM_VS_MIP_RATIO = 1 / 3
N_TEXELS = 8
N_PAIRS = 4000


def _direction(tilt, azimuth):
    return np.stack([np.sin(tilt) * np.cos(azimuth), np.sin(tilt) * np.sin(azimuth), np.cos(tilt)], -1)


def two_direction_children(key, n=N_TEXELS):
    """`n` coarse texels; each has children split 2+2 or 3+1 between two specular directions at
    least 25 degrees apart, with random widths (slopes 0.04-0.2) and colours, each child jittered
    around its direction's parameters."""
    rng = np.random.default_rng(int(jax.random.randint(key, (), 0, 2**31 - 1)))
    tilt_a, az_a = rng.uniform(np.radians(10), np.radians(30), n), rng.uniform(0, 2 * np.pi, n)
    tilt_b = rng.uniform(np.radians(10), np.radians(30), n)
    az_b = az_a + rng.choice([-1, 1], n) * rng.uniform(np.radians(100), np.radians(180), n)
    which = np.array([[0, 1, 0, 1], [0, 0, 0, 1], [1, 0, 1, 1], [0, 1, 1, 0]])[np.arange(n) % 4]  # n 4
    pick = lambda a: np.take_along_axis(a, which.reshape(which.shape + (1,) * (a.ndim - 2)), axis=1)  # noqa: E731
    # Each child jitters around its direction: 2 degrees of tilt, 5 of azimuth, 15 % in sigma and rho_s.
    tilt = pick(np.stack([tilt_a, tilt_b], 1)) + rng.normal(0, np.radians(2), (n, 4))
    azimuth = pick(np.stack([az_a, az_b], 1)) + rng.normal(0, np.radians(5), (n, 4))
    normal = _direction(tilt, azimuth)
    jitter = lambda shape: rng.uniform(0.85, 1.15, shape)  # noqa: E731
    sx = pick(rng.uniform(0.04, 0.2, (n, 2))) * jitter((n, 4))
    sy = pick(rng.uniform(0.04, 0.2, (n, 2))) * jitter((n, 4))
    rho_s = pick(rng.uniform(0.2, 1.0, (n, 2, 3))) * jitter((n, 4, 1))
    rho_d = rng.uniform(0.02, 0.3, (n, 4, 3))
    return BTFTexel.single(jnp.asarray(rho_d), jnp.asarray(rho_s), jnp.asarray(normal), jnp.asarray(sx),
                           jnp.asarray(sy))


def light_view_pairs(key, n=N_PAIRS, *, max_theta_deg=60.0, cone_deg=40.0):
    """Light/view pairs concentrated where the specular lobes are: the half vector uniform in a
    cone around z, the view uniform in the cone of `max_theta_deg`, the light its mirror about h; pairs with
    light or view beyond `max_theta_deg` from z are dropped (the 1/cos_r of eq. 1 near a tilted
    lobe's horizon would otherwise dominate every norm)."""
    u = np.asarray(jax.random.uniform(key, (n, 4), dtype=jnp.float64))
    ct = 1 - u[:, 0] * (1 - np.cos(np.radians(cone_deg)))
    h = _direction(np.arccos(ct), 2 * np.pi * u[:, 1])
    cos_max = np.cos(np.radians(max_theta_deg))
    wo = _direction(np.arccos(1 - u[:, 2] * (1 - cos_max)), 2 * np.pi * u[:, 3])
    wi = 2 * np.sum(wo * h, -1, keepdims=True) * h - wo
    keep = (wi[:, 2] > cos_max) & (wo[:, 2] > cos_max)
    return jnp.asarray(wi[keep]), jnp.asarray(wo[keep])


@jax.jit
def _render(texels: BTFTexel, wi, wo):
    """R of every texel (leading axis) at every pair: texels x pairs x 3."""
    def one(texel):
        b = jax.tree.map(lambda a: jnp.broadcast_to(a, (wi.shape[0],) + a.shape), texel)
        return reflectance(b, wi, wo)
    return jax.vmap(one)(texels)


def rendering_errors(children: BTFTexel, wi, wo) -> dict[str, float]:
    """Relative RMS (over texels, pairs and channels) of each coarse method vs the children's average."""
    reference = sum(_render(jax.tree.map(lambda a: a[:, c], children), wi, wo) for c in range(4)) / 4
    coarse = {"em": em_texels(children)[0], "moment": moment_matched_texels(children),
              "mip": jax.vmap(mip_texel)(children)}
    return {name: float(jnp.linalg.norm(_render(texel, wi, wo) - reference) / jnp.linalg.norm(reference))
            for name, texel in coarse.items()}


def test_two_lobe_level_renders_like_its_children():
    k1, k2 = jax.random.split(jax.random.PRNGKey(7))
    children = two_direction_children(k1)
    wi, wo = light_view_pairs(k2)
    assert wi.shape[0] > 1000  # enough pairs survive the angle cut to make the norms meaningful
    err = rendering_errors(children, wi, wo)
    assert err["em"] <= EM_VS_MIP_RATIO * err["mip"], err
    assert err["em"] < err["moment"], err


def test_two_lobe_texel_shades_its_diffuse_term_with_the_weighted_normal():
    """jaxrender.brdf (changed for the pyramid): rho_d cos_i of a two-lobe texel is taken to
    normalize((1 - w) N0 + w N1), the children's mean normal, not to lobe 0's normal alone."""
    n0, n1, w = _direction(0.4, 0.0), _direction(0.3, 2.5), 0.3
    lobe = lambda n: brdf.Lobe(jnp.zeros(3), jnp.asarray(n), jnp.asarray(0.1), jnp.asarray(0.1))  # noqa: E731
    texel = BTFTexel(jnp.array([0.2, 0.4, 0.6]), lobe(n0), lobe(n1), jnp.asarray(w))
    wi, wo = _direction(0.5, 1.0), _direction(0.2, 4.0)
    nd = (1 - w) * n0 + w * n1
    expected = np.array([0.2, 0.4, 0.6]) * max(wi @ nd / np.linalg.norm(nd), 0.0)
    np.testing.assert_allclose(jax.jit(reflectance)(texel, jnp.asarray(wi), jnp.asarray(wo)), expected, rtol=1e-12)


def _level0(size, key):
    """A level-0 channel dict with two specular directions in a checkerboard, plus fit statistics."""
    h, w = size
    rng = np.random.default_rng(key)
    checker = ((np.arange(h)[:, None] + np.arange(w)[None, :]) % 2).astype(np.float32)
    tilt = np.radians(20) * (2 * checker - 1) + rng.normal(0, 0.02, size)
    ch = {"normal.X": np.sin(tilt), "normal.Y": np.zeros(size), "normal.Z": np.cos(tilt),
          "sigma_x": rng.uniform(0.05, 0.2, size), "sigma_y": rng.uniform(0.05, 0.2, size)}
    for c in "RGB":
        ch[f"rho_d.{c}"] = rng.uniform(0, 0.5, size)
        ch[f"rho_s.{c}"] = rng.uniform(0, 1, size)
    ch.update(residual=rng.uniform(0, 0.01, size), converged=np.ones(size), n_valid=np.full(size, 90.0),
              n_saturated=np.zeros(size), n_dark=np.zeros(size))
    return {k: np.asarray(v, np.float32) for k, v in ch.items()}


def test_gather_children_pads_odd_sizes_like_downsample2():
    level = BTFTexel.from_channels(_level0((5, 3), 1))
    children = gather_children(level)
    assert children.weight.shape == (3, 2, 4)
    sx = np.asarray(level.lobe0.sigma_x)
    padded = np.pad(sx, ((0, 1), (0, 1)), mode="edge")
    for i in range(3):
        for j in range(2):
            block = [padded[2 * i, 2 * j], padded[2 * i + 1, 2 * j],
                     padded[2 * i, 2 * j + 1], padded[2 * i + 1, 2 * j + 1]]
            np.testing.assert_array_equal(children.lobe0.sigma_x[i, j], block)


def test_em_downsample_equals_em_texels_on_the_gathered_children():
    """The level path (split into padded structure-of-arrays chunks, merged back) gives each
    texel exactly what the batch kernel gives its gathered children: odd sizes, several chunks
    with a padded last one, one-lobe children (level 0) and two-lobe children (level 1)."""
    level0 = BTFTexel.from_channels(_level0((13, 11), 3))
    level1, _ = em_downsample(level0, chunk=16)            # 7x6 = 42 texels: chunks of 16, the last padded
    assert level1.weight.shape == (7, 6) and bool(jnp.any(level1.weight > 0))
    for level, coarse, one_lobe in ((level0, level1, True), (level1, em_downsample(level1, chunk=16)[0], False)):
        children = gather_children(level)
        hh, ww = children.weight.shape[:2]
        flat = jax.tree.map(lambda a: a.reshape((hh * ww,) + a.shape[2:]), children)
        expected, _ = em_texels(flat, one_lobe_children=one_lobe)
        for a, b in zip(jax.tree.leaves(coarse), jax.tree.leaves(expected)):
            np.testing.assert_array_equal(np.asarray(a).reshape(b.shape), np.asarray(b))


def _fields(texel: BTFTexel) -> dict:
    """A BTFTexel as the numpy peer's dict of fields."""
    lobe = lambda k: {f: getattr(getattr(texel, k), f) for f in ("rho_s", "normal", "sigma_x", "sigma_y")}  # noqa: E731
    return {"rho_d": texel.rho_d, "weight": texel.weight, "lobe0": lobe("lobe0"), "lobe1": lobe("lobe1")}


def test_numpy_peer_computes_the_same_levels():
    """benchmarks/_em_numpy.py (the speed benchmark's peer, independent numpy code) gives each
    coarse texel what `em_downsample` gives: one-lobe children (level 0 -> 1, the kernel without
    lobe 1) and two-lobe children (level 1 -> 2, EM in 98-100 % of texels), the same one-or-two-lobe
    decisions, every field within PEER_RTOL (relative, 1e-3 floor for components near 0)."""
    level0 = BTFTexel.from_channels(_level0((13, 11), 3))
    level1, _ = em_downsample(level0, chunk=16)
    level2, _ = em_downsample(level1, chunk=16)
    for fine, coarse in ((level0, level1), (level1, level2)):
        ref = em_texels_numpy(gather_children_numpy(jax.tree.map(np.asarray, _fields(fine))))
        got = jax.tree.map(lambda a: np.asarray(a).reshape((-1,) + a.shape[2:]), _fields(coarse))
        np.testing.assert_array_equal(got["weight"] > 0, ref["weight"] > 0)
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves({k: ref[k] for k in got})):
            np.testing.assert_array_less(np.abs(a - b) / np.maximum(np.abs(b), 1e-3), PEER_RTOL)


def test_chunk_size_counts_the_fixed_cost_of_a_kernel_call():
    # one call where it pays (64 texels: one padded chunk of 256, not four of 16), several where
    # the padding would cost more than the calls; never above `chunk`
    assert [_chunk_size(n, 4096) for n in (1, 16, 64, 256, 1024, 4096, 16384)] == [16, 16, 256, 256, 256, 4096, 4096]
    assert _chunk_size(42, 16) == 16 and _chunk_size(5000, 256) == 256


def test_em_downsample_chunk_sizes_agree_to_rounding():
    """64x64 = 4096 texels as one chunk (two 2048-texel blocks computed side by side) or as
    sixteen 256-texel chunks: the same level up to float32 rounding (XLA vectorizes each shape
    its own way), with the same one-or-two-lobe decisions."""
    level0 = BTFTexel.from_channels(_level0((128, 128), 5))
    whole, _ = em_downsample(level0)
    parts, _ = em_downsample(level0, chunk=256)
    np.testing.assert_array_equal(np.asarray(whole.weight) > 0, np.asarray(parts.weight) > 0)
    for a, b in zip(jax.tree.leaves(whole), jax.tree.leaves(parts)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=2e-6)


def test_compile_ahead_compiles_what_a_fixed_level_calls(caplog):
    """After `compile_ahead`, downsampling a one-lobe level and a two-lobe level with `fixed=True`
    compiles no EM kernel (JAX logs every compilation it starts, persistent-cache hits included)
    and gives the levels a plain call gives; a setting not compiled ahead (other iterations) does
    compile one. Iterations no other test uses: no kernel of them is in memory beforehand."""
    level0 = BTFTexel.from_channels(_level0((13, 11), 7))
    ahead = dict(chunk=16, iterations=11)
    compile_ahead(**ahead, dtype=level0.weight.dtype).join()   # else its own compilations count

    def kernels_compiled(fn):
        caplog.clear()
        with caplog.at_level(logging.WARNING), jax.log_compiles(True):
            out = fn()
        return out, sum("Compiling jit(_em_blocks)" in r.getMessage() for r in caplog.records)

    (level1, _), one = kernels_compiled(lambda: em_downsample(level0, **ahead, fixed=True))
    (level2, _), two = kernels_compiled(lambda: em_downsample(level1, **ahead, fixed=True))
    _, other = kernels_compiled(lambda: em_downsample(level0, chunk=16, fixed=True, iterations=7))
    assert bool(jnp.any(level1.weight > 0)), "level 1 has two-lobe texels: level 2 needs the two-lobe kernel"
    assert (one, two, other) == (0, 0, 1)
    for got, plain in ((level1, em_downsample(level0, **ahead)[0]), (level2, em_downsample(level1, **ahead)[0])):
        for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(plain)):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_build_pyramid_writes_every_channel_on_every_level_and_btf_json_last(tmp_path):
    btf_dir = tmp_path / "btf"
    level0 = _level0((5, 6), 0)
    write_btf(btf_dir, [level0], model="reciprocal")
    assert build_pyramid(btf_dir) == btf_dir
    manifest, levels = read_btf(btf_dir)
    assert [tuple(e["size"]) for e in manifest["levels"]] == [(5, 6), (3, 3), (2, 2), (1, 1)]
    assert manifest["pyramid"]["method"] == "em" and len(manifest["pyramid"]["levels"]) == 3
    json_time = (btf_dir / "btf.json").stat().st_mtime_ns
    for i, level in enumerate(levels):
        assert set(LOBE_CHANNELS) <= set(level)
        assert all(np.all(np.isfinite(v)) for v in level.values())
        assert (btf_dir / manifest["levels"][i]["file"]).stat().st_mtime_ns <= json_time
    np.testing.assert_array_equal(levels[0]["sigma_x"], level0["sigma_x"])  # level 0 untouched
    # The checkerboard of +-20 degree normals keeps two lobes on level 1 (each 2x2 block mixes both;
    # the weights follow the children's random rho_s sigma_x sigma_y energies).
    assert np.all(levels[1]["weight"][:2, :] > 0.1)
    # The files hold the in-memory pyramid (float32 round trip is exact).
    memory, _ = pyramid_levels(BTFTexel.from_channels(levels[0]))
    for texel, level in zip(memory, levels[1:]):
        for name, value in texel.to_channels().items():
            np.testing.assert_array_equal(np.asarray(value, np.float32), level[name])


def test_pyramid_cli_levels_and_bad_input(tmp_path, capsys):
    btf_dir = tmp_path / "btf"
    write_btf(btf_dir, [_level0((5, 6), 2)], model="paper")
    assert fitting_main(["pyramid", str(btf_dir)]) == 0
    assert fitting_main(["pyramid", str(btf_dir), "--levels", "2"]) == 0
    manifest = json.loads((btf_dir / "btf.json").read_text())
    assert [tuple(e["size"]) for e in manifest["levels"]] == [(5, 6), (3, 3)] and manifest["model"] == "paper"
    assert sorted(p.name for p in btf_dir.glob("level_*.exr")) == ["level_00.exr", "level_01.exr"]
    assert fitting_main(["pyramid", str(btf_dir), "--levels", "1"]) == 0  # level 0 only: no coarse level
    manifest = json.loads((btf_dir / "btf.json").read_text())
    assert [tuple(e["size"]) for e in manifest["levels"]] == [(5, 6)] and manifest["pyramid"]["levels"] == []
    assert sorted(p.name for p in btf_dir.glob("level_*.exr")) == ["level_00.exr"]
    capsys.readouterr()
    (btf_dir / "btf.json").unlink()  # an incomplete directory
    assert fitting_main(["pyramid", str(btf_dir)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "btf.json" in err
    assert not (btf_dir / "btf.json").exists()  # no partial output made to look complete
    assert fitting_main(["pyramid", str(tmp_path / "missing")]) == 2
    assert fitting_main(["pyramid", str(tmp_path), "--levels", "0"]) == 2

"""BTF directory I/O (design.md "BTF output"): round trip of every channel, btf.json last,
incomplete directories, level replacement for the pyramid, previews."""

import json
import math

import numpy as np
import pytest
import skimage.io

import jaxrender.io as jio
from jaxrender.brdf import BTFTexel
from jaxrender.io import LEVEL0_CHANNELS, LOBE_CHANNELS, InputError, read_btf, write_btf, write_btf_levels

# Names spelled out from design.md, independently of the module's constants.
DESIGN_LOBE = ["rho_d.R", "rho_d.G", "rho_d.B", "rho_s.R", "rho_s.G", "rho_s.B", "normal.X", "normal.Y", "normal.Z",
               "sigma_x", "sigma_y", "lobe1.rho_s.R", "lobe1.rho_s.G", "lobe1.rho_s.B", "lobe1.normal.X",
               "lobe1.normal.Y", "lobe1.normal.Z", "lobe1.sigma_x", "lobe1.sigma_y", "weight"]
DESIGN_STATS = ["residual", "converged", "n_valid", "n_saturated", "n_dark"]
ONE_LOBE = [c for c in DESIGN_LOBE if not c.startswith("lobe1.") and c != "weight"]


def _level(rng, shape, names):
    return {name: rng.uniform(0.01, 2.0, shape).astype(np.float32) for name in names}


def _pyramid(rng, size=(7, 5)):
    h, w = size
    level0 = _level(rng, (h, w), ONE_LOBE + DESIGN_STATS)
    level1 = _level(rng, (math.ceil(h / 2), math.ceil(w / 2)), DESIGN_LOBE)
    level2 = _level(rng, (math.ceil(h / 4), math.ceil(w / 4)), ONE_LOBE)
    return [level0, level1, level2]


def test_channel_names_match_design():
    """design.md's channels, plus `mask` on every level (docs/formats.md: fitted texels)."""
    assert list(LOBE_CHANNELS) == DESIGN_LOBE
    assert list(LEVEL0_CHANNELS) == DESIGN_LOBE + ["mask"] + DESIGN_STATS


def test_round_trip_every_channel_on_every_level(tmp_path):
    rng = np.random.default_rng(0)
    levels = _pyramid(rng)
    write_btf(tmp_path / "btf", levels, model="paper", meta={"solver": "test"})
    meta, back = read_btf(tmp_path / "btf")
    assert meta["format"] == "jaxrender-btf" and meta["version"] == 1 and meta["model"] == "paper"
    assert meta["solver"] == "test" and "units" in meta
    assert [e["file"] for e in meta["levels"]] == ["level_00.exr", "level_01.exr", "level_02.exr"]
    assert [e["size"] for e in meta["levels"]] == [[7, 5], [4, 3], [2, 2]]
    assert sorted(back[0]) == sorted(DESIGN_LOBE + DESIGN_STATS + ["mask"])  # mask: all 1 when not given
    for level in back[1:]:
        assert sorted(level) == sorted(DESIGN_LOBE + ["mask"])
    # float32 EXR channels: exact round trip.
    for original, loaded in zip(levels, back, strict=True):
        for name, value in original.items():
            np.testing.assert_array_equal(loaded[name], value)
    # One-lobe levels: lobe 1 is a copy of lobe 0 with weight 0 (design.md).
    for i in (0, 2):
        assert np.all(back[i]["weight"] == 0)
        for name in ("rho_s.G", "normal.Z", "sigma_y"):
            np.testing.assert_array_equal(back[i][f"lobe1.{name}"], levels[i][name])
    # Every channel is in the EXR file itself, not synthesised by the reader.
    assert sorted(jio.read_exr(tmp_path / "btf" / "level_02.exr")) == sorted(DESIGN_LOBE + ["mask"])
    # The channels feed the BRDF's texel type.
    texel = BTFTexel.from_channels(back[1])
    np.testing.assert_array_equal(np.asarray(texel.weight), levels[1]["weight"])


def test_btf_json_is_written_last_and_incomplete_dirs_are_errors(tmp_path, monkeypatch):
    rng = np.random.default_rng(1)
    levels = _pyramid(rng)
    out = tmp_path / "btf"
    write_btf(out, levels, model="reciprocal")
    manifest_time = (out / "btf.json").stat().st_mtime_ns
    assert all((out / f"level_0{i}.exr").stat().st_mtime_ns <= manifest_time for i in range(3))

    # A crash while rewriting: the old btf.json is gone first, so the directory reads as incomplete.
    import jaxrender.io._btf as btf_module

    calls = []

    def failing_write(path, image):
        calls.append(path)
        if len(calls) == 2:
            raise OSError("disk full")
        return jio.write_exr(path, image)

    monkeypatch.setattr(btf_module, "write_exr", failing_write)
    with pytest.raises(OSError):
        write_btf(out, levels, model="reciprocal")
    assert not (out / "btf.json").exists()
    with pytest.raises(InputError, match="btf.json.*incomplete"):
        read_btf(out)
    with pytest.raises(InputError, match="no such BTF directory"):
        read_btf(tmp_path / "nowhere")


def test_missing_channel_and_bad_manifest_name_the_file(tmp_path):
    rng = np.random.default_rng(2)
    out = tmp_path / "btf"
    write_btf(out, _pyramid(rng)[:1], model="reciprocal")
    channels = jio.read_exr(out / "level_00.exr")
    del channels["n_dark"]
    jio.write_exr(out / "level_00.exr", channels)
    with pytest.raises(InputError, match=r"level_00\.exr: missing channels n_dark"):
        read_btf(out)
    (out / "btf.json").write_text("{not json")
    with pytest.raises(InputError, match=r"btf\.json: not valid JSON"):
        read_btf(out)
    (out / "btf.json").write_text(json.dumps({"format": "jaxrender-btf", "version": 7}))
    with pytest.raises(InputError, match="unsupported BTF version 7"):
        read_btf(out)


def test_writer_rejects_bad_levels(tmp_path):
    rng = np.random.default_rng(3)
    levels = _pyramid(rng)
    with pytest.raises(ValueError, match="missing channels"):
        write_btf(tmp_path / "a", [{k: v for k, v in levels[0].items() if k != "residual"}], model="reciprocal")
    wrong = dict(levels[1], sigma_x=np.zeros((9, 9), np.float32))
    with pytest.raises(ValueError, match="one 2-D shape"):
        write_btf(tmp_path / "b", [levels[0], wrong], model="reciprocal")
    small = {k: v[:3] for k, v in levels[1].items()}  # 3 x 3 is not ceil-half of 7 x 5
    with pytest.raises(ValueError, match="ceil-half"):
        write_btf(tmp_path / "c", [levels[0], small], model="reciprocal")
    with pytest.raises(ValueError, match="unknown model"):
        write_btf(tmp_path / "d", levels, model="phong")
    assert not any((tmp_path / name).exists() for name in "abcd")


def test_write_btf_levels_replaces_the_pyramid(tmp_path):
    rng = np.random.default_rng(4)
    levels = _pyramid(rng)
    out = tmp_path / "btf"
    write_btf(out, levels, model="reciprocal", meta={"solver": "optimistix"})
    new1 = _level(rng, (4, 3), DESIGN_LOBE)
    write_btf_levels(out, [new1], start=1, meta={"em_iterations": 3})
    meta, back = read_btf(out)
    assert len(back) == 2 and not (out / "level_02.exr").exists()
    assert meta["solver"] == "optimistix" and meta["em_iterations"] == 3
    np.testing.assert_array_equal(back[1]["lobe1.sigma_x"], new1["lobe1.sigma_x"])
    np.testing.assert_array_equal(back[0]["residual"], levels[0]["residual"])
    with pytest.raises(ValueError, match="ceil-half"):
        write_btf_levels(out, [_level(rng, (3, 3), DESIGN_LOBE)], start=1)


def test_previews(tmp_path):
    rng = np.random.default_rng(5)
    level0 = _pyramid(rng, size=(6, 4))[0]
    n = rng.normal(size=(6, 4, 3))
    n[..., 2] = np.abs(n[..., 2]) + 0.5
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    for i, ax in enumerate("XYZ"):
        level0[f"normal.{ax}"] = n[..., i].astype(np.float32)
    level0["converged"] = (rng.uniform(size=(6, 4)) > 0.5).astype(np.float32)
    write_btf(tmp_path / "btf", [level0], model="reciprocal")
    paths = jio.write_btf_previews(tmp_path / "btf")
    names = {p.name for p in paths}
    assert {"rho_d.png", "rho_s.png", "normal.png", "sigma_x.png", "sigma_y.png", "residual.png",
            "converged.png", "n_valid.png"} <= names
    normal_png = skimage.io.imread(tmp_path / "btf" / "previews" / "normal.png")
    np.testing.assert_array_equal(normal_png, np.round((0.5 + 0.5 * n) * 255).astype(np.uint8))
    converged_png = skimage.io.imread(tmp_path / "btf" / "previews" / "converged.png")
    np.testing.assert_array_equal(converged_png, (level0["converged"] * 255).astype(np.uint8))

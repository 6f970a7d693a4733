"""Scene-file errors: one line naming the file and the field, exit code 2, no output written;
plus the loader's semantics (defaults, relative light maps) and one valid CLI render."""

import copy
import json
import re

import numpy as np
import pytest

from jaxrender.app.cli.programs import jaxrender_main as main
from jaxrender.app.scenes import ShaftsSceneWarning, load_shafts_scene, shafts_scene_from_dict
from jaxrender.io import InputError, read_image, write_png

_SCENE = {
    "camera": {"eye": [0, 1.5, 6], "target": [0, 1, 0], "up": [0, 1, 0], "fov_y_deg": 40, "width": 8, "height": 6},
    "medium": {"rho": 1.0, "kappa": 0.1, "K": 0.003},
    "render": {"shadow_map": 32, "s_min": 0.5, "s_max": 10, "t_max": 12},
    "spotlights": [{"position": [0, 4, 0], "target": [0, 0, 0], "up": [0, 0, 1], "cutoff_deg": 20,
                    "intensity": [40, 40, 40], "light_map": "maps/dots.png"}],
    "objects": [{"type": "sphere", "center": [0, 1, 0], "radius": 0.5, "albedo": [0.8, 0.8, 0.8]},
                {"type": "quad", "center": [0, 0, 0], "u": [3, 0, 0], "v": [0, 0, -3], "albedo": [0.5, 0.5, 0.5]}],
}


def _write(tmp_path, scene, name="scene.json"):
    (tmp_path / "maps").mkdir(exist_ok=True)
    dots = np.zeros((4, 4, 3))
    dots[1:3, 1:3] = 1.0
    write_png(tmp_path / "maps" / "dots.png", dots)
    path = tmp_path / name
    path.write_text(json.dumps(scene) if isinstance(scene, dict) else scene)
    return path


def _edit(fn):
    scene = copy.deepcopy(_SCENE)
    fn(scene)
    return scene


_CASES = {
    "missing field": (_edit(lambda s: s["spotlights"][0].pop("cutoff_deg")), "spotlights[0].cutoff_deg: missing field"),
    "wrong type": (_edit(lambda s: s["spotlights"][0].update(cutoff_deg="wide")),
                   "spotlights[0].cutoff_deg: expected a number"),
    "wrong vector": (_edit(lambda s: s["camera"].update(eye=[0, 1])), "camera.eye: expected a list of 3 numbers"),
    "unknown object": (_edit(lambda s: s["objects"].append({"type": "cube"})),
                       "objects[2].type: unknown object type 'cube'"),
    "missing light map": (_edit(lambda s: s["spotlights"][0].update(light_map="nope.png")),
                          "spotlights[0].light_map: cannot read"),
    "corrupt light map": (_edit(lambda s: s["spotlights"][0].update(light_map="scene.json")),
                          "spotlights[0].light_map: cannot read"),
    "up parallel": (_edit(lambda s: s["camera"].update(up=[0, -1, -12])),
                    "camera.up: parallel to the viewing direction"),
    "missing block": (_edit(lambda s: s.pop("medium")), "medium: missing field"),
    "beyond float32": (_edit(lambda s: s["medium"].update(rho=1e39)), "medium.rho: 1e+39 is beyond float32's range"),
    "intensity beyond float32": (_edit(lambda s: s["spotlights"][0].update(intensity=1e39)),
                                 "spotlights[0].intensity: 1e+39 is beyond float32's range"),
    "up not given": (_edit(lambda s: (s["spotlights"][0].pop("up"), s["spotlights"][0].update(target=[0, -1, 0]))),
                     "spotlights[0].up: not given, and the default up [0, 1, 0] is parallel to the light's direction"),
    "bad json": ("{not json", "not valid JSON"),
}


def test_optional_sections_absent(tmp_path):
    """`render` and `objects` may be left out (other tools' scene files): the defaults apply."""
    from jaxrender.app.scenes.shafts_file import RENDER_DEFAULTS

    scene = load_shafts_scene(_write(tmp_path, _edit(lambda s: (s.pop("render"), s.pop("objects")))))
    assert scene.render.spp == 1 and scene.render.shadow_map == RENDER_DEFAULTS["shadow_map"]
    assert float(scene.render.s_max) == RENDER_DEFAULTS["s_max"]
    assert scene.spheres.center.shape == (0, 3) and scene.quads.center.shape == (0, 3)


def test_an_image_of_nan_is_a_bug_not_a_result(tmp_path, capsys, monkeypatch):
    """Whatever produced it, a frame with NaN is never written: one line, exit code 1."""
    import jaxrender.app.cli.shafts as command

    monkeypatch.setattr(command, "render", lambda scene, **kw: np.full((6, 8, 3), np.nan, np.float32))
    out = tmp_path / "x.png"
    assert main(["shafts", str(_write(tmp_path, _SCENE)), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "144 of 144 values to write are NaN or infinite" in err[0] and "a bug" in err[0]
    assert not out.exists()


@pytest.mark.parametrize("case", sorted(_CASES))
def test_cli_reports_file_and_field(case, tmp_path, capsys):
    scene, expected = _CASES[case]
    path = _write(tmp_path, scene)
    out = tmp_path / "out.exr"
    code = main(["shafts", str(path), "--out", str(out)])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1, err
    assert str(path) in err and expected in err, err
    assert "Traceback" not in err
    assert not out.exists() and not list(tmp_path.glob("*.exr*")) and not list(tmp_path.glob(".out*"))


def test_quantize_bits_with_raymarch_is_an_error(tmp_path, capsys):
    path = _write(tmp_path, _SCENE)
    code = main(["shafts", str(path), "--out", str(tmp_path / "o.png"), "--method", "raymarch", "--quantize-bits", "8"])
    assert code == 2 and "--quantize-bits" in capsys.readouterr().err
    assert not (tmp_path / "o.png").exists()


def test_loader_defaults_relative_maps_and_warning(tmp_path):
    path = _write(tmp_path, _SCENE)
    scene = load_shafts_scene(path)
    light = scene.lights[0]
    assert float(light.beam_width_deg) == pytest.approx(15.0)  # 0.75 * cutoff by default
    np.testing.assert_allclose(np.asarray(light.light_map), read_image(tmp_path / "maps" / "dots.png")[..., :3],
                               atol=1e-6)
    assert float(scene.render.shadow_bias) == pytest.approx(0.002) and scene.render.table_size == 256
    hot = _edit(lambda s: s["medium"].update(K=0.01))  # 8 pi K = 0.25 > kappa = 0.1
    with pytest.warns(ShaftsSceneWarning, match="8\\*pi\\*K"):
        shafts_scene_from_dict(hot, base_dir=tmp_path, source="hot.json")
    with pytest.raises(InputError, match=re.escape("x.json: spotlights[0].up: parallel")):
        shafts_scene_from_dict(_edit(lambda s: s["spotlights"][0].update(up=[0, 1, 0])), base_dir=tmp_path,
                               source="x.json")


def test_cli_renders_png_and_times(tmp_path, capsys):
    path = _write(tmp_path, _SCENE)
    out = tmp_path / "shafts.png"
    code = main(["shafts", str(path), "--out", str(out), "--planes", "4", "--subplanes", "2", "--width", "10",
                 "--height", "7", "--time", "2"])
    assert code == 0
    line = capsys.readouterr().out.strip()
    assert re.fullmatch(r"compile_s=[0-9.]+ median_frame_s=[0-9.]+", line), line
    img = read_image(out)
    assert img.shape == (7, 10, 3) and img.max() > 0.005  # the lit sphere top (dim: most of the map is dark)


def test_every_problem_of_a_scene_is_reported_at_once(tmp_path):
    scene = _edit(lambda s: (s["camera"].update(fov_y_deg=-3), s["medium"].update(densty=2.0),
                             s["spotlights"][0].pop("intensity"), s["objects"][0].update(radius="big")))
    with pytest.raises(InputError) as info:
        shafts_scene_from_dict(scene, source="x.json", base_dir=_write(tmp_path, _SCENE).parent)
    lines = str(info.value).splitlines()
    assert lines == ["x.json: camera.fov_y_deg: must be > 0, got -3",
                     "x.json: medium.densty: unknown field (expected one of: rho, kappa, K, density)",
                     "x.json: spotlights[0].intensity: missing field",
                     "x.json: objects[0].radius: expected a number, got 'big'"]


@pytest.mark.parametrize("size", [(10**6, 10**6), (16385, 4), (8192, 8192)])
def test_sizes_beyond_the_renderers_indices_are_refused_up_front(tmp_path, capsys, size):
    """width x height (or W x H x spp) past int32-safe indexing: one line, exit 2, before any compile."""
    path = _write(tmp_path, _SCENE)
    out = tmp_path / "out.png"
    code = main(["shafts", str(path), "--out", str(out), "--width", str(size[0]), "--height", str(size[1]),
                 "--spp", "4"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "beyond what the renderer indexes" in err, err
    assert not out.exists()
    scene = _edit(lambda s: (s["camera"].update(width=size[0], height=size[1]), s["render"].update(spp=4)))
    with pytest.raises(InputError):
        shafts_scene_from_dict(scene, source="x.json", base_dir=tmp_path)


@pytest.mark.parametrize("option, value", [("--time", "-1"), ("--width", "inf"), ("--error", "nan")])
def test_bad_option_values_one_line(tmp_path, capsys, option, value):
    out = tmp_path / "x.png"
    assert main(["shafts", str(_write(tmp_path, _SCENE)), "--out", str(out), option, value]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and option in err[0] and "usage" not in err[0], err
    assert not out.exists()

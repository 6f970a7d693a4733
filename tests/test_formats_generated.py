"""Every format tested by documents generated from its description (tests/format_documents.py):
valid ones (every optional part absent or present, legal extremes, other rotation orders, 3 or 6
channels, BOM, CRLF) are read and give finite results; broken ones give one line per problem
naming the file, exit code 2, and nothing written.

A small derandomized budget runs here; `python benchmarks/format_fuzz.py` runs a larger one
through the installed command lines, in float32 as users run them.
"""

import contextlib
import tempfile
import warnings
from pathlib import Path

import numpy as np
from format_documents import (
    broken_bvh_documents,
    broken_capture_documents,
    broken_diligent_documents,
    broken_scene_documents,
    bvh_documents,
    capture_documents,
    diligent_documents,
    scene_documents,
)
from hypothesis import HealthCheck, given, settings

from fitting import load_capture, merge_capture
from jaxrender import shafts
from jaxrender.app.cli.programs import fitting_main, jaxrender_main
from jaxrender.app.scenes import ShaftsSceneWarning, load_shafts_scene
from jaxrender.io import read_bvh
from sims import pose_motion


def budget(examples: int):
    return settings(max_examples=examples, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much,
                                           HealthCheck.function_scoped_fixture])  # capsys: read after each call


@contextlib.contextmanager
def folder():
    with tempfile.TemporaryDirectory() as name:
        yield Path(name)


def refused(capsys, rc: int, named: Path, *, command: str) -> list[str]:
    """The lines of a refusal: exit code 2, each line the command's one-line error naming `named`."""
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err, (rc, err)
    for line in err:
        assert line.startswith(f"{command}: error: ") and "Traceback" not in line, err
    assert any(str(named) in line for line in err), err
    return err


@contextlib.contextmanager
def bright_fog_allowed():
    """A medium with 8*pi*K > kappa is legal (a warning, which the suite's filters make an error)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ShaftsSceneWarning)
        yield


def _load_scene(path: Path):
    with bright_fog_allowed():
        return load_shafts_scene(path)


@budget(60)
@given(scene_documents())
def test_valid_scene_files_load(document):
    with folder() as where:
        scene = _load_scene(document.write(where))
        assert len(scene.lights) >= 1 and scene.render.spp >= 1


@budget(3)
@given(scene_documents(renderable=True))
def test_valid_scene_files_render_finite(document):
    with folder() as where:
        image = shafts.render(_load_scene(document.write(where)).with_size(6, 4))
        assert np.all(np.isfinite(np.asarray(image)))


@budget(40)
@given(broken_scene_documents())
def test_broken_scene_files_one_line_each_exit_2_nothing_written(capsys, document):
    with folder() as where, bright_fog_allowed():
        path, out = document.write(where), where / "out.exr"
        refused(capsys, jaxrender_main(["shafts", str(path), "--out", str(out), "--width", "6", "--height", "4"]),
                path, command="jaxrender shafts")
        assert not out.exists(), document.breaks


@budget(25)
@given(bvh_documents())
def test_valid_bvh_files_read_and_pose_finite(document):
    with folder() as where:
        bvh = read_bvh(document.write(where))
        motion = pose_motion(bvh)
        assert motion.positions.shape[:2] == (bvh.frames, len(bvh.names))
        assert np.all(np.isfinite(np.asarray(motion.positions))) and np.all(np.isfinite(np.asarray(motion.rotations)))


@budget(40)
@given(broken_bvh_documents())
def test_broken_bvh_files_one_line_exit_2_nothing_written(capsys, document):
    with folder() as where:
        path, out = document.write(where), where / "out"
        err = refused(capsys, jaxrender_main(["noh", "--out", str(out), "--motion", str(path)]), path,
                      command="jaxrender noh")
        assert len(err) == 1 and not out.exists(), document.breaks


@budget(5)
@given(capture_documents())
def test_valid_captures_merge_finite(document):
    with folder() as where:
        capture = load_capture(document.write(where))
        obs = merge_capture(capture, progress=False)
        assert np.all(np.isfinite(np.asarray(obs.ratio))) and np.all(np.asarray(obs.weight) >= 0)


@budget(30)
@given(broken_capture_documents())
def test_broken_captures_one_line_each_exit_2_nothing_written(capsys, document):
    with folder() as where:
        path, store = document.write(where / "capture"), where / "store"
        refused(capsys, fitting_main(["ingest", str(path), "--store", str(store)]), path, command="fitting ingest")
        assert not store.exists(), document.breaks


@budget(5)
@given(diligent_documents())
def test_valid_diligent_folders_make_captures_that_merge_finite(capsys, document):
    with folder() as where:
        source, out = document.write(where / "object"), where / "capture" / "capture.json"
        assert fitting_main(["manifest", str(source), "--out", str(out)]) == 0
        obs = merge_capture(load_capture(out.parent), progress=False)
        assert np.all(np.isfinite(np.asarray(obs.ratio)))


@budget(30)
@given(broken_diligent_documents())
def test_broken_diligent_folders_one_line_each_exit_2_nothing_written(capsys, document):
    with folder() as where:
        source, out = document.write(where / "object"), where / "capture" / "capture.json"
        refused(capsys, fitting_main(["manifest", str(source), "--out", str(out)]), source, command="fitting manifest")
        assert not out.parent.exists(), document.breaks

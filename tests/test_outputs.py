"""What a command may do to its outputs (`jaxrender.io.output_file`, `output_folder`,
`check_finite`): write the files it names, each whole, keep every other file, change nothing when
it fails, and never write a value that is not finite."""

import json
import os
import stat

import numpy as np
import pytest

from jaxrender.errors import InputError, NonFiniteOutput
from jaxrender.io import check_finite, output_file, output_folder, write_exr, write_png


def _tree(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


@pytest.fixture
def user_folder(tmp_path):
    """A folder of the user's: notes, photos, and a frame from an earlier run."""
    folder = tmp_path / "mine"
    (folder / "photos").mkdir(parents=True)
    (folder / "notes.txt").write_text("mine")
    (folder / "photos" / "a.jpg").write_bytes(b"jpeg")
    (folder / "frame_000.png").write_bytes(b"old frame")
    return folder


def test_folder_keeps_other_files_and_replaces_its_own(user_folder):
    with output_folder(user_folder) as stage:
        assert stage.parent == user_folder and stage.name.startswith(".")
        (stage / "frame_000.png").write_bytes(b"new frame")
        (stage / "photos").mkdir()
        (stage / "photos" / "b.jpg").write_bytes(b"new")
        (stage / "meshes").mkdir()
        (stage / "meshes" / "m.obj").write_text("v 0 0 0\n")
    assert _tree(user_folder) == ["frame_000.png", "meshes", "meshes/m.obj", "notes.txt", "photos", "photos/a.jpg",
                                  "photos/b.jpg"]
    assert (user_folder / "frame_000.png").read_bytes() == b"new frame"
    assert (user_folder / "notes.txt").read_text() == "mine"


def test_folder_is_unchanged_when_the_command_fails(user_folder):
    before = {p: p.read_bytes() for p in user_folder.rglob("*") if p.is_file()}
    with pytest.raises(RuntimeError), output_folder(user_folder) as stage:
        (stage / "frame_000.png").write_bytes(b"half")
        raise RuntimeError("the render failed")
    assert {p: p.read_bytes() for p in user_folder.rglob("*") if p.is_file()} == before


def test_current_folder(user_folder, monkeypatch):
    monkeypatch.chdir(user_folder)
    with output_folder(".") as stage:
        (stage / "noh.gif").write_bytes(b"gif")
    assert _tree(user_folder) == ["frame_000.png", "noh.gif", "notes.txt", "photos", "photos/a.jpg"]


def test_new_folder_appears_only_on_success(tmp_path):
    out = tmp_path / "a" / "b"
    with pytest.raises(KeyboardInterrupt), output_folder(out) as stage:
        (stage / "x").write_text("x")
        raise KeyboardInterrupt
    assert not (tmp_path / "a").exists()
    old = os.umask(0o022)
    try:
        with output_folder(out) as stage:
            (stage / "x").write_text("x")
    finally:
        os.umask(old)
    assert _tree(out) == ["x"] and stat.S_IMODE(os.stat(out).st_mode) == 0o755


def test_conflicts_and_inputs_are_refused_before_anything_moves(user_folder):
    with pytest.raises(InputError, match="is a folder where the command writes a file"), \
            output_folder(user_folder) as stage:
        (stage / "new.png").write_bytes(b"x")
        (stage / "photos").write_bytes(b"a file where the user has a folder")
    with pytest.raises(InputError, match="is an input of this command"), \
            output_folder(user_folder, inputs=[user_folder / "notes.txt"]) as stage:
        (stage / "notes.txt").write_text("overwritten")
    assert (user_folder / "notes.txt").read_text() == "mine" and not (user_folder / "new.png").exists()
    with pytest.raises(InputError, match="not a folder"), output_folder(user_folder / "notes.txt"):
        pass


def test_output_file_checks(user_folder):
    assert output_file(user_folder / "x.png", suffixes=(".png",)) == user_folder / "x.png"
    for path, suffixes, inputs, needle in [
            (user_folder, (), (), "is a folder"),
            (user_folder / "x.jpg", (".png", ".exr"), (), "must end in .png or .exr"),
            (user_folder / "nowhere" / "x.png", (), (), "does not exist"),
            (user_folder / "notes.txt", (), [user_folder / "notes.txt"], "is an input")]:
        with pytest.raises(InputError, match=needle):
            output_file(path, suffixes=suffixes, inputs=inputs)
    assert output_file(user_folder / "new" / "x.json", make_folder=True).name == "x.json"


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_writers_refuse_values_that_are_not_finite(tmp_path, bad):
    image = np.full((4, 4, 3), 0.5, np.float32)
    image[1, 2, 0] = bad
    for writer, name in ((write_png, "x.png"), (write_exr, "x.exr")):
        with pytest.raises(NonFiniteOutput, match="1 of 48 values"):
            writer(tmp_path / name, image)
    assert list(tmp_path.iterdir()) == []
    check_finite(np.arange(3), tmp_path / "ints.npy")   # integers are always finite


def _capture(root):
    """A valid 4 x 4 capture of 3 lights (the ingest's input)."""
    from capture_helpers import write_capture

    (root / "images").mkdir(parents=True)

    def image(name):
        write_png(root / name, np.full((4, 4, 3), 0.5), srgb=False)
        return name

    return write_capture(root, image, size=(4, 4), ext="png", lights=3, exposures_s=[1.0], angle_step=(10.0, 30.0))


# every command that writes one file, with an existing folder (or the current one) where the file goes
FILE_COMMANDS = [
    ("jaxrender", ["shafts", "{scene}", "--out", "{out}"]),
    ("jaxrender", ["desert", "--out", "{out}"]),
    ("fitting", ["relight", "{folder}", "--theta", "10", "--phi", "0", "--out", "{out}"]),
    ("fitting", ["report", "{folder}", "{folder}", "--out", "{out}"]),
    ("fitting", ["manifest", "{folder}", "--out", "{out}"]),
    ("sims", ["ripples", "--out", "{out}"]),
    ("sims", ["dunes", "--out", "{out}"]),
    ("sims", ["ripples", "--out", "{folder}/f.npy", "--preview", "{out}"]),
]


@pytest.mark.parametrize("program, argv", FILE_COMMANDS, ids=lambda v: v if isinstance(v, str) else " ".join(v[:1]))
@pytest.mark.parametrize("where", ["folder", "current folder"])
def test_file_commands_refuse_a_folder_and_keep_its_files(tmp_path, monkeypatch, capsys, user_folder, program, argv,
                                                          where):
    from jaxrender.app.cli.programs import fitting_main, jaxrender_main, sims_main

    main = {"jaxrender": jaxrender_main, "fitting": fitting_main, "sims": sims_main}[program]
    before = {p: p.read_bytes() for p in user_folder.rglob("*") if p.is_file()}
    monkeypatch.chdir(user_folder)
    out = "." if where == "current folder" else str(user_folder)
    scene = tmp_path / "scene.json"
    scene.write_text("{}")
    args = [a.format(out=out, folder=user_folder, scene=scene) for a in argv]
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "error:" in err[0] and "Traceback" not in err[0], err
    assert {p: p.read_bytes() for p in user_folder.rglob("*") if p.is_file()} == before


def test_ingest_refuses_a_folder_of_the_users_and_keeps_its_files(tmp_path, monkeypatch, capsys, user_folder):
    from jaxrender.app.cli.programs import fitting_main

    capture = _capture(tmp_path / "capture")
    before = {p: p.read_bytes() for p in user_folder.rglob("*") if p.is_file()}
    monkeypatch.chdir(user_folder)
    for store in (".", str(user_folder)):
        assert fitting_main(["ingest", str(capture), "--store", store]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "is not an observation store" in err[0], err
    assert {p: p.read_bytes() for p in user_folder.rglob("*") if p.is_file()} == before
    assert not [p for p in user_folder.iterdir() if p.name.startswith(".")]


def test_manifest_never_writes_over_its_own_input(tmp_path, capsys):
    """`fitting manifest DIR --out DIR/filenames.txt` (or over an image, or the CSV) is refused."""
    from jaxrender.app.cli.programs import fitting_main

    folder = tmp_path / "object"
    folder.mkdir()
    write_png(folder / "001.png", np.full((3, 3, 3), 0.5))
    (folder / "filenames.txt").write_text("001.png\n")
    (folder / "light_directions.txt").write_text("0 0 1\n")
    (folder / "light_intensities.txt").write_text("1 1 1\n")
    before = {p: p.read_bytes() for p in folder.iterdir()}
    for target in ("filenames.txt", "001.png", "light_directions.txt"):
        assert fitting_main(["manifest", str(folder), "--out", str(folder / target)]) == 2
        assert "is an input of this command" in capsys.readouterr().err
    assert {p: p.read_bytes() for p in folder.iterdir()} == before
    assert fitting_main(["manifest", str(folder), "--out", str(folder / "capture.json")]) == 0   # beside them: fine


def test_report_and_fit_refuse_what_they_cannot_measure(tmp_path, capsys):
    """`fitting report --holdout K` with K beyond the capture's lights, and a capture whose mask
    selects no texel: one line, exit code 2, nothing written."""
    from jaxrender.app.cli.programs import fitting_main

    capture = _capture(tmp_path / "capture")
    assert fitting_main(["report", str(capture), str(tmp_path / "btf"), "--holdout", "100"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--holdout 100: hold out every k-th light with 2 <= k <= 3" in err[0], err
    np.save(tmp_path / "zeros.npy", np.zeros((4, 4, 3)))
    assert fitting_main(["report", str(capture), str(tmp_path / "btf"), "--normals", str(tmp_path / "zeros.npy")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "zeros.npy: no non-zero normal inside the capture's mask" in err[0], err
    write_png(capture / "mask.png", np.zeros((4, 4, 3)), srgb=False)
    manifest = json.loads((capture / "capture.json").read_text())
    (capture / "capture.json").write_text(json.dumps({**manifest, "mask": "mask.png"}))
    btf = tmp_path / "btf"
    assert fitting_main(["fit", str(capture), "--out", str(btf)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "the mask is all zero" in err[0], err
    assert not btf.exists()


def _twice_the_memory() -> str:
    """A grid side whose automaton needs about twice this machine's memory (within int32 indexing)."""
    from jaxrender.app.cli.arguments import physical_memory
    from jaxrender.app.cli.fields import BYTES_PER_CELL

    side = int((2 * physical_memory() / BYTES_PER_CELL) ** 0.5)
    assert side**2 < 2**31, "this machine has more memory than the kernels can index: pick another case"
    return str(side)


@pytest.mark.parametrize("argv, code, needle", [
    (["ripples", "--size", "100000x100000"], 2, "beyond what the kernels index"),
    (["ripples", "--size", "TWICE"], 3, "out of memory (--size"),
    (["dunes", "--size", "3000000000"], 2, "beyond what the kernels index"),
])
def test_sizes_are_checked_before_allocation(tmp_path, capsys, argv, code, needle):
    from jaxrender.app.cli.programs import sims_main

    argv = [_twice_the_memory() if a == "TWICE" else a for a in argv]
    out = tmp_path / "f.npy"
    assert sims_main(argv + ["--out", str(out)]) == code
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0] and "--memory-gb" not in err[0], err
    assert not out.exists()

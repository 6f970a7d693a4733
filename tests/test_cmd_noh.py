"""`jaxrender noh` rejects bad input (options, files, motion capture) with one line, exit code 2 and
no output directory."""

import pytest

from jaxrender.app.cli.programs import jaxrender_main as main


@pytest.mark.parametrize("extra, needle", [
    (["--mask", "MISSING.png"], "MISSING.png"),
    (["--mask", "mask.jpg"], "mask.jpg"),
    (["--btf", "gold=btf"], "unknown label 'gold'"),
    (["--btf", "brocade"], "LABEL=BTF_DIR"),
    (["--btf", "brocade=btf"], "btf.json"),
    (["--env", "bad.exr"], "bad.exr"),
    (["--frames", "0"], "--frames"),
    (["--width", "4"], "--width"),
])
def test_bad_input_one_line_exit_2_no_output(tmp_path, capsys, monkeypatch, extra, needle):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "btf").mkdir()
    (tmp_path / "bad.exr").write_bytes(b"not an exr")
    (tmp_path / "mask.jpg").write_bytes(b"\xff\xd8")
    out = tmp_path / "out"
    rc = main(["noh", "--out", str(out)] + extra)
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert len(err) == 1 and needle in err[0] and "Traceback" not in err[0]
    assert not out.exists()


def test_motion_without_the_body_joints_is_one_line_exit_2(tmp_path, capsys):
    """A well-formed BVH whose skeleton lacks a joint the performer needs: the file and the role named."""
    path = tmp_path / "arm.bvh"
    path.write_text("HIERARCHY\nROOT Hips\n{\n  OFFSET 0 90 0\n  CHANNELS 3 Xposition Yposition Zposition\n"
                    "  JOINT Arm\n  {\n    OFFSET 10 0 0\n    CHANNELS 1 Zrotation\n  }\n}\n"
                    "MOTION\nFrames: 1\nFrame Time: 0.05\n0 90 0 10\n")
    out = tmp_path / "out"
    assert main(["noh", "--out", str(out), "--motion", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "arm.bvh: no joint for the spine" in err[0] and not out.exists()

"""`jaxrender noh` rejects bad input with one line, exit code 2 and no output directory."""

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

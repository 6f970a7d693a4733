"""`jaxrender.io.atomic_path`: the output appears whole or not at all, with the mode a plain write gives."""

import os
import stat

import pytest

from jaxrender.io import atomic_path


def _mode(path):
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.fixture
def umask_022():
    old = os.umask(0o022)
    yield
    os.umask(old)


def test_file_appears_with_the_umask_mode(tmp_path, umask_022):
    out = tmp_path / "sub" / "image.png"
    with atomic_path(out) as tmp:
        assert tmp.parent == out.parent and tmp != out and not out.exists()
        tmp.write_bytes(b"data")
    assert out.read_bytes() == b"data"
    assert _mode(out) == 0o644  # 0666 & ~022, not mkstemp's 0600
    assert [p.name for p in out.parent.iterdir()] == ["image.png"]  # no temporary left


def test_failure_keeps_the_old_file_and_removes_the_temporary(tmp_path):
    out = tmp_path / "maps.exr"
    out.write_bytes(b"old")
    with pytest.raises(RuntimeError), atomic_path(out) as tmp:
        tmp.write_bytes(b"half")
        raise RuntimeError("writer failed")
    assert out.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["maps.exr"]

"""The gallery page: sections render into their folders, failures are reported, not hidden."""

import sys
import types

import numpy as np

from jaxrender import io
from jaxrender.app import gallery
from jaxrender.app.cli.programs import jaxrender_main as main


def _fake_section(out_dir, *, quick=False):
    io.write_png(out_dir / "img.png", np.full((4, 4, 3), 0.5))
    yield {"title": "fake", "images": ["img.png"], "caption": "a grey square",
           "params": {"size": 4, "quick": quick}, "timings": {"render_s": 0.25}}


def _broken_section(out_dir, *, quick=False):
    io.write_png(out_dir / "first.png", np.full((4, 4, 3), 0.25))
    yield {"title": "first", "images": ["first.png"], "caption": "written before the failure"}
    raise RuntimeError("boom")


def test_gallery_page_lists_images_params_timings_and_failures(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "fake_ok", types.SimpleNamespace(gallery_section=_fake_section))
    monkeypatch.setitem(sys.modules, "fake_broken", types.SimpleNamespace(gallery_section=_broken_section))
    monkeypatch.setattr(gallery, "SECTIONS", {"ok": ("fake_ok", "OK section"), "broken": ("fake_broken", "Broken")})
    lines = []
    result = gallery.render_gallery(tmp_path, quick=True, log=lines.append)
    page = (tmp_path / "index.html").read_text()
    assert (tmp_path / "ok" / "img.png").is_file()
    assert 'src="ok/img.png"' in page and "a grey square" in page and "render_s" in page
    assert result["sections"]["ok"]["error"] is None
    assert "boom" in result["sections"]["broken"]["error"] and "boom" in page
    # each entry is announced as it is written; a section's entries before its failure stay on the page
    assert any(line.startswith("[gallery] ok: wrote ok/img.png (") for line in lines), lines
    assert any(line.startswith("[gallery] broken: wrote broken/first.png (") for line in lines), lines
    assert 'src="broken/first.png"' in page and "written before the failure" in page


def test_gallery_cli_rejects_unknown_section(tmp_path, capsys):
    assert main(["gallery", "--out", str(tmp_path / "g"), "--only", "nonsense"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nonsense" in err[0]
    assert not (tmp_path / "g").exists()

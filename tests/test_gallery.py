"""The gallery page: sections render into their folders, failures are reported, not hidden."""

import os
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
    result = gallery.render_gallery(tmp_path, quick=True, log=lines.append)  # jobs=1: in this process
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


def test_sections_render_side_by_side_in_processes_of_their_own(tmp_path, monkeypatch):
    """`jobs=2`: the two "together" sections run at once (each waits for the other to start), each
    section in a process other than this one, on cores of its own; lines reach this process's log
    as they are written, and the sections' progress bars are drawn here; a failing section and one
    whose process dies are reported, the others kept, the page in `SECTIONS`' order."""
    fake = ("gallery_fake_sections", "stand-in")
    monkeypatch.setattr(gallery, "SECTIONS", {n: fake for n in ("together_a", "broken", "together_b", "dies")})
    bars = []

    class Bar:   # what this process draws on a terminal
        def __init__(self, *, total, desc, **_):
            self.desc, self.total, self.n, self.closed = desc, total, 0, False
            bars.append(self)

        def update(self, n=1):
            self.n += n

        def close(self):
            self.closed = True

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.close()

    monkeypatch.setattr(gallery, "tqdm", Bar)
    lines = []
    result = gallery.render_gallery(tmp_path, quick=True, log=lines.append, jobs=2)
    sections = result["sections"]
    assert list(sections) == ["together_a", "broken", "together_b", "dies"] and result["jobs"] == 2
    for name in ("together_a", "together_b"):
        assert sections[name]["error"] is None, sections[name]["error"]
        assert sections[name]["entries"][0]["params"]["pid"] != os.getpid()
        assert f"[gallery] {name}: wrote {name}/img.png (" in "\n".join(lines)
    # each on its own share of the cores (the suite's machines have 2 or more)
    cores = [set(sections[n]["entries"][0]["params"]["cores"]) for n in ("together_a", "together_b")]
    assert cores[0] and cores[1] and not cores[0] & cores[1] and cores[0] | cores[1] <= os.sched_getaffinity(0)
    assert "boom" in sections["broken"]["error"] and sections["broken"]["entries"]
    assert "exit code 3" in sections["dies"]["error"] and sections["dies"]["entries"] == []
    assert any(line.startswith("[gallery] dies: wrote dies/img.png (") for line in lines), lines  # sent before it died
    page = (tmp_path / "index.html").read_text()
    assert page.index('id="together_a"') < page.index('id="broken"') < page.index('id="together_b"')
    assert "exit code 3" in page and "2 sections rendering at once, each on its share of the cores" in page
    shown = {(b.desc, b.total, b.n, b.closed) for b in bars}
    assert ("gallery", 4, 4, True) in shown
    assert {("together_a: steps", 3, 3, True), ("together_b: steps", 3, 3, True)} <= shown, shown


def test_gallery_cli_rejects_jobs_below_one(tmp_path, capsys):
    assert main(["gallery", "--out", str(tmp_path / "g"), "--jobs", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--jobs" in err[0]
    assert not (tmp_path / "g").exists()

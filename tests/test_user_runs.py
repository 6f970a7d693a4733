"""What users run, run the way they run it: the installed console scripts (`jaxrender`, `fitting`,
`sims`, next to this Python) in subprocesses, in float32 as installed (the suite's float64 is not
inherited), on small sizes. Each test checks that the outputs exist, are readable and are sensible
(shapes, finite values, the physics they show), not only that the exit code is 0.

The gallery run is the slow one (`--quick`, its sections side by side beside the suite's other
worker: 185 s in a full run on 2 cores of an AMD EPYC with AVX-512, 393 s on one with AVX2 only);
it is not skipped.
"""

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
import robe_contact
from skimage import io as skio

from fitting.pyramid import pyramid_levels
from fitting.synth import synth_capture
from jaxrender.app.gallery import SECTIONS
from jaxrender.brdf import BTFTexel
from jaxrender.io import read_btf, read_exr

SCRIPTS = Path(sys.executable).parent  # console scripts are installed beside the interpreter
EDGE_DEPTH_TOL = 0.005  # m: how deep a robe edge may reach into a closed body part (measured 3.5 mm)
FLOOR_TOL = 0.15     # m: the lowest point of the performer from the stage floor (y = 0; an odd pose's toe dips below)
MOCAP = Path(os.environ.get("JAXRENDER_MOCAP", Path(__file__).resolve().parents[2] / "shared" / "data" / "mocap"))
HANG_GUARD_S = 1800  # a hung run fails the test instead of the suite; not a speed assertion

# `sims ripples` / `sims dunes` in float32 over 10,000 steps: the bound on the drift of the
# total (sand moves on a fixed-point grid; measured 2.4e-8 and 1.2e-7 at 128x128, <= 1e-8 here).
SAND_DRIFT_TOL = 1e-6
# The EM pyramid from `fitting pyramid` (float32) against the same pyramid built in float64 in this
# process, compared where it matters, rendered at 2000 light/view pairs: relative RMS, measured
# 7e-8 to 9e-8 (float32 rounding through the EM iterations); a lobe decision that flipped would
# show as > 1e-2.
PYRAMID_F32_RTOL = 1e-5
# `fitting report` on the capture the BTF was fitted to (8-bit, shot and read noise): per-light relative
# RMS relighting error, measured median 1.13 %, max 1.52 %; a wrong map gives tens of percent.
REPORT_MEDIAN_MAX = 0.03
REPORT_MAX_MAX = 0.05


def run(tool: str, *args, cwd=None) -> subprocess.CompletedProcess:
    """Run a console script; assert it exits 0 and return it (stdout/stderr captured)."""
    env = dict(os.environ)
    env.pop("JAX_ENABLE_X64", None)  # as a user runs it: float32
    env["MPLBACKEND"] = "Agg"
    # (the run's persistent compilation cache, tests/conftest.py: a command run twice compiles once)
    exe = SCRIPTS / tool
    assert exe.is_file(), f"console script {exe} is not installed (pip install -e .)"
    proc = subprocess.run([str(exe), *map(str, args)], capture_output=True, text=True, env=env, cwd=cwd,
                          timeout=HANG_GUARD_S)
    assert proc.returncode == 0, f"{tool} {' '.join(map(str, args))} exited {proc.returncode}:\n{proc.stderr[-4000:]}"
    return proc


def read_rgb(path: Path) -> np.ndarray:
    """An image file as float64 RGB: [0, 1] from a PNG (grey repeated), linear from an EXR."""
    assert path.is_file() and path.stat().st_size > 0, path
    if path.suffix == ".exr":
        channels = read_exr(path)
        names = [c for c in ("R", "G", "B") if c in channels] or sorted(channels)
        return np.stack([np.asarray(channels[c], np.float64) for c in names], axis=-1)
    image = skio.imread(path)
    scale = np.iinfo(image.dtype).max if np.issubdtype(image.dtype, np.integer) else 1.0
    image = np.asarray(image, np.float64) / scale
    return np.repeat(image[..., None], 3, axis=-1) if image.ndim == 2 else image[..., :3]  # grey -> RGB


def assert_picture(image: np.ndarray, *, min_std: float = 0.02, max_clipped: float = 0.2):
    """Finite, not blank, not one flat colour, at most `max_clipped` of a display image's pixels
    clipped to white or to black (a stage in the dark or a chart on white needs more)."""
    assert np.all(np.isfinite(image))
    assert image.min() >= 0.0
    assert image.std() > min_std * max(float(image.mean()), 1e-12), "a flat image"
    if image.max() <= 1.0:
        assert np.mean(np.all(image >= 0.999, axis=-1)) < max_clipped, "mostly white"
        assert np.mean(np.all(image <= 0.001, axis=-1)) < max_clipped, "mostly black"


def exact_total(field) -> float:
    return math.fsum(np.asarray(field, np.float64).ravel().tolist())


# --- sims -----------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("command,low,high,extra", [("ripples", 1.0, 1.5, ["--L0", "9"]),
                                                    ("dunes", 2.0, 4.0, ["--wind-deg", "30"])])
def test_sims_conserve_sand_over_10000_steps_float32(tmp_path, command, low, high, extra):
    """`sims ripples` / `sims dunes` (float32, chunks of 100 steps with a progress bar) keep
    the total of a 32 x 48 field to within 1e-6 over 10,000 steps; the features did grow."""
    init = np.random.default_rng(7).uniform(low, high, (32, 48)).astype(np.float32)
    np.save(tmp_path / "init.npy", init)
    out = tmp_path / "out.npy"
    proc = run("sims", command, "--init", tmp_path / "init.npy", "--steps", "10000", "--out", out,
               "--preview", tmp_path / "preview.png", *extra)
    assert "10000 steps" in proc.stdout
    field = np.load(out)
    assert field.dtype == np.float32 and field.shape == (32, 48) and np.all(np.isfinite(field))
    drift = abs(exact_total(field) - exact_total(init)) / exact_total(init)
    assert drift <= SAND_DRIFT_TOL, drift
    assert field.std() > 5 * init.std()  # ripples / dunes formed: sand did move
    preview = read_rgb(tmp_path / "preview.png")
    assert preview.shape[:2] == (32, 48)
    assert_picture(preview)


# --- jaxrender desert / noh ----------------------------------------------------------------------------------------

def test_jaxrender_desert_small(tmp_path):
    """A 96 x 64 desert: sand below (warm: red over blue), a bluer sky above, nothing flat or clipped;
    the EXR is the linear frame the PNG was tone mapped from (same shape, brighter where the PNG is)."""
    png, exr = tmp_path / "desert.png", tmp_path / "desert.exr"
    small = ["--width", "96", "--height", "64", "--dune-size", "16", "--ripple-size", "16", "--texels", "16"]
    run("jaxrender", "desert", "--out", png, *small)
    run("jaxrender", "desert", "--out", exr, *small)
    image = read_rgb(png)
    assert image.shape == (64, 96, 3)
    assert_picture(image)
    sky, sand = image[:6].mean(axis=(0, 1)), image[-16:].mean(axis=(0, 1))
    assert sand[0] > 1.3 * sand[2]  # sand is warm (measured R/B 1.65)
    assert sky[2] / sky[0] > 1.2 * sand[2] / sand[0]  # the sky is bluer than the sand (0.92 vs 0.60)
    linear = read_rgb(exr)
    assert linear.shape == (64, 96, 3) and np.all(np.isfinite(linear)) and linear.min() >= 0.0
    lum_png, lum_exr = image.mean(axis=-1).ravel(), linear.mean(axis=-1).ravel()
    assert np.corrcoef(np.argsort(np.argsort(lum_png)), np.argsort(np.argsort(lum_exr)))[0, 1] > 0.95  # same picture


def users_folder(folder: Path) -> dict[Path, bytes]:
    """A folder of the user's (a note, a photo in a subfolder) that a command's output goes into: the
    files it held before, to check that they are still there after."""
    (folder / "photos").mkdir(parents=True)
    (folder / "notes.txt").write_text("my notes")
    (folder / "photos" / "a.jpg").write_bytes(b"my photo")
    return {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def assert_kept(kept: dict[Path, bytes]) -> None:
    for path, content in kept.items():
        assert path.read_bytes() == content, f"{path} was changed or removed"


def relabelled_walk(path: Path) -> Path:
    """The captured walk with its rotation channels relabelled X Y Z (the same numbers in another
    order: a pose no one captured, limbs flung about), saved with a byte-order mark and CRLF line ends."""
    clip = MOCAP / "walk_normal_001.bvh"
    assert clip.is_file(), f"{clip}: the motion capture data is missing (set JAXRENDER_MOCAP)"
    text = clip.read_text().replace("Zrotation Xrotation Yrotation", "Xrotation Yrotation Zrotation")
    path.write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
    return path


class TestNohCommand:  # its own scope under --dist loadscope (conftest.py)
    def test_jaxrender_noh_small(self, tmp_path):
        """Two 64 x 48 frames of the Noh scene dancing an odd motion (a real walk with relabelled rotation
        channels, BOM, CRLF), written with `--out .` into a folder of the user's that holds the motion
        (its files stay): PNG + linear EXR per frame, the GIF and the MP4; the frames are pictures, and
        they differ (the fires flicker) but show the same scene. With `--meshes`, each frame's body and
        robe as OBJ (`assert_performer_meshes`)."""
        out = tmp_path / "noh"
        kept = users_folder(out)
        motion = relabelled_walk(out / "walk.bvh")
        kept[motion] = motion.read_bytes()
        proc = run("jaxrender", "noh", "--out", ".", "--motion", "walk.bvh", "--frames", "2", "--width", "64",
                   "--height", "48", "--meshes", cwd=out)
        assert "2 frames" in proc.stdout
        assert_kept(kept)
        assert not [p for p in out.iterdir() if p.name.startswith(".")]   # no staging folder left
        frames = []
        for i in range(2):
            png = read_rgb(out / f"frame_{i:03d}.png")
            exr = read_rgb(out / f"frame_{i:03d}.exr")
            assert png.shape == exr.shape == (48, 64, 3)
            assert_picture(png)
            assert np.all(np.isfinite(exr)) and exr.min() >= 0.0 and exr.max() > 0.0
            frames.append(exr)
        change = np.abs(frames[1] - frames[0]).mean() / frames[0].mean()
        assert 1e-4 < change < 0.5, change  # flicker, not a different scene (or a frozen one)
        gif = skio.imread(out / "noh.gif")
        assert gif.shape[0] == 2 and gif.shape[1:3] == (48, 64)
        assert (out / "noh.mp4").read_bytes()[4:8] == b"ftyp"      # an MP4 (ISO media) file beside them
        assert_performer_meshes(out / "meshes", frames=2)


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(vertices, triangles, uv, uv triangles) of an OBJ of triangles `f v/vt v/vt v/vt` (0-based)."""
    v, vt, f, ft = [], [], [], []
    for line in path.read_text().splitlines():
        word, *rest = line.split() or [""]
        if word == "v":
            v.append([float(x) for x in rest])
        elif word == "vt":
            vt.append([float(x) for x in rest])
        elif word == "f":
            assert len(rest) == 3, line
            corners = [[int(i) - 1 for i in c.split("/")] for c in rest]
            f.append([c[0] for c in corners])
            ft.append([c[1] for c in corners])
    return np.asarray(v), np.asarray(f), np.asarray(vt), np.asarray(ft)


def assert_performer_meshes(folder: Path, frames: int):
    """frame_NNN_body.obj and frame_NNN_robe.obj, read back by their text: a standing performer in
    metres with y up; every body part but the mask a closed mesh; uv in the texture's pages; no
    robe vertex inside a closed body part and no robe edge deeper in one than `EDGE_DEPTH_TOL`
    (`robe_contact.contact`: its own welding, nothing of the capsules). Edges do cross the body's
    triangles in this odd pose (2 robe triangles in each frame, measured)."""
    assert sorted(p.name for p in folder.iterdir()) == sorted(
        f"frame_{i:03d}_{part}.obj" for i in range(frames) for part in ("body", "robe"))
    for i in range(frames):
        body = read_obj(folder / f"frame_{i:03d}_body.obj")
        robe = read_obj(folder / f"frame_{i:03d}_robe.obj")
        for v, f, vt, ft in (body, robe):
            assert np.all(np.isfinite(v)) and f.min() >= 0 and f.max() < len(v) and ft.max() < len(vt)
            assert f.shape == ft.shape and len(np.unique(f)) == len(v)     # every vertex used
            assert np.all((vt[:, 0] >= 0) & (vt[:, 0] <= 1) & (vt[:, 1] >= 0) & (vt[:, 1] <= 2))
        assert np.all(vt_page(body) >= 1) and np.all(vt_page(robe) < 1)     # body page / robe page
        part, closed = robe_contact.parts(body[0], body[1])
        assert closed.sum() == len(closed) - 1 >= 10                        # the capsules; the mask is open
        height = body[0][:, 1].max() - body[0][:, 1].min()
        assert 1.3 < height < 2.2 and abs(body[0][:, 1].min()) < FLOOR_TOL  # metres, y up, on the stage floor
        shape = robe_contact.BodyShape(body[0], body[1], part, closed)
        c = robe_contact.contact(robe[0], robe[1], shape)
        assert c.inside_vertices == 0 and c.depth <= EDGE_DEPTH_TOL, c     # measured: 0 and 0 mm


def vt_page(mesh) -> np.ndarray:
    """The texture page of each triangle (robe: v < 1, body: v >= 1), from its uv centroid."""
    return np.floor(mesh[2][mesh[3]].mean(axis=1)[:, 1])


# --- fitting synth / fit / pyramid / relight / report ------------------------------------------------------------

@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A tiny synthetic capture (8 x 8 texels, 60 lights) fitted by `fitting fit --no-pyramid`, then the
    EM pyramid built by `fitting pyramid` (both float32, as installed)."""
    root = tmp_path_factory.mktemp("user_fit")
    capture = synth_capture(root / "capture", key=jax.random.key(5), size=(8, 8), lights=60, progress=False)
    btf = root / "btf"
    kept = users_folder(btf)   # fitted with `--out .` from inside a folder of the user's: its files stay
    run("fitting", "fit", capture, "--out", ".", "--no-pyramid", cwd=btf)
    manifest, levels = read_btf(btf)
    assert len(levels) == 1
    level0 = {k: np.array(v) for k, v in levels[0].items()}
    run("fitting", "pyramid", btf)
    assert_kept(kept)
    assert sorted(p.name for p in btf.iterdir() if p.name.startswith(".")) == []   # no store, partial or lock left
    return capture, btf, level0


def test_fitting_pyramid_float32_matches_float64(fitted):
    """`fitting pyramid` (float32) against the same EM pyramid built here in float64 from the same
    level 0: every level, rendered at 2000 light/view pairs, within PYRAMID_F32_RTOL."""
    from test_pyramid import _render, light_view_pairs

    _, btf, level0 = fitted
    manifest, levels = read_btf(btf)
    assert [tuple(e["size"]) for e in manifest["levels"]] == [(8, 8), (4, 4), (2, 2), (1, 1)]
    assert manifest["pyramid"]["method"] == "em"
    np.testing.assert_array_equal(levels[0]["sigma_x"], level0["sigma_x"])  # level 0 untouched
    reference, _ = pyramid_levels(BTFTexel.from_channels({k: np.asarray(v, np.float64) for k, v in level0.items()}))
    wi, wo = light_view_pairs(jax.random.key(0), 2000)

    def flat(texel):
        return jax.tree.map(lambda a: a.reshape((-1,) + a.shape[2:]), texel)

    for ref, level in zip(reference, levels[1:]):
        ours = BTFTexel.from_channels({k: np.asarray(v, np.float64) for k, v in level.items()})
        r_ours, r_ref = np.asarray(_render(flat(ours), wi, wo)), np.asarray(_render(flat(ref), wi, wo))
        assert np.all(np.isfinite(r_ours))
        assert np.linalg.norm(r_ours - r_ref) / np.linalg.norm(r_ref) < PYRAMID_F32_RTOL


def test_fitting_relight_and_report(fitted, tmp_path):
    """`fitting relight` (EXR and PNG, level 0 and a pyramid level) and `fitting report`: the relit
    texels are finite and positive, a grazing light gives less light than an overhead one (cosine),
    and the report's relighting error is small on a capture the BTF was fitted to."""
    capture, btf, _ = fitted
    overhead, grazing = tmp_path / "overhead.exr", tmp_path / "grazing.exr"
    run("fitting", "relight", btf, "--theta", "0", "--phi", "0", "--out", overhead)
    run("fitting", "relight", btf, "--theta", "75", "--phi", "40", "--out", grazing)
    run("fitting", "relight", btf, "--theta", "30", "--phi", "0", "--level", "1", "--out", tmp_path / "level1.png")
    top, low = read_rgb(overhead), read_rgb(grazing)
    assert top.shape[:2] == (8, 8) and low.shape == top.shape
    assert np.all(np.isfinite(top)) and np.all(top > 0) and np.all(low >= 0)
    assert low.mean() < 0.6 * top.mean()  # cos 75 deg = 0.26, times a BRDF that does not grow 2.3x
    level1 = read_rgb(tmp_path / "level1.png")
    assert level1.shape[:2] == (4, 4) and np.all(np.isfinite(level1)) and level1.max() > 0
    figure = tmp_path / "report.png"
    proc = run("fitting", "report", capture, btf, "--out", figure)
    chart = read_rgb(figure)
    assert min(chart.shape[:2]) > 200 and np.mean(np.any(chart < 0.9, axis=-1)) > 0.05  # a figure, not blank
    overall = re.search(r"relighting error over all lights: median ([\d.]+)\s+max ([\d.]+)", proc.stdout)
    converged = re.search(r"converged ([\d.]+)%", proc.stdout)
    assert overall and converged, proc.stdout
    assert float(overall.group(1)) < REPORT_MEDIAN_MAX and float(overall.group(2)) < REPORT_MAX_MAX
    assert float(converged.group(1)) >= 90.0


# --- jaxrender gallery --quick ------------------------------------------------------------------------------------

class TestGallery:  # its own scope under --dist loadscope (conftest.py)
    def test_gallery_quick_end_to_end(self, tmp_path):
        """The main job: `jaxrender gallery --quick`, every section rendered without error, every image the
        page shows is on disk, readable and a picture, and the index links them all."""
        out = tmp_path / "gallery"
        kept = users_folder(out)   # an existing folder is used, its other files kept
        proc = run("jaxrender", "gallery", "--quick", "--out", out)
        assert "FAILED" not in proc.stdout
        assert_kept(kept)
        # not a terminal: no progress bars, one line per entry as it is written
        assert "\r" not in proc.stderr and "it/s" not in proc.stderr and "section/s" not in proc.stderr, proc.stderr
        result = json.loads((out / "gallery.json").read_text())
        assert result["quick"] is True
        assert set(result["sections"]) == set(SECTIONS)
        page = (out / "index.html").read_text()
        for name, section in result["sections"].items():
            assert section["error"] is None, f"{name}: {section['error']}"
            assert section["entries"], f"{name}: no entries"
            for entry in section["entries"]:
                assert entry["title"] and entry["images"], (name, entry)
                assert f"[gallery] {name}: wrote {', '.join(entry['images'])} (" in proc.stdout, proc.stdout
                for rel in entry["images"]:
                    assert rel.startswith(f"{name}/")
                    assert rel in page, f"index.html does not show {rel}"
                    path = out / rel
                    if path.suffix in (".png", ".exr"):
                        image = read_rgb(path)
                        assert image.ndim == 3 and min(image.shape[:2]) >= 8, (rel, image.shape)
                        # the stage is lit by spot lights in the dark (measured 45 % black pixels), the fit's
                        # chart has a white background (55 % white): clipped up to 80 %, never all
                        assert_picture(image, min_std=0.01, max_clipped=0.8)
                    else:
                        assert path.is_file() and path.stat().st_size > 0, rel

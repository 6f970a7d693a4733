"""Faults survived: a damaged store never becomes wrong maps, every failure is one line with
the exit code of its kind, a BTF is complete only when it is, one writer per output.

One small capture (8 x 8 texels, 12 lights of random codes; a store of 4 tiles x 3 light blocks) and
one reference fit (in-process, float32 as `fitting fit` runs it, compiled into a persistent cache
that the one fitting subprocess here loads). Every fault is made by hand on a copy of the store or the BTF, or injected
(disk full, read-only, out of memory: an `OSError`/`MemoryError` raised where the write happens; a
real small tmpfs and a read-only mount were checked by hand once; a test cannot mount one). The command
lines run in this process through `fitting_main` / `jaxrender_main` (the driver is what is checked);
the subprocesses are a second writer (a lock holder) and a fit killed by SIGKILL.
"""

import errno
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from capture_helpers import write_capture
from test_store import _env, _fit_mode

from fitting import FitSettings, fit_store, ingest_capture, open_store
from fitting.store import FILL, StoreDamaged, create_arrays
from jaxrender.app.cli.programs import fitting_main, jaxrender_main
from jaxrender.errors import EXIT_BUSY, EXIT_INPUT, EXIT_INTERNAL, EXIT_MACHINE, InputError, OutputBusy
from jaxrender.io import LOCK_NAME, atomic_path, output_lock, read_btf, remove_temporaries, write_exr, write_png

SIZE = (8, 8)
LIGHTS = 12
TILE = 16          # 4 tiles of the store and of the fit
LIGHT_BLOCK = 4    # 3 light blocks: 12 chunks of ratio, 12 of flags, 1 of counts
LEVELS = 4         # 8x8, 4x4, 2x2, 1x1


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return tmp_path_factory.mktemp("faults")


@pytest.fixture(scope="module")
def capture(root):
    """Codes drawn at random, written as PNGs (no synthesis to compile: the faults do not need real maps)."""
    rng = np.random.default_rng(11)

    def image(name):
        write_png(root / "capture" / name, rng.uniform(0.1, 0.9, SIZE + (3,)).astype(np.float32), srgb=False)
        return name

    return write_capture(root / "capture", image, size=SIZE, ext="png", lights=LIGHTS, exposures_s=[0.1, 1.0],
                         angle_step=(6.0, 30.0))


@pytest.fixture(scope="module")
def store(root, capture):
    return ingest_capture(capture, root / "store", tile=TILE, light_block=LIGHT_BLOCK, progress=False)


@pytest.fixture(scope="module")
def reference(root, store):
    """A clean fit of the store with its pyramid (compiles the tile and EM programs into the cache)."""
    with _fit_mode(root):
        return fit_store(store, root / "reference", FitSettings(chunk=TILE), progress=False)


def _levels(btf: Path) -> list[dict]:
    return read_btf(btf)[1]


def assert_same_maps(btf: Path, reference: Path, levels: int | None = None):
    """Bit for bit: the damage was written again exactly as the ingest wrote it (the merge is deterministic)."""
    got, ref = _levels(btf), _levels(reference)[:levels]
    assert len(got) == len(ref)
    for g, r in zip(got, ref, strict=True):
        for name in r:
            np.testing.assert_array_equal(g[name], r[name], err_msg=name)


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _chunk(store_dir: Path, array: str, coords: tuple[int, ...]) -> Path:
    return store_dir / array / "c" / "/".join(map(str, coords))


def _damage(path: Path, kind: str) -> None:
    data = path.read_bytes()
    if kind == "missing":
        path.unlink()
    elif kind == "truncated":
        path.write_bytes(data[:len(data) // 2])
    elif kind == "empty":
        path.write_bytes(b"")
    else:   # corrupt: bytes in the middle overwritten, the length kept
        noise = np.random.default_rng(0).integers(0, 256, 8, dtype=np.uint8).tobytes()
        path.write_bytes(data[:4] + bytes(a ^ (b | 1) for a, b in zip(data[4:12], noise, strict=True)) + data[12:])


def cli(main, *args) -> tuple[int, str]:
    """Run a command line in this process; (exit code, stderr)."""
    import contextlib
    import io

    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main([str(a) for a in args])
    return code, err.getvalue()


def assert_one_line(stderr: str, *needles: str):
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in stderr, stderr
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


# --- stores that prove their contents ---------------------------------------------------------------------------

def test_every_chunk_is_on_disk_even_when_it_equals_zero(tmp_path):
    """All-zero data (a block of dark or invalid observations) is written, and what is not written reads
    as no data: NaN ratio, flags 255, counts -1, never the zeros the ingest writes for invalid texels."""
    import zarr

    create_arrays(tmp_path, size=(4, 4), n_lights=6, tile=8, light_block=3, dtype="float16")
    group = zarr.open_group(str(tmp_path), mode="r+")
    group["ratio"][:8] = 0.0
    group["flags"][:8] = 0
    files = sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("c/*/*") if p.is_file())
    files += sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("c/*/*/*") if p.is_file())
    assert sorted(files) == ["flags/c/0/0", "flags/c/0/1", "ratio/c/0/0/0", "ratio/c/0/1/0"]
    assert np.all(np.isnan(group["ratio"][8:])) and np.all(group["flags"][8:] == FILL["flags"])
    assert np.all(group["counts"][:] == FILL["counts"])


@pytest.mark.parametrize("array,coords,kind", [("ratio", (1, 2, 0), "missing"), ("flags", (2, 0), "missing"),
                                               ("ratio", (3, 1, 0), "truncated"), ("flags", (0, 1), "corrupt"),
                                               ("ratio", (0, 0, 0), "corrupt"), ("ratio", (2, 2, 0), "empty")])
def test_a_damaged_chunk_is_found_when_read(root, store, array, coords, kind):
    """The read of a tile that holds a damaged chunk raises `StoreDamaged` naming that chunk (and only the
    tiles that hold it); the other tiles read as before."""
    bad = _copy(store, root / f"read_{array}_{kind}_{'_'.join(map(str, coords))}")
    _damage(_chunk(bad, array, coords), kind)
    clean, damaged = open_store(store), open_store(bad)
    for tile in range(4):
        if tile != coords[0]:
            for got, ref in zip(damaged.read(tile * TILE, TILE), clean.read(tile * TILE, TILE), strict=True):
                np.testing.assert_array_equal(got, ref)
            continue
        with pytest.raises(StoreDamaged) as info:
            damaged.read(tile * TILE, TILE)
        (found,) = info.value.damage
        assert (found.array, found.key) == (array, "c/" + "/".join(map(str, coords)))
        assert found.block == coords[1] and found.texels == (tile * TILE, (tile + 1) * TILE)
        assert f"{bad}: damaged chunk {array}/c/" in str(info.value) and "\n" not in str(info.value)
    if kind in ("missing", "empty"):   # the file listing finds these without reading a chunk
        assert [(d.array, d.key) for d in damaged.scan()] == [(array, "c/" + "/".join(map(str, coords)))]


@pytest.mark.parametrize("array,coords,kind", [("ratio", (1, 2, 0), "missing"), ("flags", (2, 1), "corrupt"),
                                               ("ratio", (3, 0, 0), "truncated"), ("counts", (0, 0), "missing")])
def test_a_damaged_chunk_is_written_again_from_the_capture(root, store, reference, array, coords, kind, caplog):
    """With the capture at hand the fit writes the chunk's light block again and gives the maps of the
    undamaged store bit for bit (a deleted chunk once gave 256 wrong texels with exit 0)."""
    bad = _copy(store, root / f"repair_{array}_{kind}")
    _damage(_chunk(bad, array, coords), kind)
    with _fit_mode(root), caplog.at_level(logging.WARNING, logger="fitting.ingest"):
        out = fit_store(bad, root / f"btf_repair_{array}_{kind}", FitSettings(chunk=TILE), pyramid=False,
                        progress=False)
    assert_same_maps(out, reference, levels=1)
    assert f"{array}/c/{'/'.join(map(str, coords))}" in caplog.text and "again" in caplog.text
    assert open_store(bad).scan() == []


@pytest.mark.parametrize("kind", ["missing", "corrupt", "changed"])
def test_without_its_capture_a_damaged_store_stops_with_one_line(root, store, capture, kind):
    """No capture (moved away) or a capture changed since the ingest: the fit stops naming the store and
    the chunk, with no BTF that looks complete; `fitting fit` exits 2 with that one line."""
    bad = _copy(store, root / f"orphan_{kind}")
    _damage(_chunk(bad, "ratio", (2, 1, 0)), "missing" if kind != "corrupt" else "corrupt")
    info = json.loads((bad / "store.json").read_text())
    if kind == "changed":
        moved = _copy(capture, root / "capture_changed")
        image = next((moved / "images").glob("*.png"))
        os.utime(image, ns=(image.stat().st_atime_ns, image.stat().st_mtime_ns + 10**9))
        info["capture"] = str(moved)
    else:
        info["capture"] = str(root / "no_such_capture")
    (bad / "store.json").write_text(json.dumps(info))
    out = root / f"btf_orphan_{kind}"
    with _fit_mode(root):
        code, err = cli(fitting_main, "fit", bad, "--out", out, "--chunk", TILE, "--no-pyramid")
    assert code == EXIT_INPUT
    assert_one_line(err, f"{bad}: damaged chunk ratio/c/2/1/0", "changed" if kind == "changed" else "not at hand")
    assert not (out / "btf.json").exists()


def test_ingest_on_a_complete_store_writes_its_damage_again(root, store, capture):
    """`fitting ingest` rerun on a complete store whose file listing shows damage rewrites it: the arrays
    come back equal to the undamaged store's."""
    import zarr

    bad = _copy(store, root / "reingest")
    _damage(_chunk(bad, "flags", (1, 2)), "missing")
    _damage(_chunk(bad, "mask", (0,)), "empty")
    ingest_capture(capture, bad, tile=TILE, light_block=LIGHT_BLOCK, progress=False)
    assert open_store(bad).scan() == []
    for name in ("ratio", "flags", "counts", "mask"):
        np.testing.assert_array_equal(zarr.open_group(str(bad), mode="r")[name][:],
                                      zarr.open_group(str(store), mode="r")[name][:], err_msg=name)


def test_store_damage_crosses_process_boundaries(store):
    """A Dask worker returns the damage it found to the driver: `StoreDamaged` pickles with its chunks."""
    import pickle

    with pytest.raises(StoreDamaged) as info:
        raise StoreDamaged(store, [open_store(store).chunk_damage("ratio", (1, 2, 0), "missing")])
    back = pickle.loads(pickle.dumps(info.value))
    assert type(back) is StoreDamaged and str(back) == str(info.value) and back.damage == info.value.damage


FIELDS = [("size", [4, 16], "recorded in"), ("size", [8, 7], "56 texels"), ("size", [16, 16], "256 texels"),
          ("n_lights", 11, "light count"), ("tile", 8, "chunk of texels"), ("light_block", 3, "chunk of lights"),
          ("dtype", "float32", "ratio dtype"), ("light_dirs", [[0, 0, 1]], "1 directions"),
          ("size", "8x8", "expected [H, W]")]


@pytest.mark.parametrize("field,value,problem", FIELDS)
def test_store_json_is_checked_against_the_arrays(root, store, field, value, problem):
    """Each metadata field edited: refused when the store is opened, before any tile is fitted (a
    size of [16, 64] on a 32 x 32 store once gave a complete-looking 16 x 64 BTF with exit 0)."""
    bad = _copy(store, root / f"meta_{field}_{str(value).replace(' ', '')}")
    info = json.loads((bad / "store.json").read_text())
    info[field] = value
    (bad / "store.json").write_text(json.dumps(info))
    with pytest.raises(InputError) as error:
        open_store(bad)
    assert any(line.startswith(f"{bad / 'store.json'}: {field}:") and problem in line
               for line in str(error.value).splitlines()), str(error.value)
    out = root / f"btf_meta_{field}"
    code, err = cli(fitting_main, "fit", bad, "--out", out, "--chunk", TILE)
    assert code == EXIT_INPUT and "Traceback" not in err and f"{field}:" in err
    assert not out.exists()


def test_a_version_1_store_is_refused(root, store):
    bad = _copy(store, root / "version1")
    info = json.loads((bad / "store.json").read_text())
    info["version"] = 1
    (bad / "store.json").write_text(json.dumps(info))
    with pytest.raises(InputError, match="unsupported store version 1"):
        open_store(bad)


# --- one line for every failure -----------------------------------------------------------------------------------

def test_disk_full_while_fitting_exits_3_and_resumes(root, store, reference, monkeypatch):
    """ENOSPC at the third tile's checkpoint: one line naming that file, exit 3, nothing complete; the
    rerun with room resumes from the two tiles written and gives the reference maps."""
    import fitting.checkpoint

    out = root / "btf_full"
    real, saved = fitting.checkpoint.np.savez, []

    def savez(file, **arrays):
        if len(saved) == 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        saved.append(file)
        real(file, **arrays)

    monkeypatch.setattr(fitting.checkpoint.np, "savez", savez)
    with _fit_mode(root):
        code, err = cli(fitting_main, "fit", store, "--out", out, "--chunk", TILE, "--no-pyramid")
    assert code == EXIT_MACHINE
    assert_one_line(err, f"{out / '.partial' / 'chunk_000002.npz'}: No space left on device")
    assert not (out / "btf.json").exists() and len(list((out / ".partial").glob("chunk_*.npz"))) == 2
    assert not [p for p in (out / ".partial").iterdir() if ".tmp" in p.name]   # the temporary went with the error
    monkeypatch.setattr(fitting.checkpoint.np, "savez", real)
    with _fit_mode(root):
        code, err = cli(fitting_main, "fit", store, "--out", out, "--chunk", TILE, "--no-pyramid")
    assert code == 0, err
    assert_same_maps(out, reference, levels=1)


def test_disk_full_while_writing_levels_leaves_no_btf_json(root, store, reference, monkeypatch):
    """ENOSPC writing level 1 of the pyramid (OpenEXR's RuntimeError, as a full disk gives it): exit 3,
    level 0 on disk but no `btf.json`; readers refuse the directory; the rerun completes it."""
    import OpenEXR

    out = root / "btf_full_levels"
    real = OpenEXR.File.write

    def write(self, path):
        if ".level_01." in str(path):
            raise RuntimeError(f'Failed to write pixel data to image file "{path}". No space left on device.')
        return real(self, path)

    monkeypatch.setattr(OpenEXR.File, "write", write)
    with _fit_mode(root):
        code, err = cli(fitting_main, "fit", store, "--out", out, "--chunk", TILE)
    assert code == EXIT_MACHINE
    assert_one_line(err, f"{out / 'level_01.exr'}: No space left on device")
    assert (out / "level_00.exr").is_file() and not (out / "btf.json").exists()
    assert not [p for p in out.iterdir() if ".tmp" in p.name]
    code, err = cli(fitting_main, "relight", out, "--theta", 10, "--phi", 0, "--out", root / "relit.png")
    assert code == EXIT_INPUT
    assert_one_line(err, f"{out / 'btf.json'}: missing: the BTF directory is incomplete")
    monkeypatch.setattr(OpenEXR.File, "write", real)
    with _fit_mode(root):
        assert cli(fitting_main, "fit", store, "--out", out, "--chunk", TILE)[0] == 0
    assert_same_maps(out, reference)


@pytest.mark.parametrize("number", [errno.EROFS, errno.EACCES])
def test_read_only_output_exits_3(root, store, monkeypatch, number):
    """A read-only file system or a directory without write permission (injected where the lock file is
    created: tests may run as root, whom permissions do not stop): one line naming it, exit 3."""
    import jaxrender.io._lock as lock

    real = lock.os.open

    def refuse(path, flags, *args):
        if str(path).endswith(LOCK_NAME) and flags & os.O_CREAT:
            raise OSError(number, os.strerror(number), str(path))
        return real(path, flags, *args)

    monkeypatch.setattr(lock.os, "open", refuse)
    out = root / f"btf_readonly_{number}"
    code, err = cli(fitting_main, "fit", store, "--out", out, "--chunk", TILE)
    assert code == EXIT_MACHINE
    assert_one_line(err, f"{out / LOCK_NAME}: {os.strerror(number)}")
    assert not out.exists()


@pytest.mark.parametrize("command", ["fit", "ingest", "pyramid"])
def test_an_existing_file_as_output_exits_2(root, store, capture, command):
    target = root / f"a_file_{command}"
    target.write_text("keep")
    args = {"fit": ["fit", store, "--out", target], "ingest": ["ingest", capture, "--store", target],
            "pyramid": ["pyramid", target]}[command]
    code, err = cli(fitting_main, *args)
    assert code == EXIT_INPUT
    assert_one_line(err, str(target))
    assert target.read_text() == "keep"


def test_memory_and_internal_errors_are_one_line(root, store, monkeypatch):
    """Out of memory: exit 3; a bug (any other exception): exit 1 with how to see the traceback, which
    `--debug` or JAXRENDER_DEBUG=1 prints above the same line."""
    import jaxrender.app.cli.fit as fit_command

    def out_of_memory(*args, **kwargs):
        raise MemoryError()

    def bug(*args, **kwargs):
        raise KeyError("a bug")

    monkeypatch.setattr(fit_command, "fit_capture", out_of_memory)
    code, err = cli(fitting_main, "fit", store, "--out", root / "btf_oom")
    assert code == EXIT_MACHINE
    assert_one_line(err, f"{root / 'btf_oom'}: out of memory")
    monkeypatch.setattr(fit_command, "fit_capture", bug)
    code, err = cli(fitting_main, "fit", store, "--out", root / "btf_bug")
    assert code == EXIT_INTERNAL
    assert_one_line(err, "internal error: KeyError", "--debug", "JAXRENDER_DEBUG=1")
    code, err = cli(fitting_main, "fit", store, "--out", root / "btf_bug", "--debug")
    assert code == EXIT_INTERNAL and "Traceback" in err and err.strip().splitlines()[-1].startswith("fitting fit:")
    monkeypatch.setenv("JAXRENDER_DEBUG", "1")
    code, err = cli(fitting_main, "fit", store, "--out", root / "btf_bug")
    assert code == EXIT_INTERNAL and "Traceback" in err


# --- complete means complete ----------------------------------------------------------------------------------------

KILL_AFTER_LEVEL0 = """
import os, signal, sys
import jaxrender.io._btf as btf_io
from jaxrender.io import atomic_path
from fitting import FitSettings, fit_store
real = btf_io.write_exr
def write_exr(path, channels):
    if path.name == "level_01.exr":   # level 0 is written: die inside the next level's atomic write
        with atomic_path(path) as tmp:
            tmp.write_bytes(b"half")
            os.kill(os.getpid(), signal.SIGKILL)
    return real(path, channels)
btf_io.write_exr = write_exr
fit_store(sys.argv[1], sys.argv[2], FitSettings(chunk={chunk}), progress=False)
"""


def test_killed_between_level0_and_the_pyramid(root, store, reference):
    """SIGKILL after level 0 is written, inside the next level's write: no `btf.json`, so every reader
    refuses the directory with one line (`read_btf`, `fitting relight`, `fitting report`, `fitting
    pyramid`, `jaxrender noh --btf`); the rerun completes it with every level, bit for bit, and leaves
    no temporaries (btf.json once listed level 0 only for half the run, and readers took it)."""
    out = root / "btf_killed"
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(KILL_AFTER_LEVEL0.format(chunk=TILE)), str(store),
                           str(out)], env=_env(root), capture_output=True, timeout=600)
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()[-3000:]
    assert (out / "level_00.exr").is_file() and not (out / "btf.json").exists()
    assert [p.name for p in out.glob(".level_01.*.tmp.exr")]   # what a killed atomic write leaves
    with pytest.raises(InputError, match="incomplete"):
        read_btf(out)
    for main, args in ((fitting_main, ["relight", out, "--theta", 10, "--phi", 0, "--out", root / "x.png"]),
                       (fitting_main, ["report", root / "capture", out]),
                       (fitting_main, ["pyramid", out]),
                       (jaxrender_main, ["noh", "--out", root / "noh", "--btf", f"satin={out}"])):
        code, err = cli(main, *args)
        assert code == EXIT_INPUT
        assert_one_line(err, f"{out / 'btf.json'}: missing: the BTF directory is incomplete")
    with _fit_mode(root):
        fit_store(store, out, FitSettings(chunk=TILE), progress=False)
    assert_same_maps(out, reference)
    assert len(read_btf(out, load=False)[0]["levels"]) == LEVELS
    assert sorted(p.name for p in out.iterdir()) == ["btf.json"] + [f"level_0{i}.exr" for i in range(LEVELS)] + \
        ["previews"]


def test_leftovers_of_a_killed_run_are_removed(root, store, reference):
    """The temporaries a SIGKILL leaves (`.level_00.*.tmp.exr`, `.btf.*.tmp.json`, a checkpoint's, the
    previews') are gone after the resumed run; an unrelated dot file stays."""
    out = root / "btf_leftovers"
    (out / ".partial").mkdir(parents=True)
    (out / "previews").mkdir()
    names = [".level_00.k3j_x9a1.tmp.exr", ".btf.ab12cd34.tmp.json", ".partial/.chunk_000001.zzzzzzzz.tmp.npz",
             "previews/.rho_d.q1w2e3r4.tmp.png"]
    for name in names:
        (out / name).write_bytes(b"")
    (out / ".notes").write_text("mine")
    with _fit_mode(root):
        fit_store(store, out, FitSettings(chunk=TILE), pyramid=False, progress=False)
    assert not [name for name in names if (out / name).exists()]
    assert (out / ".notes").read_text() == "mine" and not (out / LOCK_NAME).exists()
    assert_same_maps(out, reference, levels=1)


def test_remove_temporaries_matches_atomic_path(tmp_path):
    """`remove_temporaries` knows `atomic_path`'s names (a writer killed inside the block leaves one)."""
    with pytest.raises(KeyboardInterrupt), atomic_path(tmp_path / "level_00.exr") as tmp:
        name = tmp.name
        raise KeyboardInterrupt   # atomic_path removes its temporary: put one of that name back, as a kill leaves it
    (tmp_path / name).write_bytes(b"")
    (tmp_path / "level_00.exr").write_bytes(b"done")
    assert remove_temporaries(tmp_path) == [tmp_path / name]
    assert name.startswith(".level_00.") and name.endswith(".tmp.exr")
    assert [p.name for p in tmp_path.iterdir()] == ["level_00.exr"]


# --- one writer per output --------------------------------------------------------------------------------------------

HOLD = """
import sys, time
from jaxrender.io import output_lock
with output_lock(sys.argv[1]):
    print("held", flush=True)
    time.sleep(120)
"""


def test_a_second_writer_stops_at_once(root, store, capture):
    """While another process holds BTF_DIR's lock, `fitting fit` and `fitting ingest` on it stop with one
    line naming that process (exit 4), and touch nothing."""
    out = root / "btf_busy"
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        owner = json.loads((out / LOCK_NAME).read_text())
        assert owner["pid"] == holder.pid and owner["host"]
        for args in (["fit", store, "--out", out, "--chunk", TILE], ["ingest", capture, "--store", out]):
            code, err = cli(fitting_main, *args)
            assert code == EXIT_BUSY
            assert_one_line(err, f"{out}: pid {holder.pid} on {owner['host']}", "is writing it")
        with pytest.raises(OutputBusy):
            ingest_capture(capture, out, progress=False)
        assert sorted(p.name for p in out.iterdir()) == [LOCK_NAME]
    finally:
        holder.kill()
        holder.wait()
    # the holder died without releasing: its lock file stays, the kernel freed the lock, the next writer takes it
    assert (out / LOCK_NAME).is_file()
    with output_lock(out) as path:
        assert json.loads(path.read_text())["pid"] == os.getpid()
    assert not (out / LOCK_NAME).exists()


def test_a_stale_lock_file_is_taken_over_and_the_lock_is_reentrant(tmp_path):
    """A lock file naming a dead process (left by a crash, no one holding it) is taken over; this process
    may take its own lock again (a fit ingests, fits and builds its pyramid under one lock)."""
    out = tmp_path / "out"
    out.mkdir()
    (out / LOCK_NAME).write_text(json.dumps({"pid": 2**22 + 12345, "host": "elsewhere", "started": "then"}))
    with output_lock(out):
        with output_lock(out):
            assert json.loads((out / LOCK_NAME).read_text())["pid"] == os.getpid()
        assert (out / LOCK_NAME).is_file()
    assert not (out / LOCK_NAME).exists()


def test_exit_codes_in_readme():
    """README's table of exit codes names the ones the driver uses."""
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    for code in (EXIT_INTERNAL, EXIT_INPUT, EXIT_MACHINE, EXIT_BUSY):
        assert f"| {code} |" in readme


def test_write_exr_reports_a_full_disk_as_oserror(tmp_path, monkeypatch):
    import OpenEXR

    def write(self, path):
        raise RuntimeError(f'Failed to write pixel data to image file "{path}". No space left on device.')

    monkeypatch.setattr(OpenEXR.File, "write", write)
    with pytest.raises(OSError) as info:
        write_exr(tmp_path / "x.exr", np.zeros((2, 2), np.float32))
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(tmp_path / "x.exr")
    assert list(tmp_path.iterdir()) == []

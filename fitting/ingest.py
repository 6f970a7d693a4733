"""`ingest_capture(CAPTURE_DIR, STORE_DIR)`: one streaming pass from a capture to an observation store.

Validation first, before anything is written: the manifest and every image's header (existence,
type, bit depth, channels, size; `load_capture(headers_only=True)`) and the white board's pixels.
Then the lights are read in blocks of `light_block` lights (every exposure of each, full frames:
the block is sized so that it, the next block read ahead, and the merge's buffers fit the memory
budget), each block merged and white-normalised by `fitting.hdr.observe` (the function the
in-memory `merge_capture` uses) and written as one column of chunks of the store
(`fitting.store`). A pixel problem found in a block (a truncated file, NaN or Inf in an EXR)
stops the pass with one line per problem of that block (`CaptureError`), and the store is removed.

Resumable: a marker per finished light block in `STORE_DIR/.ingest/`; a rerun on the same store
with the same capture and settings skips the finished blocks (chunks are written whole, once per
block, so an interrupted block is simply written again). `store.json` is written last.
One writer at a time (`STORE_DIR/.lock`, `jaxrender.io.output_lock`). `repair_store` writes the
light blocks of damaged chunks again from the capture (docs/formats.md, "Integrity").
"""

from __future__ import annotations

import concurrent.futures
import json
import logging
import os
import re
import shutil
import time
from pathlib import Path

import numpy as np

from jaxrender.io import InputError, atomic_path, output_lock, remove_temporaries

from .capture import MAX_IMAGE_PROBLEMS, Capture, CaptureError, load_capture
from .checkpoint import fingerprint
from .hdr import observe, thresholds
from .store import (
    DARK,
    DEFAULT_STORE_DTYPE,
    MARKER,
    SATURATED,
    STORE_DTYPES,
    STORE_FORMAT,
    STORE_VERSION,
    VALID,
    ChunkDamage,
    ObservationStore,
    StoreDamaged,
    create_arrays,
    is_store,
    open_store,
    store_entries,
    write_marker,
)

__all__ = ["ingest_capture", "repair_store", "light_block_for", "DEFAULT_MEMORY_GB", "DEFAULT_TILE", "FLOAT16_MAX"]

log = logging.getLogger(__name__)

DEFAULT_MEMORY_GB = 1.0   # budget of a light block and its merge buffers (the process adds JAX, ~0.5 GB)
DEFAULT_TILE = 4096       # texels per chunk row: the fit's default --chunk, so a fit tile reads whole chunks
FLOAT16_MAX = 65504.0     # a ratio above this (never met: R is ~1 for white, ~100 for a sharp lobe) is clipped
PROGRESS = ".ingest"


def light_block_for(size: tuple[int, int], n_exposures: int, memory_gb: float = DEFAULT_MEMORY_GB) -> int:
    """Lights per block so that a block's buffers fit `memory_gb`.

    Per light and texel: the codes of every exposure twice (the block being merged and the one read
    ahead, float32 RGB: 2 x 12 E bytes), their copy into JAX (12 E), the merge's output and
    temporaries (ratio RGB float32 and three flags, then the stored dtype and the flag byte: ~40 bytes).
    """
    per_light = size[0] * size[1] * (36 * n_exposures + 40)
    return max(1, int(memory_gb * 2**30 // per_light))


def _settings(dtype: str, tile: int, block: int) -> dict:
    """The settings a store's fingerprint covers besides its capture."""
    return {"format": STORE_FORMAT, "version": STORE_VERSION, "dtype": dtype, "tile": tile, "light_block": block}


def _capture_fingerprint(capture: Capture, settings: dict) -> str:
    """Manifest text, every image's size and modification time, and the settings of the store (not the
    paths, which the manifest names: the same capture reached by another path has the same fingerprint)."""
    masks = (capture.mask,) if capture.mask is not None else ()
    stats = (f"{path.name}:{path.stat().st_size}:{path.stat().st_mtime_ns}"
             for path in (*capture.white_images, *(p for images in capture.light_images for p in images), *masks))
    return fingerprint(settings, (capture.root / "capture.json").read_bytes(), *stats)


def _read_config(store_dir: Path) -> dict | None:
    try:
        return json.loads((store_dir / PROGRESS / "config.json").read_text())
    except (OSError, ValueError):
        return None


def _start(store_dir: Path, fingerprint: str) -> str:
    """'done' (a complete store of this capture and these settings), 'resume', or 'new'."""
    if not store_entries(store_dir):
        return "new"
    if (store_dir / MARKER).is_file():
        try:
            if json.loads((store_dir / MARKER).read_text()).get("fingerprint") == fingerprint:
                return "done"
        except (OSError, ValueError):
            pass
    elif (_read_config(store_dir) or {}).get("fingerprint") == fingerprint:
        return "resume"
    if not is_store(store_dir):
        raise InputError(store_dir, "exists and is not an observation store or an empty directory; choose a new one")
    for entry in store_entries(store_dir):  # another capture or other settings: start again (the lock stays)
        shutil.rmtree(entry) if entry.is_dir() and not entry.is_symlink() else entry.unlink()
    return "new"


# zarr writes a chunk to "NAME.<32 hex digits>.partial" and renames it: a killed writer leaves those
_ZARR_PARTIAL = re.compile(r"\.[0-9a-f]{32}\.partial$")


def _remove_leftovers(store_dir: Path) -> None:
    """The temporaries a killed ingest left (store.json's, .ingest/'s and zarr's chunk temporaries)."""
    remove_temporaries(store_dir)
    remove_temporaries(store_dir / PROGRESS)
    for name in ("ratio", "flags", "counts"):
        for root, _, files in os.walk(store_dir / name):
            for file in files:
                if _ZARR_PARTIAL.search(file):
                    Path(root, file).unlink(missing_ok=True)


def _create(store_dir: Path, capture: Capture, *, dtype: str, tile: int, block: int, fingerprint: str) -> None:
    (store_dir / PROGRESS).mkdir(parents=True)
    t, n = capture.size[0] * capture.size[1], capture.n_lights
    create_arrays(store_dir, size=capture.size, n_lights=n, tile=min(tile, t), light_block=min(block, n), dtype=dtype)
    _write_mask(store_dir, capture)
    with atomic_path(store_dir / PROGRESS / "config.json") as tmp:  # last: the arrays exist
        tmp.write_text(json.dumps({"fingerprint": fingerprint}))


def _read_block(capture: Capture, pool, lights: range, block: int) -> np.ndarray:
    """Codes `block E H W 3` of `lights` (zero-padded to `block`: one shape, one compilation), or
    `CaptureError` with every pixel problem of the block."""
    paths = [p for i in lights for p in capture.light_images[i]]
    results = list(pool.map(capture.read_checked, paths))
    problems = [line for _, lines in results for line in lines]
    if problems:
        if len(problems) > MAX_IMAGE_PROBLEMS:
            extra = len(problems) - MAX_IMAGE_PROBLEMS
            problems = problems[:MAX_IMAGE_PROBLEMS] + [f"{capture.root}: ... and {extra} more image problems"]
        raise CaptureError(problems)
    h, w = capture.size
    codes = np.zeros((block, len(capture.exposures_s), h, w, 3), np.float32)
    codes[:len(lights)] = np.stack([c for c, _ in results]).reshape(len(lights), -1, h, w, 3)
    return codes


def _write_mask(store_dir: Path, capture: Capture) -> None:
    """The capture's mask (1 for the texels to fit) into the store's `mask` array."""
    import zarr

    zarr.open_group(str(store_dir), mode="r+")["mask"][:] = capture.read_mask().reshape(-1).astype(np.uint8)


def _write_counts(store_dir: Path) -> None:
    """Per-texel counts from the flags (streamed over texel tiles)."""
    import zarr

    group = zarr.open_group(str(store_dir), mode="r+")
    flags, counts = group["flags"], group["counts"]
    t = flags.shape[0]
    step = counts.chunks[0]
    for start in range(0, t, step):
        f = np.asarray(flags[start:start + step])
        counts[start:start + step] = np.stack([np.sum((f & bit) > 0, axis=1, dtype=np.int32)
                                               for bit in (VALID, SATURATED, DARK)], axis=1)


def _finish(store_dir: Path, capture: Capture, *, tile: int, info: dict) -> None:
    """The counts, then `store.json` last."""
    _write_counts(store_dir)
    write_marker(store_dir, info)
    shutil.rmtree(store_dir / PROGRESS, ignore_errors=True)


def ingest_capture(capture_dir: str | os.PathLike, store_dir: str | os.PathLike, *, dtype: str = DEFAULT_STORE_DTYPE,
                   memory_gb: float = DEFAULT_MEMORY_GB, tile: int = DEFAULT_TILE, light_block: int | None = None,
                   progress: bool | None = None, workers: int = 4, on_block=None) -> Path:
    """Capture directory -> observation store `store_dir` (module docstring); returns `store_dir`.

    `dtype`: "float16" (default, half the disk and reads; its cost in fit accuracy is in
    RESULTS.md) or "float32" (the fit is then bit-identical to the in-memory path). `light_block`:
    lights per block (default: from `memory_gb`, `light_block_for`). `tile`: texels per chunk.
    Raises `CaptureError` (an `InputError`) for a malformed capture: before anything is written
    for the manifest and the headers, and with the store removed for pixel problems.
    `on_block(i)` is called after each light block is stored (tests). Holds `STORE_DIR/.lock` while it
    writes (`OutputBusy` when another process holds it).
    """
    if dtype not in STORE_DTYPES:
        raise ValueError(f"unknown store dtype {dtype!r}: use one of {STORE_DTYPES}")
    if tile < 1 or (light_block is not None and light_block < 1) or memory_gb <= 0:
        raise ValueError("tile, light_block and memory_gb must be positive")
    store_dir = Path(store_dir)
    t0 = time.perf_counter()
    with output_lock(store_dir):
        try:
            return _ingest(capture_dir, store_dir, dtype=dtype, memory_gb=memory_gb, tile=tile,
                           light_block=light_block, progress=progress, workers=workers, on_block=on_block, t0=t0)
        except OSError as error:
            if error.filename is None:   # zarr's failed chunk write names no file: name the store
                error.filename = os.fspath(store_dir)
            raise


def _ingest(capture_dir, store_dir: Path, *, dtype, memory_gb, tile, light_block, progress, workers, on_block,
            t0) -> Path:
    """`ingest_capture` while holding the store's lock."""
    from tqdm.auto import tqdm

    capture = load_capture(capture_dir, headers_only=True, workers=workers)
    pool = concurrent.futures.ThreadPoolExecutor(max_workers=max(1, workers))
    prefetch = concurrent.futures.ThreadPoolExecutor(max_workers=1)  # apart from `pool`: no deadlock
    state = None
    try:
        white_results = list(pool.map(capture.read_checked, capture.white_images))
        problems = [line for _, lines in white_results for line in lines]
        if problems:  # still nothing written
            raise CaptureError(problems)
        mask_problems = [] if capture.mask is None else capture.read_checked(capture.mask)[1]
        if mask_problems:
            raise CaptureError(mask_problems)
        n_exp = len(capture.exposures_s)
        block = min(light_block or light_block_for(capture.size, n_exp, memory_gb), capture.n_lights)
        tile = min(tile, capture.size[0] * capture.size[1])
        settings = _settings(dtype, tile, block)
        fingerprint_ = _capture_fingerprint(capture, settings)
        state = _start(store_dir, fingerprint_)
        _remove_leftovers(store_dir)
        if state == "done":   # complete: rewrite what the file listing shows damaged, if anything
            store = open_store(store_dir)
            damage = store.scan()
            if damage:
                _repair(store, capture, damage, white_results, pool, prefetch, tqdm=tqdm, progress=progress)
            return store_dir
        if state == "new":
            _create(store_dir, capture, dtype=dtype, tile=tile, block=block, fingerprint=fingerprint_)
        white = np.stack([c for c, _ in white_results]) if capture.has_white else None
        exposures = np.asarray(capture.exposures_s, np.float32)
        reflectance = np.asarray(capture.white_reflectance, np.float32) if capture.has_white else None
        blocks = [range(s, min(s + block, capture.n_lights)) for s in range(0, capture.n_lights, block)]
        todo = [i for i in range(len(blocks)) if not (store_dir / PROGRESS / f"block_{i:06d}").exists()]
        _store_blocks(store_dir, capture, blocks, todo, white, exposures, reflectance, pool, prefetch,
                      dtype=dtype, block=block, progress=progress, tqdm=tqdm, on_block=on_block)
        info = {**settings, "size": list(capture.size), "n_lights": capture.n_lights,
                "light_dirs": capture.light_dirs.tolist(), "view_dir": capture.view_dir.tolist(),
                "light_angles": np.asarray(capture.light_angles).tolist(), "view_angles": list(capture.view_angles),
                "exposures_s": list(capture.exposures_s), "response": capture.response,
                "encoding": capture.encoding, "saturation": capture.saturation,
                "white_reflectance": None if not capture.has_white else capture.white_reflectance.tolist(),
                "light_intensities": None if capture.light_intensities is None
                else capture.light_intensities.tolist(), "mask": capture.mask is not None, "capture": str(capture.root),
                "fingerprint": fingerprint_, "ingest_seconds": round(time.perf_counter() - t0, 3)}
        _finish(store_dir, capture, tile=tile, info=info)
        return store_dir
    except CaptureError:
        if state in ("new", "resume") and is_store(store_dir):  # a pixel problem: no store of a bad capture
            for entry in store_entries(store_dir):
                shutil.rmtree(entry) if entry.is_dir() and not entry.is_symlink() else entry.unlink()
        raise
    finally:
        prefetch.shutdown(wait=True, cancel_futures=True)
        pool.shutdown(wait=True, cancel_futures=True)


def repair_store(store: ObservationStore, damage: list[ChunkDamage] | None = None, *, progress: bool | None = False,
                 workers: int = 4) -> None:
    """Write again every light block holding a damaged chunk of `ratio` or `flags`, from the store's
    capture, then the counts from the flags (`damage`: what `fitting.store.StoreDamaged` lists; None:
    the chunks the file listing shows missing or truncated, `ObservationStore.scan`). The merge
    is deterministic: the blocks come back bit for bit. Raises `StoreDamaged` naming the chunk when a
    block is damaged and the capture is no longer at hand or has changed since the ingest (its
    fingerprint differs). Holds the store's lock while it writes."""
    from tqdm.auto import tqdm

    damage = store.scan() if damage is None else damage
    if not damage:
        return
    if all(d.array == "counts" for d in damage):   # only counts: they come from the flags
        with output_lock(store.path):
            _write_counts(store.path)
        log.warning("%s: wrote the counts again from the flags (damaged: %s)", store.path, damage[0].describe())
        return
    where = store.info.get("capture")
    remedy = f"the store's capture {where} is not at hand to write it again"
    try:
        capture = load_capture(where, headers_only=True, workers=workers) if where else None
    except InputError as error:
        raise StoreDamaged(store.path, damage, f"{remedy} ({str(error).splitlines()[0]})") from None
    if capture is None:
        raise StoreDamaged(store.path, damage, remedy)
    info = store.info
    settings = _settings(info["dtype"], int(info["tile"]), int(info["light_block"]))
    if _capture_fingerprint(capture, settings) != store.fingerprint:
        raise StoreDamaged(store.path, damage, f"its capture {capture.root} changed since the ingest: "
                                               "ingest it again into a new store")
    with output_lock(store.path), concurrent.futures.ThreadPoolExecutor(max_workers=max(1, workers)) as pool, \
            concurrent.futures.ThreadPoolExecutor(max_workers=1) as prefetch:
        white_results = list(pool.map(capture.read_checked, capture.white_images))
        problems = [line for _, lines in white_results for line in lines]
        if problems:
            raise CaptureError(problems)
        _repair(store, capture, damage, white_results, pool, prefetch, tqdm=tqdm, progress=progress)


def _repair(store: ObservationStore, capture: Capture, damage: list[ChunkDamage], white_results, pool, prefetch, *,
            tqdm, progress) -> None:
    """Write again the mask (when damaged), the light blocks of damaged chunks, then the counts."""
    if any(d.array == "mask" for d in damage):
        _write_mask(store.path, capture)
    block = int(store.info["light_block"])
    blocks = [range(s, min(s + block, capture.n_lights)) for s in range(0, capture.n_lights, block)]
    todo = sorted({d.block for d in damage if d.block is not None})
    white = np.stack([c for c, _ in white_results]) if capture.has_white else None
    reflectance = np.asarray(capture.white_reflectance, np.float32) if capture.has_white else None
    _store_blocks(store.path, capture, blocks, todo, white, np.asarray(capture.exposures_s, np.float32), reflectance,
                  pool, prefetch, dtype=store.dtype, block=block, progress=progress, tqdm=tqdm, on_block=None,
                  markers=False)
    _write_counts(store.path)
    lights = ", ".join(f"{blocks[i].start}..{blocks[i].stop - 1}" for i in todo) or "none"
    log.warning("%s: wrote lights %s again from the capture %s, and the counts (damaged: %s%s)", store.path, lights,
                capture.root, damage[0].describe(), f" and {len(damage) - 1} more" if len(damage) > 1 else "")


def _store_blocks(store_dir, capture, blocks, todo, white, exposures, reflectance, pool, prefetch, *, dtype, block,
                  progress, tqdm, on_block, markers: bool = True) -> None:
    """Read (one block ahead), merge and write every light block of `todo`."""
    import zarr

    group = zarr.open_group(str(store_dir), mode="r+")
    ratio_arr, flags_arr = group["ratio"], group["flags"]
    t = capture.size[0] * capture.size[1]
    mask = capture.read_mask()   # what the store's `mask` holds, read from the capture: never a damaged chunk
    done = sum(len(b) for i, b in enumerate(blocks) if i not in set(todo))
    bar = tqdm(total=capture.n_lights, initial=done, unit="light", desc="ingest",
               disable=None if progress is None else not progress)
    future = prefetch.submit(_read_block, capture, pool, blocks[todo[0]], block) if todo else None
    for k, i in enumerate(todo):
        codes = future.result()
        if k + 1 < len(todo):  # read the next block while this one merges and is written
            future = prefetch.submit(_read_block, capture, pool, blocks[todo[k + 1]], block)
        n = len(blocks[i])
        intensities = np.ones((block, 3), np.float32)
        intensities[:n] = capture.intensities()[blocks[i].start:blocks[i].stop]
        ratio, valid, saturated, dark = observe(codes, exposures, white, reflectance, response=capture.merge_response,
                                                intensities=intensities, mask=mask,
                                                levels=thresholds(capture.encoding, capture.saturation))
        del codes
        lights = slice(blocks[i].start, blocks[i].stop)
        r = np.asarray(ratio).reshape(t, block, 3)[:, :n]
        if dtype == "float16":
            r = np.minimum(r, FLOAT16_MAX)
        ratio_arr[:, lights] = r.astype(dtype)
        flags = np.asarray(valid, np.uint8) * np.uint8(VALID)
        flags |= np.asarray(saturated, np.uint8) * np.uint8(SATURATED)
        flags |= np.asarray(dark, np.uint8) * np.uint8(DARK)
        flags_arr[:, lights] = flags.reshape(t, block)[:, :n]
        if markers:
            (store_dir / PROGRESS / f"block_{i:06d}").touch()  # after the block's chunks are written
        bar.update(n)
        if on_block is not None:
            on_block(i)
    bar.close()

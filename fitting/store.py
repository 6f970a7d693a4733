"""The observation store: a capture's merged observations on disk, chunked and compressed (zarr).

`fitting.ingest.ingest_capture` writes it in one streaming pass over the images; the fit engine
(`fitting.engine`) fits it chunk by chunk. Texels are flattened in row-major order (t = row * W +
column), so a chunk of the fit (`--chunk` texels) is one contiguous range of rows of every array:

```
STORE_DIR/zarr.json     zarr v3 group; its attributes record the layout (size, lights, tile, dtype)
STORE_DIR/ratio/        T x L x 3   float16 (default) or float32: observed reflectance, 0 where invalid
STORE_DIR/flags/        T x L       uint8: bit 0 valid, bit 1 a channel saturated, bit 2 a channel dark
STORE_DIR/counts/       T x 3       int32: n_valid, n_saturated, n_dark (written after the last light)
STORE_DIR/mask/         T           uint8: 1 for the texels to fit (the capture's mask; all 1 without one)
STORE_DIR/.ingest/      progress of an unfinished ingest (one marker per finished light block)
STORE_DIR/store.json    written last: format, version, size, lights, view, dtype, chunking, fingerprint
```

Chunks are (`tile` texels) x (`light_block` lights): every chunk is written exactly once by the
ingest (one light block of full frames at a time), and a tile of the fit reads L / light_block
chunks of each array. A directory without `store.json` is an unfinished store: readers refuse it
and a rerun of the ingest resumes it.

The store proves its contents (docs/formats.md, "Integrity"): every chunk carries a CRC-32C of
its bytes, every chunk is written even when it equals the fill value, and the fill values are no
data (NaN ratio, flags 255, counts -1), so a chunk that is missing, truncated or corrupt is found
when it is read (`StoreDamaged`, naming the chunk), never read as zeros. `store.json` is checked
against the arrays and the layout recorded with them when the store is opened.
"""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np

from jaxrender.io import LOCK_NAME, Fields, InputError, InputErrors, atomic_path

from .hdr import ObservationCounts, Observations

__all__ = ["STORE_FORMAT", "STORE_VERSION", "STORE_DTYPES", "DEFAULT_STORE_DTYPE", "ObservationStore",
           "open_store", "is_store", "create_arrays", "ChunkDamage", "StoreDamaged", "VALID", "SATURATED", "DARK"]

STORE_FORMAT = "jaxrender-observations"
STORE_VERSION = 2   # 2: chunk checksums and fill values that are no data (version 1 stores: ingest again)
STORE_DTYPES = ("float16", "float32")
DEFAULT_STORE_DTYPE = "float16"  # benchmarks/capture_scale.py: fit cost of float16 vs float32 (RESULTS.md)
VALID, SATURATED, DARK = 1, 2, 4
MARKER = "store.json"
COUNTS_TILES = 16   # a chunk of `counts` spans this many tiles
# what a chunk that is not on disk reads as: never a value the ingest writes
FILL = {"ratio": float("nan"), "flags": 0xFF, "counts": -1, "mask": 0xFF}
ARRAY_DTYPES = {"flags": "uint8", "counts": "int32", "mask": "uint8"}
MIN_CHUNK_BYTES = 5   # a chunk file holds at least a compressed frame and its 4-byte checksum


def is_store(path: str | os.PathLike) -> bool:
    """Whether `path` is an observation store directory (complete or not), not a capture."""
    path = Path(path)
    return path.is_dir() and ((path / MARKER).is_file() or (path / ".ingest").is_dir()) \
        and not (path / "capture.json").is_file()


def write_marker(store_dir: Path, info: dict) -> None:
    with atomic_path(store_dir / MARKER) as tmp:
        tmp.write_text(json.dumps(info, indent=1) + "\n")


def create_arrays(store_dir: Path, *, size: tuple[int, int], n_lights: int, tile: int, light_block: int,
                  dtype: str) -> None:
    """The empty arrays of a store (chunks with a CRC-32C, fill values that are no data, every chunk
    written) and the layout recorded in the group's attributes."""
    import zarr
    from zarr.codecs import Crc32cCodec, ZstdCodec

    t = size[0] * size[1]
    group = zarr.open_group(str(store_dir), mode="a")   # not "w": that would wipe the directory and its lock
    common = {"compressors": [ZstdCodec(), Crc32cCodec()], "config": {"write_empty_chunks": True}}
    group.create_array("ratio", shape=(t, n_lights, 3), chunks=(tile, light_block, 3), dtype=dtype,
                       fill_value=FILL["ratio"], **common)
    group.create_array("flags", shape=(t, n_lights), chunks=(tile, light_block), dtype="uint8",
                       fill_value=FILL["flags"], **common)
    group.create_array("counts", shape=(t, 3), chunks=(tile * COUNTS_TILES, 3), dtype="int32",
                       fill_value=FILL["counts"], **common)
    group.create_array("mask", shape=(t,), chunks=(tile * COUNTS_TILES,), dtype="uint8", fill_value=FILL["mask"],
                       **common)
    group.attrs["layout"] = {"size": list(size), "n_lights": n_lights, "tile": tile, "light_block": light_block,
                             "dtype": dtype}


@dataclasses.dataclass(frozen=True)
class ChunkDamage:
    """One chunk that is missing, truncated or corrupt: `array`/`key` under the store, the texels and
    lights it holds, and the light block whose ingest writes it (None for `counts`)."""

    array: str
    key: str
    problem: str
    texels: tuple[int, int]
    lights: tuple[int, int] | None
    block: int | None

    def describe(self) -> str:
        lights = f", lights {self.lights[0]}..{self.lights[1] - 1}" if self.lights else ""
        return f"{self.array}/{self.key} ({self.problem}: texels {self.texels[0]}..{self.texels[1] - 1}{lights})"


class StoreDamaged(InputError):
    """Chunks of a store that are missing, truncated or corrupt (`damage`), in one line naming the store
    and the first chunk; `remedy` says what to do."""

    def __init__(self, store_dir: str | os.PathLike, damage: list[ChunkDamage], remedy: str = ""):
        self.damage = list(damage)
        more = f" and {len(damage) - 1} more" if len(damage) > 1 else ""
        remedy = remedy or "rerun `fitting ingest CAPTURE --store STORE` with its capture to rewrite it"
        super().__init__(store_dir, f"damaged chunk {damage[0].describe()}{more}; {remedy}")


class ObservationStore:
    """A complete observation store, opened for reading (see the module docstring).

    `read(start, count)` gives the fit's inputs of texels `start .. start + count - 1` as float32
    (`ratio` `count L 3`, `weight` `count L`, 1 valid / 0 not), exactly what the in-memory
    `Observations` holds for those texels when the store is float32. Every read checks what it
    read: `StoreDamaged` for a chunk that is missing, truncated or corrupt.
    """

    def __init__(self, path: Path, info: dict):
        import zarr

        self.path, self.info = path, info
        self._group = zarr.open_group(str(path), mode="r")
        self._arrays = {}
        for name in FILL:
            try:
                self._arrays[name] = self._group[name]
            except KeyError:
                pass
        _check_layout(self)
        self._ratio, self._flags, self._counts = self._arrays["ratio"], self._arrays["flags"], self._arrays["counts"]
        self.size = (int(info["size"][0]), int(info["size"][1]))
        self.light_dirs = np.asarray(info["light_dirs"], np.float64)
        self.view_dir = np.asarray(info["view_dir"], np.float64)

    @property
    def n_texels(self) -> int:
        return self.size[0] * self.size[1]

    @property
    def n_lights(self) -> int:
        return int(self.light_dirs.shape[0])

    @property
    def fingerprint(self) -> str:
        return str(self.info["fingerprint"])

    @property
    def dtype(self) -> str:
        return str(self.info["dtype"])

    def read(self, start: int, count: int) -> tuple[np.ndarray, np.ndarray]:
        ratio = np.asarray(self._get("ratio", start, count), np.float32)
        weight = (self._get("flags", start, count) & VALID).astype(np.float32)
        return ratio, weight

    def flags(self, start: int, count: int) -> np.ndarray:
        return self._get("flags", start, count)

    def mask(self) -> np.ndarray:
        """`H W` bool: the texels to fit."""
        return self._get("mask", 0, self.n_texels).reshape(self.size) > 0

    def counts(self) -> ObservationCounts:
        """`H W` int32 maps n_valid, n_saturated, n_dark."""
        counts = self._get("counts", 0, self.n_texels).reshape(self.size + (3,))
        return ObservationCounts(counts[..., 0], counts[..., 1], counts[..., 2])

    def observations(self):
        """The whole store as in-memory `fitting.hdr.Observations` (small stores and tests only)."""
        import jax.numpy as jnp

        ratio, weight = self.read(0, self.n_texels)
        h, w = self.size
        counts = self.counts()
        return Observations(ratio=jnp.asarray(ratio.reshape(h, w, self.n_lights, 3)),
                            weight=jnp.asarray(weight.reshape(h, w, self.n_lights)),
                            light_dirs=jnp.asarray(self.light_dirs.astype(np.float32)),
                            view_dir=jnp.asarray(self.view_dir.astype(np.float32)),
                            n_valid=jnp.asarray(counts.n_valid), n_saturated=jnp.asarray(counts.n_saturated),
                            n_dark=jnp.asarray(counts.n_dark), mask=jnp.asarray(self.mask()))

    # --- integrity -------------------------------------------------------------------------------------------

    def chunk_grid(self, name: str) -> list[tuple[int, ...]]:
        """Every chunk's coordinates of array `name`."""
        array = self._arrays[name]
        counts = [-(-n // c) for n, c in zip(array.shape, array.chunks, strict=True)]
        return [tuple(int(i) for i in idx) for idx in np.ndindex(*counts)]

    def chunk_damage(self, name: str, coords: tuple[int, ...], problem: str) -> ChunkDamage:
        array = self._arrays[name]
        tile = array.chunks[0]
        texels = (coords[0] * tile, min((coords[0] + 1) * tile, array.shape[0]))
        if name in ("counts", "mask"):   # per texel: no light block
            return ChunkDamage(name, array.metadata.encode_chunk_key(coords), problem, texels, None, None)
        block = array.chunks[1]
        lights = (coords[1] * block, min((coords[1] + 1) * block, array.shape[1]))
        return ChunkDamage(name, array.metadata.encode_chunk_key(coords), problem, texels, lights, coords[1])

    def scan(self) -> list[ChunkDamage]:
        """Chunks missing or too short to be whole, found from the file listing alone (no chunk is read)."""
        found = []
        for name, array in self._arrays.items():
            for coords in self.chunk_grid(name):
                path = self.path / name / array.metadata.encode_chunk_key(coords)
                try:
                    size = path.stat().st_size
                except FileNotFoundError:
                    found.append(self.chunk_damage(name, coords, "missing"))
                    continue
                if size < MIN_CHUNK_BYTES:
                    found.append(self.chunk_damage(name, coords, f"truncated to {size} bytes"))
        return found

    def _get(self, name: str, start: int, count: int) -> np.ndarray:
        """Rows `start .. start + count - 1` of array `name`, checked: `StoreDamaged` for every chunk of
        them that fails its checksum, cannot be decoded, or is not on disk (read as the fill value)."""
        array = self._arrays[name]
        try:
            data = np.asarray(array[start:start + count])
        except Exception as error:   # a checksum mismatch (ValueError), a codec's error, an unreadable file
            damage = self._unreadable(name, start, count)
            if not damage:
                raise
            raise StoreDamaged(self.path, damage) from error
        bad = np.isnan(data) if name == "ratio" else data == FILL[name]
        if name in ("ratio", "counts"):   # per texel and light (ratio's RGB) or per texel (counts' three)
            bad = np.any(bad, axis=-1)
        if not np.any(bad):
            return data
        hits = np.argwhere(bad)
        hits[:, 0] += start
        hits //= np.asarray(array.chunks[:bad.ndim])   # the chunk of every value read as the fill value
        coords = sorted({tuple(h) + (0,) * (array.ndim - bad.ndim) for h in hits.tolist()})
        raise StoreDamaged(self.path, [self.chunk_damage(name, c, "missing") for c in coords])

    def _unreadable(self, name: str, start: int, count: int) -> list[ChunkDamage]:
        """The chunks of rows `start .. start + count - 1` that fail when read one by one."""
        array = self._arrays[name]
        tile = array.chunks[0]
        found = []
        for coords in self.chunk_grid(name):
            if not (coords[0] * tile < start + count and (coords[0] + 1) * tile > start):
                continue
            region = tuple(slice(i * c, (i + 1) * c) for i, c in zip(coords, array.chunks, strict=True))
            try:
                array[region]
            except Exception as error:
                text = str(error).splitlines()[0] if str(error) else type(error).__name__
                problem = ("corrupt or truncated: checksum mismatch" if "checksum" in text.lower()
                           else f"unreadable: {text}")
                found.append(self.chunk_damage(name, coords, problem))
        return found


def _check_layout(store: ObservationStore) -> None:
    """`store.json`'s fields against themselves, the arrays and the layout recorded with the arrays:
    every problem at once (`InputErrors`), before any tile is read."""
    marker = store.path / MARKER
    doc = Fields.document(store.info, marker, error=InputErrors)
    problems = doc.problems
    size = doc.raw("size")
    if size is not None and not (isinstance(size, list) and len(size) == 2
                                 and all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in size)):
        doc.problem("size", f"expected [H, W] of positive integers, got {size!r}")
        size = None
    n_lights = doc.integer("n_lights", lo=1)
    tile = doc.integer("tile", lo=1)
    block = doc.integer("light_block", lo=1)
    dtype = doc.choice("dtype", STORE_DTYPES)
    doc.vector("view_dir")
    doc.string("fingerprint")
    dirs = doc.raw("light_dirs")
    if dirs is not None:
        ok = isinstance(dirs, list) and all(isinstance(d, list) and len(d) == 3 and all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) for v in d) for d in dirs)
        if not ok:
            doc.problem("light_dirs", "expected a list of [x, y, z] directions")
        elif n_lights is not None and len(dirs) != n_lights:
            doc.problem("light_dirs", f"{len(dirs)} directions for n_lights {n_lights}")
    missing = [name for name in FILL if name not in store._arrays]
    problems.extend(f"{store.path / name}: missing array" for name in missing)
    if missing:
        problems.check()
    layout = store._group.attrs.get("layout")
    if not isinstance(layout, dict):
        problems.add(f"{store.path / 'zarr.json'}: no recorded layout (a store of an older version: ingest again)")
        layout = {}
    ratio, flags, counts = store._arrays["ratio"], store._arrays["flags"], store._arrays["counts"]
    t, n = ratio.shape[0], ratio.shape[1]

    def differs(field, value, actual, what):
        if value is not None and value != actual:
            problems.add(f"{marker}: {field}: {value!r} differs from the store's {what} ({actual!r}); "
                         "store.json was edited or belongs to another store")

    differs("size", size, layout.get("size"), f"size recorded in {store.path / 'zarr.json'}")
    if size is not None and size[0] * size[1] != t:
        problems.add(f"{marker}: size: {size!r} is {size[0] * size[1]} texels, the arrays hold {t}")
    differs("n_lights", n_lights, n, "arrays' light count")
    differs("tile", tile, ratio.chunks[0], "chunk of texels")
    differs("light_block", block, ratio.chunks[1], "chunk of lights")
    differs("dtype", dtype, str(ratio.dtype), "ratio dtype")
    mask = store._arrays["mask"]
    for name, array, shape in (("flags", flags, (t, n)), ("counts", counts, (t, 3)), ("mask", mask, (t,))):
        if array.shape != shape or str(array.dtype) != ARRAY_DTYPES[name]:
            problems.add(f"{store.path / name}: shape {array.shape} {array.dtype}, expected {shape} "
                         f"{ARRAY_DTYPES[name]} beside ratio {ratio.shape}")
    if flags.chunks != ratio.chunks[:2]:
        problems.add(f"{store.path / 'flags'}: chunks {flags.chunks} differ from ratio's {ratio.chunks[:2]}")
    for name, array in store._arrays.items():
        codecs = [type(c).__name__ for c in array.metadata.codecs]
        fill = array.fill_value
        same_fill = bool(np.isnan(fill)) if name == "ratio" else fill == FILL[name]
        if "Crc32cCodec" not in codecs or not same_fill:
            problems.add(f"{store.path / name}: written without chunk checksums or with a fill value that "
                         "could pass as data (an older store: ingest again)")
    problems.check()


def open_store(store_dir: str | os.PathLike) -> ObservationStore:
    """Open a complete store, its metadata checked against its arrays; `InputError` naming the file
    when it is missing, unfinished, foreign or inconsistent."""
    store_dir = Path(store_dir)
    marker = store_dir / MARKER
    if not store_dir.is_dir():
        raise InputError(store_dir, "no such observation store")
    if not marker.is_file():
        raise InputError(marker, "missing: the observation store is unfinished (rerun `fitting ingest` to resume)")
    try:
        info = json.loads(marker.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise InputError(marker, f"not valid JSON ({error})") from None
    if not isinstance(info, dict) or info.get("format") != STORE_FORMAT:
        raise InputError(marker, f"not an observation store (format must be {STORE_FORMAT!r})")
    if info.get("version") != STORE_VERSION:
        raise InputError(marker, f"unsupported store version {info.get('version')!r} "
                                 f"(this reader knows {STORE_VERSION}; ingest the capture again)")
    try:
        return ObservationStore(store_dir, info)
    except (KeyError, ValueError, FileNotFoundError) as error:
        raise InputError(store_dir, f"damaged observation store ({type(error).__name__}: {error})") from None


def store_entries(store_dir: Path) -> list[Path]:
    """What a store directory holds, its lock file aside."""
    return [p for p in store_dir.iterdir() if p.name != LOCK_NAME]

"""`fitting ingest CAPTURE_DIR --store STORE_DIR`: one streaming pass from a capture directory to an
observation store (chunked, compressed; resumable), which `fitting fit STORE_DIR` fits."""

from __future__ import annotations

from fitting.ingest import DEFAULT_MEMORY_GB, DEFAULT_TILE, ingest_capture
from fitting.store import DEFAULT_STORE_DTYPE, STORE_DTYPES, open_store

from .arguments import positive_float, positive_int


def configure(parser):
    parser.add_argument("capture_dir", metavar="CAPTURE_DIR", help="capture directory (capture.json + images)")
    parser.add_argument("--store", required=True, metavar="STORE_DIR",
                        help="observation store to write (rerun on the same one to resume an interrupted ingest)")
    parser.add_argument("--dtype", choices=STORE_DTYPES, default=DEFAULT_STORE_DTYPE,
                        help=f"stored ratio dtype (default {DEFAULT_STORE_DTYPE}; float32: fits bit-identical to "
                             "the in-memory merge)")
    parser.add_argument("--memory-gb", type=positive_float, default=DEFAULT_MEMORY_GB,
                        help=f"memory budget of one block of lights (default {DEFAULT_MEMORY_GB})")
    parser.add_argument("--tile", type=positive_int, default=DEFAULT_TILE,
                        help=f"texels per chunk (default {DEFAULT_TILE}: the fit's default --chunk)")


def run(args) -> int:
    store = open_store(ingest_capture(args.capture_dir, args.store, dtype=args.dtype, memory_gb=args.memory_gb,
                                      tile=args.tile))
    h, w = store.size
    print(f"{store.path}: {h}x{w} texels x {store.n_lights} lights, {store.dtype}, "
          f"light block {store.info['light_block']}, tile {store.info['tile']}")
    return 0

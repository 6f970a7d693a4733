"""`fitting fit (CAPTURE_DIR | STORE_DIR) --out BTF_DIR`: per-texel anisotropic BRDF fit of a capture
directory (ingested into BTF_DIR/.store/ first) or of an observation store, in this process or on
a Dask cluster (`--scheduler`, `--dask-workers`)."""

from __future__ import annotations

import json

from fitting import fit_capture
from fitting.ingest import DEFAULT_MEMORY_GB
from fitting.store import DEFAULT_STORE_DTYPE, STORE_DTYPES

from .arguments import positive_float, positive_int
from .fit_options import add_fit_settings, fit_settings


def configure(parser):
    parser.add_argument("capture_dir", metavar="CAPTURE_DIR|STORE_DIR",
                        help="capture directory (capture.json + images) or observation store (`fitting ingest`)")
    parser.add_argument("--out", required=True, metavar="BTF_DIR",
                        help="output BTF directory (rerun on the same one to resume an interrupted fit)")
    add_fit_settings(parser)
    parser.add_argument("--no-pyramid", action="store_true", help="write level 0 only (skip the EM pyramid)")
    parser.add_argument("--keep-store", action="store_true",
                        help="keep BTF_DIR/.store/ (the ingested observations) once the BTF is complete")
    parser.add_argument("--store-dtype", choices=STORE_DTYPES, default=DEFAULT_STORE_DTYPE,
                        help="dtype of the stored observations when ingesting a capture "
                             f"(default {DEFAULT_STORE_DTYPE})")
    parser.add_argument("--memory-gb", type=positive_float, default=DEFAULT_MEMORY_GB,
                        help=f"memory budget of the ingest's light block (default {DEFAULT_MEMORY_GB})")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="fit the tiles on the Dask cluster at ADDRESS (tcp://HOST:PORT; started with "
                            "`dask scheduler` and `dask worker ADDRESS --nthreads 1`; store and BTF_DIR on a "
                            "shared path)")
    where.add_argument("--dask-workers", type=positive_int, metavar="N",
                       help="fit the tiles on a local Dask cluster of N worker processes")


def run(args) -> int:
    out = fit_capture(args.capture_dir, args.out, fit_settings(args), pyramid=not args.no_pyramid,
                      keep_store=args.keep_store, store_dtype=args.store_dtype, memory_gb=args.memory_gb,
                      scheduler=args.scheduler or args.dask_workers)
    info = json.loads((out / "btf.json").read_text()).get("fit", {})
    print(f"{out}: converged {info.get('converged_fraction', float('nan')):.1%}, "
          f"median residual {info.get('median_residual', float('nan')):.4g}, fit {info.get('seconds', 0):.1f} s")
    return 0

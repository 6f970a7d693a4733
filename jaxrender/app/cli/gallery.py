"""`jaxrender gallery --out DIR`: the main job."""

from __future__ import annotations

from pathlib import Path

from jaxrender.errors import InputError

from ..gallery import SECTIONS, default_jobs, render_gallery


def configure(parser):
    parser.add_argument("--out", required=True, help="output directory (index.html, PNG, EXR)")
    parser.add_argument("--only", default=None,
                        help=f"comma-separated sections to render (default all: {','.join(SECTIONS)})")
    parser.add_argument("--quick", action="store_true", help="small sizes (about a minute per section)")
    parser.add_argument("--jobs", type=int, default=None,
                        help="sections rendered at once, each in its own process (default: one per core, at most "
                             "one per section; 1: one after the other in this process)")


def run(args) -> int:
    sections = None if args.only is None else [s.strip() for s in args.only.split(",") if s.strip()]
    unknown = [s for s in sections or [] if s not in SECTIONS]
    if unknown:
        raise InputError(None, f"--only: unknown sections {unknown}; choose from {list(SECTIONS)}")
    if Path(args.out).exists() and not Path(args.out).is_dir():
        raise InputError(args.out, "exists and is not a folder")
    if args.jobs is not None and args.jobs < 1:
        raise InputError(None, f"--jobs: must be at least 1, got {args.jobs}")
    jobs = default_jobs(len(sections or SECTIONS)) if args.jobs is None else args.jobs
    result = render_gallery(args.out, sections=sections, quick=args.quick, jobs=jobs)
    failed = [name for name, s in result["sections"].items() if s["error"]]
    print(f"gallery written to {args.out}/index.html" + (f" (FAILED sections: {', '.join(failed)})" if failed else ""))
    return 1 if failed else 0

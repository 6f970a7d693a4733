"""Execute the example notebooks in place, so that they are stored with their outputs (figures
included) and the reference site shows them as run.

    python examples/run_notebooks.py                 # every notebook in examples/
    python examples/run_notebooks.py desert noh      # some of them

Each notebook runs top to bottom in a fresh kernel (matplotlib's inline PNG, 72 dpi, keeps the
files small); its metadata records the hash of its code cells (`jaxrender.code_sha256`) and the
date. The notebook tests execute each notebook again and check that the stored outputs come from
the current code: the same hash, and the same numbers printed (tests/notebook_helpers.py).
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import os
import sys
from pathlib import Path

import nbclient
import nbformat

HERE = Path(__file__).resolve().parent
INLINE = "module://matplotlib_inline.backend_inline"  # figures stored as PNG in the outputs

def code_sha256(nb: nbformat.NotebookNode) -> str:
    """The hash of the notebook's code cells, in order: what its outputs were computed from."""
    digest = hashlib.sha256()
    for cell in nb.cells:
        if cell.cell_type == "code":
            digest.update(cell.source.encode() + b"\0")
    return digest.hexdigest()


def execute(path: Path, *, cwd: Path | None = None, backend: str = INLINE, timeout: int = 1800,
            ) -> nbformat.NotebookNode:
    """The notebook at `path` run top to bottom in a fresh python3 kernel, working directory `cwd`
    (default: its folder), matplotlib's `backend` (default: inline PNG figures; the tests use Agg);
    outputs in the returned notebook, the file untouched. MPLBACKEND is restored afterwards."""
    nb = nbformat.read(path, as_version=4)
    saved = os.environ.get("MPLBACKEND")
    os.environ["MPLBACKEND"] = backend
    try:
        nbclient.NotebookClient(nb, timeout=timeout, kernel_name="python3",
                                resources={"metadata": {"path": str(cwd or path.parent)}}).execute()
    finally:
        if saved is None:
            os.environ.pop("MPLBACKEND", None)
        else:
            os.environ["MPLBACKEND"] = saved
    return nb


def store(path: Path) -> None:
    nb = execute(path)
    nb.metadata["jaxrender"] = {
        "code_sha256": code_sha256(nb),
        "executed": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d"),
    }
    nbformat.write(nb, path)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", help="notebook names without .ipynb (default: all)")
    args = parser.parse_args()
    paths = [HERE / f"{n}.ipynb" for n in args.names] or sorted(HERE.glob("*.ipynb"))
    for path in paths:
        if not path.is_file():
            print(f"{path}: no such notebook", file=sys.stderr)
            return 2
        print(f"executing {path.name} ...", flush=True)
        store(path)
        print(f"  {path.name}: {path.stat().st_size / 1024:.0f} kB with outputs", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

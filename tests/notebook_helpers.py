"""Running the example notebooks headless, as the notebook tests do: executed top to bottom in a
fresh kernel (matplotlib's Agg backend), and their summary read back from what they print."""

from __future__ import annotations

import json
import os
from pathlib import Path

import nbclient
import nbformat


def run_notebook(path: Path, *, cwd: Path | None = None, timeout: int = 600) -> nbformat.NotebookNode:
    """The notebook at `path` executed in a fresh python3 kernel, working directory `cwd` (default: the
    notebook's folder); MPLBACKEND is Agg for the kernel and restored afterwards."""
    nb = nbformat.read(path, as_version=4)
    saved = os.environ.get("MPLBACKEND")
    os.environ["MPLBACKEND"] = "Agg"
    try:
        nbclient.NotebookClient(nb, timeout=timeout, kernel_name="python3",
                                resources={"metadata": {"path": str(cwd or path.parent)}}).execute()
    finally:
        if saved is None:
            os.environ.pop("MPLBACKEND", None)
        else:
            os.environ["MPLBACKEND"] = saved
    return nb


def tagged_results(nb: nbformat.NotebookNode, tag: str = "RESULTS ") -> dict:
    """The JSON after `tag` on the one printed line that starts with it."""
    lines = [line for cell in nb.cells if cell.cell_type == "code" for out in cell.get("outputs", [])
             for line in out.get("text", "").splitlines() if line.startswith(tag)]
    assert len(lines) == 1, lines
    return json.loads(lines[0][len(tag):])


def last_results(nb: nbformat.NotebookNode) -> dict:
    """The JSON on the last line the last cell printed."""
    text = "".join(o.get("text", "") for o in nb.cells[-1].outputs if o.get("output_type") == "stream")
    return json.loads(text.strip().splitlines()[-1])

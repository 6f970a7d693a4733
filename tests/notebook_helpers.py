"""Running the example notebooks headless, as the notebook tests do: executed top to bottom in a
fresh kernel (matplotlib's Agg backend), and their summary read back from what they print."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import nbformat

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples"))
from run_notebooks import code_sha256, execute  # noqa: E402  (examples/: one runner, one hash)


def run_notebook(path: Path, *, cwd: Path | None = None, timeout: int = 600) -> nbformat.NotebookNode:
    """The notebook at `path` executed in a fresh python3 kernel, working directory `cwd` (default: the
    notebook's folder), matplotlib's Agg backend (no figures encoded)."""
    return execute(path, cwd=cwd, backend="Agg", timeout=timeout)


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


def _is_machine_dependent(key: str) -> bool:
    """A wall-clock time the notebook prints (`seconds`, `fit_seconds`, `frame_s`), or where on a map
    an extreme falls (`worst_texel`: near-ties break differently on other CPUs): compared by key only."""
    return key.endswith(("seconds", "_s", "_texel"))


def _numbers_match(stored, fresh, *, rtol: float, path: str = "") -> list[str]:
    """Where two printed results differ: numbers beyond `rtol` (relative, 1e-9 absolute), anything else
    unequal; machine-dependent values are compared by key only."""
    if isinstance(stored, dict) and isinstance(fresh, dict):
        if set(stored) != set(fresh):
            return [f"{path}: keys {sorted(set(stored) ^ set(fresh))} differ"]
        return [d for k in stored if not _is_machine_dependent(k)
                for d in _numbers_match(stored[k], fresh[k], rtol=rtol, path=f"{path}.{k}")]
    if isinstance(stored, list) and isinstance(fresh, list) and len(stored) == len(fresh):
        return [d for i, (a, b) in enumerate(zip(stored, fresh)) for d in _numbers_match(a, b, rtol=rtol,
                                                                                         path=f"{path}[{i}]")]
    numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (stored, fresh))
    if numbers and abs(stored - fresh) <= rtol * max(abs(stored), abs(fresh)) + STORED_ATOL:
        return []
    return [] if stored == fresh else [f"{path}: stored {stored!r}, now {fresh!r}"]


# stored numbers against a fresh run's (the notebooks are stored from one CPU, checked on others):
# the same keys, numbers within 50 % or 0.05 (optimizers stop a step apart, fits of noisy data
# round apart, errors at the level of rounding differ wholly); a notebook stored before a change
# of the code differs in its code hash, its keys, or by far more
STORED_RTOL, STORED_ATOL = 0.5, 0.05


def assert_outputs_current(path: Path, executed: nbformat.NotebookNode, results, *,
                           rtol: float = STORED_RTOL) -> None:
    """The notebook stored at `path` carries outputs computed from its current code: every code cell
    ran, its recorded hash is that of the code now (examples/run_notebooks.py), and the results it
    printed (`results(nb)`: `tagged_results` or `last_results`) are those of the fresh run `executed`,
    numbers within `rtol` (other CPUs, other summation orders)."""
    stored = nbformat.read(path, as_version=4)
    recorded = stored.metadata.get("jaxrender", {}).get("code_sha256")
    assert recorded == code_sha256(stored) == code_sha256(executed), (
        f"{path.name}: its stored outputs are not from its current code: run `python examples/run_notebooks.py "
        f"{path.stem}`")
    assert all(c.get("execution_count") for c in stored.cells if c.cell_type == "code"), f"{path.name}: not run"
    differences = _numbers_match(results(stored), results(executed), rtol=rtol)
    assert not differences, f"{path.name}: stored outputs differ from a fresh run: {differences[:5]}"

"""Writing a generated example notebook: cells with stable ids (regenerating changes only what the
cells say) and the python3 kernel, as the notebook tests run it."""

from pathlib import Path

import nbformat as nbf


def write_notebook(cells: list, path: Path) -> None:
    for i, cell in enumerate(cells):
        cell["id"] = f"cell-{i:02d}"
    nb = nbf.v4.new_notebook(cells=cells, metadata={"kernelspec": {"name": "python3", "display_name": "Python 3",
                                                                   "language": "python"}})
    nbf.write(nb, path)

"""Shared by the notebook builders: turn (kind, source) cells into a notebook, execute it, write it."""

import pathlib

import nbformat
from nbclient import NotebookClient

HERE = pathlib.Path(__file__).resolve().parent


def build(cells, name: str, timeout: int = 600) -> pathlib.Path:
    """Execute `cells` ([("md" | "code", source)]) with the notebooks folder as working directory and
    write notebooks/`name`."""
    nb = nbformat.v4.new_notebook()
    nb.cells = [nbformat.v4.new_markdown_cell(src) if kind == "md" else nbformat.v4.new_code_cell(src) for kind, src in cells]
    nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
    NotebookClient(nb, timeout=timeout, kernel_name="python3", resources={"metadata": {"path": str(HERE)}}).execute()
    out = HERE / name
    nbformat.write(nb, out)
    print(f"wrote {out}")
    return out

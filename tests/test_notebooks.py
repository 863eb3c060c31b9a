"""The notebooks run end to end (at smoke sizes: MJX_MULTIARM_SMOKE=1)."""

from __future__ import annotations

import pathlib

import nbclient
import nbformat
import pytest

NOTEBOOKS = pathlib.Path(__file__).resolve().parents[1] / "notebooks"

pytestmark = pytest.mark.slow  # the notebooks end to end


@pytest.mark.parametrize("name", ["quickstart", "reproduce"])
def test_notebook_runs(name, tmp_path, monkeypatch):
    monkeypatch.setenv("MJX_MULTIARM_SMOKE", "1")
    monkeypatch.setenv("MJX_MULTIARM_WORKDIR", str(tmp_path))
    book = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
    nbclient.NotebookClient(book, timeout=900, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}).execute()
    errors = [o for cell in book.cells if cell.cell_type == "code" for o in cell.outputs if o.output_type == "error"]
    assert not errors

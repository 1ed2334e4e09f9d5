"""The notebooks run from top to bottom without an error (each also asserts its own
checks: the parts add up to the render, the fit recovers the truth, the identifiability
warning appears), with DIFFSHADE_NB_QUICK=1 cutting image sizes and steps; and they are
kept in the repository without outputs. They run with an empty temporary folder as the
working directory, not notebooks/, to show that they find their files from any directory."""

from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"
NAMES = ["01_quickstart.ipynb", "02_fit_material.ipynb", "03_accuracy_vs_time.ipynb",
         "04_objects_shadows.ipynb"]


@pytest.mark.parametrize("name", NAMES)
def test_notebook_executes_without_errors(name, monkeypatch, tmp_path):
    monkeypatch.setenv("DIFFSHADE_NB_QUICK", "1")
    notebook = nbformat.read(NOTEBOOKS / name, as_version=4)
    client = NotebookClient(notebook, timeout=300, kernel_name="python3",
                            resources={"metadata": {"path": str(tmp_path)}})
    client.execute()  # raises CellExecutionError naming the cell that failed
    code = [cell for cell in notebook.cells if cell.cell_type == "code"]
    assert all(cell.execution_count for cell in code)
    errors = [out for cell in code for out in cell.outputs if out.output_type == "error"]
    assert errors == []
    images = [out for cell in code for out in cell.outputs if "image/png" in out.get("data", {})]
    assert images, "no figure was drawn"


@pytest.mark.parametrize("name", NAMES)
def test_notebook_is_stored_without_outputs(name):
    notebook = nbformat.read(NOTEBOOKS / name, as_version=4)
    nbformat.validate(notebook)
    assert notebook.metadata.kernelspec.name == "python3"
    for cell in notebook.cells:
        if cell.cell_type == "code":
            assert cell.outputs == [] and cell.execution_count is None

"""The notebooks run from top to bottom without an error (each also asserts its own
checks: the parts add up to the render, the fit recovers the truth, the identifiability
warning appears), with DIFFSHADE_NB_QUICK=1 cutting image sizes and steps. They run with
an empty temporary folder as the working directory, not notebooks/, to show that they
find their files from any directory.

They are kept in the repository executed (by notebooks/execute.py, in full mode), so that
their figures show when browsing it: every code cell ran, in order, in one kernel, from
the source it holds now, without an error, and no output names a folder of the machine
that ran it."""

import importlib.util
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = Path(__file__).resolve().parent.parent / "notebooks"
NAMES = ["01_quickstart.ipynb", "02_fit_material.ipynb", "03_accuracy_vs_time.ipynb",
         "04_objects_shadows.ipynb", "05_real_capture.ipynb", "06_texture.ipynb"]


def _execute_module():
    spec = importlib.util.spec_from_file_location("notebooks_execute", NOTEBOOKS / "execute.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


execute = _execute_module()


def _images(cells):
    return [out for cell in cells for out in cell.outputs if "image/png" in out.get("data", {})]


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
    assert _images(code), "no figure was drawn"


def test_execute_lists_every_notebook():
    assert sorted(f"{name}.ipynb" for name in execute.NAMES) == sorted(NAMES)
    assert sorted(path.name for path in NOTEBOOKS.glob("*.ipynb")) == sorted(NAMES)


@pytest.mark.parametrize("name", NAMES)
def test_notebook_is_stored_executed(name):
    notebook = nbformat.read(NOTEBOOKS / name, as_version=4)
    nbformat.validate(notebook)
    assert notebook.metadata.kernelspec.name == "python3"
    code = [cell for cell in notebook.cells if cell.cell_type == "code" and cell.source.strip()]
    rerun = f"re-run `python notebooks/execute.py {Path(name).stem}`"
    # one fresh kernel, top to bottom: the counts are 1..n in the order of the cells
    assert [cell.execution_count for cell in code] == list(range(1, len(code) + 1)), rerun
    stale = [i for i, cell in enumerate(code)
             if cell.metadata.get("source_hash") != execute.source_hash(cell.source)]
    assert stale == [], f"code cells {stale} changed since their outputs were made; {rerun}"
    errors = [out for cell in code for out in cell.outputs if out.output_type == "error"]
    assert errors == []
    assert _images(code), "no figure is stored"
    assert all("execution" not in cell.metadata for cell in code), "timestamps are stored"
    assert execute.machine_paths(notebook) == []


@pytest.mark.parametrize("text, found", [
    ("saved to /work/wt-x/out.png", True), ("C:\\Users\\me\\data", True),
    ("/tmp/abc/data.json", True), ("see docs/color.md", False),
    ("benchmarks/results/accuracy_vs_time.json", False), ("1/255 units", False)])
def test_machine_paths_are_found_in_outputs(text, found):
    notebook = nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell(
        "print()", outputs=[nbformat.v4.new_output("stream", name="stdout", text=text)])])
    assert bool(execute.machine_paths(notebook)) == found

"""Execute the notebooks in place, as they are committed: top to bottom in a fresh kernel,
in full mode (not DIFFSHADE_NB_QUICK), with this checkout first on the kernel's path and
an empty temporary folder as its working directory, so that no output names a folder of
the machine that ran it. Each code cell's metadata records a hash of the source that made
its outputs (tests/test_notebooks.py checks it); the per-cell timestamps are not kept.

    python notebooks/execute.py                      # every notebook
    python notebooks/execute.py 03_accuracy_vs_time  # some of them
"""

import argparse
import hashlib
import os
import re
import sys
import tempfile
import time
from pathlib import Path

import nbformat
from nbclient import NotebookClient

FOLDER = Path(__file__).resolve().parent
ROOT = FOLDER.parent
NAMES = ["01_quickstart", "02_fit_material", "03_accuracy_vs_time", "04_objects_shadows",
         "05_real_capture", "06_texture"]
TIMEOUT_S = 1800
# Absolute paths of a POSIX or Windows machine; a committed output must not name one.
MACHINE_PATH = re.compile(r"(?<![\w.~])(/(home|tmp|work|Users|root|var|private|opt)/|[A-Z]:\\)")


def source_hash(source):
    """The hash of a cell's source that its stored outputs were made from."""
    return hashlib.sha256(source.encode("utf-8")).hexdigest()[:16]


def kernel_env():
    """The environment the kernel inherits: this checkout first on PYTHONPATH, full mode."""
    env = {k: v for k, v in os.environ.items() if k != "DIFFSHADE_NB_QUICK"}
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    return env


def run(notebook, folder):
    """Execute notebook (in place) with folder as the kernel's working directory."""
    client = NotebookClient(notebook, timeout=TIMEOUT_S, kernel_name="python3",
                            record_timing=False, resources={"metadata": {"path": str(folder)}})
    old = dict(os.environ)
    os.environ.clear()
    os.environ.update(kernel_env())  # the kernel process inherits this environment
    try:
        client.execute()
    finally:
        os.environ.clear()
        os.environ.update(old)
    return notebook


def check_kernel_imports_checkout(folder):
    """A kernel started as run() starts it imports diffshade from this checkout."""
    probe = nbformat.v4.new_notebook(cells=[nbformat.v4.new_code_cell(
        "import diffshade\nprint(diffshade.__file__)")])
    probe.metadata.kernelspec = {"name": "python3", "display_name": "Python 3",
                                 "language": "python"}
    printed = run(probe, folder).cells[0].outputs[0]["text"].strip()
    expected = ROOT / "diffshade" / "__init__.py"
    if Path(printed).resolve() != expected:
        raise RuntimeError(f"the kernel imports diffshade from {printed}; expected {expected}")


def machine_paths(notebook):
    """The outputs' lines that name an absolute path of this machine."""
    lines = []
    for cell in notebook.cells:
        for output in cell.get("outputs", []):
            text = output.get("text", "") + "".join(output.get("traceback", []))
            text += output.get("data", {}).get("text/plain", "")
            lines += [line for line in text.splitlines() if MACHINE_PATH.search(line)]
    return lines


def execute(name):
    """Execute notebooks/<name>.ipynb in place and stamp each code cell with its source hash."""
    path = FOLDER / f"{name}.ipynb"
    notebook = nbformat.read(path, as_version=4)
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as folder:
        run(notebook, folder)
    seconds = time.perf_counter() - start
    leaks = machine_paths(notebook)
    if leaks:
        raise RuntimeError(f"{path.name}: outputs name machine paths: {leaks[:3]}")
    for cell in notebook.cells:
        if cell.cell_type == "code":
            cell.metadata["source_hash"] = source_hash(cell.source)
    nbformat.write(notebook, path)
    print(f"{path.name}: executed in {seconds:.0f} s")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", default=NAMES, help=f"some of {NAMES}")
    args = parser.parse_args(argv)
    unknown = [name for name in args.names if name not in NAMES]
    if unknown:
        parser.error(f"names: got {unknown}; expected names from {NAMES}")
    with tempfile.TemporaryDirectory() as folder:
        check_kernel_imports_checkout(folder)
    for name in args.names:
        execute(name)


if __name__ == "__main__":
    sys.exit(main())

"""Every ```python block in README.md and docs/*.md runs exactly as written.

The convention (docs/snippets.md says the same for writers):
- one test per block, named FILE:LINE (the line of its opening fence);
- each block runs alone, in a fresh namespace: it makes its own imports and data, so a
  reader can copy any one block and run it (no block relies on an earlier one);
- the working directory is an empty temporary folder holding only `examples`, a link to
  the repository's examples/ folder, as when a reader runs a block from a checkout's
  root; whatever a block writes lands in the temporary folder;
- any exception fails the test. Blocks in other languages (bash, json, text) are not run.

Blocks run in this process, one after another, so they share JAX's compiled programs
(the same renders in several documents compile once). A block that switches float64 on
is switched back afterwards.
"""

import re
from pathlib import Path

import jax
import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
_OPEN, _CLOSE = re.compile(r"^```python\s*$"), re.compile(r"^```\s*$")


def python_blocks(text):
    """[(line of the opening fence, code)] of the ```python blocks of a Markdown text."""
    blocks, start, code = [], None, []
    for number, line in enumerate(text.splitlines(), start=1):
        if start is None and _OPEN.match(line):
            start, code = number, []
        elif start is not None and _CLOSE.match(line):
            blocks.append((start, "\n".join(code) + "\n"))
            start = None
        elif start is not None:
            code.append(line)
    if start is not None:
        raise ValueError(f"the ```python block at line {start} is never closed")
    return blocks


SNIPPETS = [pytest.param(path, line, code, id=f"{path.relative_to(ROOT)}:{line}")
            for path in DOCUMENTS for line, code in python_blocks(path.read_text())]


def test_blocks_are_found():
    text = "a\n```python\nx = 1\n```\n```bash\nls\n```\n```python\ny = 2\n\nz = 3\n```\n"
    assert python_blocks(text) == [(2, "x = 1\n"), (8, "y = 2\n\nz = 3\n")]
    assert len(SNIPPETS) >= 10


@pytest.mark.parametrize("path, line, code", SNIPPETS)
def test_snippet_runs_as_written(path, line, code, tmp_path, monkeypatch):
    (tmp_path / "examples").symlink_to(ROOT / "examples", target_is_directory=True)
    monkeypatch.chdir(tmp_path)
    x64 = jax.config.jax_enable_x64
    try:
        exec(compile(code, f"{path.relative_to(ROOT)}:{line}", "exec"), {"__name__": "__main__"})
    finally:
        jax.config.update("jax_enable_x64", x64)

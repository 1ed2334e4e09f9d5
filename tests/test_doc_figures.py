"""The figure tables of README.md and the performance pages are what their benchmarks' JSON says.

Each block between `<!-- figures:NAME:begin -->` and `<!-- figures:NAME:end -->` must equal
`benchmarks/doc_figures.py`'s output from the JSON files in benchmarks/results/, so a page
cannot keep a figure its benchmark no longer gives (`python benchmarks/doc_figures.py
--write` refreshes them after a run).
"""

import copy
import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
_SPEC = importlib.util.spec_from_file_location("doc_figures", ROOT / "benchmarks/doc_figures.py")
doc_figures = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(doc_figures)


def loaded(name):
    return {f: json.loads((ROOT / "benchmarks/results" / f).read_text())
            for f in doc_figures.BLOCKS[name][2]}


@pytest.mark.parametrize("name", sorted(doc_figures.BLOCKS))
def test_each_json_a_block_reads_exists(name):
    for file in doc_figures.BLOCKS[name][2]:
        assert (ROOT / "benchmarks/results" / file).is_file(), file


@pytest.mark.parametrize("name", sorted(doc_figures.BLOCKS))
def test_page_block_equals_the_script_output(name):
    page = doc_figures.BLOCKS[name][0]
    text = (ROOT / page).read_text()
    assert doc_figures.block_in(text, name) == doc_figures.render(name), (
        f"{page}: the {name} figures differ from benchmarks/results; run "
        "python benchmarks/doc_figures.py --write")


def test_readme_figures_follow_the_json():
    data = loaded("readme")
    soft = data["peers.json"]["diffshade"]["soft_forward"]["median_s"]
    mitsuba = data["peers.json"]["mitsuba"]["forward"]["median_s"]
    table = doc_figures.render("readme", data)
    assert f"{soft * 1e3:.1f} ms; Mitsuba {mitsuba * 1e3:.1f} ms ({mitsuba / soft:.2f}×)" in table
    changed = copy.deepcopy(data)
    changed["peers.json"]["diffshade"]["soft_forward"]["median_s"] = mitsuba / 2
    assert f"{mitsuba / 2 * 1e3:.1f} ms; Mitsuba {mitsuba * 1e3:.1f} ms (2.00×)" in (
        doc_figures.render("readme", changed))


def test_readme_memory_row_is_the_largest_peak_of_each_point():
    data = loaded("readme")
    rows = data["memory_views.json"]["rows"]
    expected = " / ".join(f"{r['peak_steps'] / 2**30:.2f}" for r in rows) + " GiB"
    assert expected in doc_figures.render("readme", data)


def test_a_missing_or_doubled_marker_is_refused():
    begin, end = doc_figures.markers("peers")
    for text in ("no markers", f"{end}\n{begin}", f"{begin}\n{begin}\n{end}"):
        with pytest.raises(ValueError, match="figures:peers"):
            doc_figures.block_in(text, "peers")
    assert doc_figures.replace_block(f"a\n{begin}\nold\n{end}\nb", "peers", "new") == (
        f"a\n{begin}\nnew\n{end}\nb")


def test_readme_keeps_its_two_commands_first():
    lines = (ROOT / "README.md").read_text().splitlines()
    ci = (ROOT / ".ci/run").read_text().strip().splitlines()[-1]
    assert lines[2:6] == ["```bash", lines[3], ci, "```"]
    assert lines[3].endswith("diffshade fit out/data -o out/fit")

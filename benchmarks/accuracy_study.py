"""The accuracy-versus-time study in one command: every study module, each JSON with its run
record (commit, start, minutes, load before and after), the plots, and the tables of
docs/accuracy-vs-time.md.

    python benchmarks/accuracy_study.py --docs        # the whole study (an idle machine):
                                                      # JSON, docs/img plots, the page's tables
    python benchmarks/accuracy_study.py --docs --no-run   # the page's tables from the JSON
    python benchmarks/accuracy_study.py --only shadows,penumbrae --docs   # some studies
    python benchmarks/accuracy_study.py --quick --results /tmp/study      # CI-size run

A study module (MODULES) has NAME, OUT (its JSON), run(quick) -> dict, tables(results) ->
markdown, plots(results, folder) -> PNG paths and main(argv). The page holds each study's
tables between `<!-- study:NAME:begin -->` and `<!-- study:NAME:end -->`, and the "choose
your settings" table (accuracy_tables.choose_table, from every study's JSON) in the block
named "choose"; `--docs` rewrites every block and nothing else.
"""

import argparse
import importlib
import json
import re
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from accuracy_tables import choose_table  # noqa: E402
from common import run_study  # noqa: E402

ROOT = HERE.parent
DOC = ROOT / "docs" / "accuracy-vs-time.md"
RESULTS = ROOT / "benchmarks" / "results"
MODULES = ("accuracy_vs_time", "accuracy_shadows", "accuracy_area_lights",
           "accuracy_penumbrae", "accuracy_choices", "accuracy_textures", "accuracy_lens")
CHOOSE = "choose"
BLOCK = re.compile(r"<!-- study:(\w+):begin -->\n(.*?)\n?<!-- study:\1:end -->", re.S)


def modules():
    """{NAME: module} of the study modules present."""
    found = {}
    for name in MODULES:
        module = importlib.import_module(name)
        found[module.NAME] = module
    return found


def load_published(folder=RESULTS):
    """{NAME: results} of every study whose JSON is in `folder`."""
    studies = {}
    for name, module in modules().items():
        path = Path(folder) / Path(module.OUT).name
        if path.exists():
            studies[name] = json.loads(path.read_text(encoding="utf-8"))
    return studies


def generated_blocks(studies):
    """{block name: markdown}: each study's tables and the "choose your settings" table."""
    found = modules()
    blocks = {CHOOSE: choose_table(studies)}
    blocks |= {name: found[name].tables(results) for name, results in studies.items()}
    return blocks


def doc_blocks(text):
    """{block name: markdown} of the generated blocks of a page."""
    return {m.group(1): m.group(2) for m in BLOCK.finditer(text)}


def rewrite_blocks(text, blocks):
    """The page with each generated block's content replaced by `blocks[name]`; a block
    of the page that `blocks` lacks is an error (its study's JSON is missing)."""
    missing = sorted(set(doc_blocks(text)) - set(blocks))
    if missing:
        raise ValueError(f"the page has blocks {missing} that no study's JSON fills; "
                         f"expected names from {sorted(blocks)}")
    return BLOCK.sub(lambda m: (f"<!-- study:{m.group(1)}:begin -->\n{blocks[m.group(1)]}\n"
                                f"<!-- study:{m.group(1)}:end -->"), text)


def write_docs(studies, doc=DOC):
    """Rewrite the generated blocks of `doc`; returns the names of studies it has no
    block for (a new study's block is added to the page by hand, once)."""
    blocks = generated_blocks(studies)
    text = Path(doc).read_text(encoding="utf-8")
    Path(doc).write_text(rewrite_blocks(text, blocks), encoding="utf-8")
    print(f"rewrote the generated blocks of {doc}")
    return sorted(set(blocks) - set(doc_blocks(text)))


def parse(argv):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true",
                        help="CI-size runs of every study (needs --results)")
    parser.add_argument("--only", default=None,
                        help="comma-separated study names (default: every study)")
    parser.add_argument("--results", default=None,
                        help=f"folder for the JSON (default {RESULTS.relative_to(ROOT)})")
    parser.add_argument("--plots", default=None,
                        help="folder for the plots (default docs/img; <results>/img if quick)")
    parser.add_argument("--docs", action="store_true",
                        help="rewrite the generated blocks of --doc from the JSON")
    parser.add_argument("--doc", default=str(DOC), help="the page (default: %(default)s)")
    parser.add_argument("--no-run", action="store_true",
                        help="run nothing: with --docs, rewrite the page from the JSON")
    args = parser.parse_args(argv)
    if args.quick and args.results is None:
        parser.error("--quick: give --results FOLDER (benchmarks/results holds the full "
                     "study, which the page and tests/test_accuracy_current.py read)")
    return parser, args


def main(argv=None):
    parser, args = parse(argv)
    found = modules()
    names = list(found) if args.only is None else args.only.split(",")
    unknown = [n for n in names if n not in found]
    if unknown:
        parser.error(f"--only: got {unknown}; expected names from {list(found)}")
    results = Path(args.results or RESULTS)
    plots = args.plots or (results / "img" if args.quick else ROOT / "docs" / "img")
    results.mkdir(parents=True, exist_ok=True)
    for name in [] if args.no_run else names:
        print(f"== {name}", flush=True)
        module = found[name]
        run_study(module, args.quick, str(results / Path(module.OUT).name), str(plots))
    if args.docs:
        lacking = write_docs(load_published(results), args.doc)
        for name in lacking:
            print(f"{args.doc} has no block for {name!r}: add <!-- study:{name}:begin --> "
                  f"and <!-- study:{name}:end --> where its tables go")


if __name__ == "__main__":
    main()

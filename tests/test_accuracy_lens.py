"""The quick run of benchmarks/accuracy_lens.py completes, its figures agree with
independent expectations and reproduce the published JSON.

Timings are not asserted. References: the truth the photos were made with (the exact
sphere, benchmarks/undistortion.py); the published rows that the quick rows repeat (64 px,
8-bit photos, every handling); the lens model itself for what ignoring it does (the
outline of a distorted photo is displaced against the pinhole render's).
"""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import accuracy_lens as study  # noqa: E402

pytestmark = pytest.mark.cost(30)  # one quick study shared by the module


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    folder = tmp_path_factory.mktemp("lens")
    payload = study.main(["--quick", "--out", str(folder / "lens.json"),
                          "--plots", str(folder / "img")])
    return folder, payload["rows"]


def _row(rows, handling, margin=1):
    return next(r for r in rows if (r["handling"], r["margin"]) == (handling, margin))


def test_quick_run_writes_rows_record_and_plot(quick):
    folder, rows = quick
    saved = json.loads((folder / "lens.json").read_text())
    assert saved["quick"] is True and len(saved["rows"]) == len(rows) == len(study.HANDLINGS)
    assert (folder / "img" / "accuracy_lens.png").exists()
    assert all(r["fit_ms"] > 0 for r in rows)
    assert all(r["load_ms"] > 0 for r in rows if r["handling"] == "undistorted on load")


def test_undistorting_recovers_the_truth_as_well_as_a_lens_free_camera(quick):
    _, rows = quick
    free = _row(rows, "no lens")["max_rel_error"]
    assert free < 1e-2  # 8-bit photos of the exact sphere: the truth within rounding
    for margin in (1, 2):
        assert _row(rows, "undistorted on load", margin)["max_rel_error"] < 2 * free
    assert _row(rows, "distortion ignored")["max_rel_error"] > 5 * free


def test_ignoring_the_lens_moves_the_outline():
    # the same camera with and without its distortion: the photo's silhouette (through the
    # lens) and the pinhole one differ by whole pixels, which a fit that ignores the lens
    # counts as error
    with_lens = study.photos(64, False, True)
    without = study.photos(64, False, False)
    moved = [np.sum((a.max(-1) > 0) != (b.max(-1) > 0)) for (_, a), (_, b) in
             zip(with_lens, without, strict=True)]
    assert min(moved) > 10


def test_quick_rows_reproduce_the_published_rows(quick):
    _, rows = quick
    published = json.loads((ROOT / study.OUT).read_text())
    assert published["quick"] is False
    for row in rows:
        found = [p for p in published["rows"] if all(
            p[k] == row[k] for k in ("size", "photos", "handling", "margin"))]
        assert len(found) == 1, row
        # the tests compile without LLVM's optimizations (conftest.py): rounding moves
        # these small errors (ka's comes from a few dark pixels) by up to about 1 %
        for key in ("kd_rel_error", "ka_rel_error"):
            assert row[key] == pytest.approx(found[0][key], rel=0.02), key

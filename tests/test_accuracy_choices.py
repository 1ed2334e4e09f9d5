"""The quick run of benchmarks/accuracy_choices.py completes, its errors agree with
independent expectations, and docs/accuracy-vs-time.md shows the published tables.

Timings are not asserted. References: central differences in float64 (the gradient
section's own reference, so the check is that float64 gets within 1e-6 of it and
float32 does not beat float64); the host kernels' image for the jax kernels; the
published accuracy_vs_time rows that the quick rows repeat (the 64 px subdivision-3
Phong mesh row, the 8-bit fit at 32 px); accuracy_shadows' own shadow test (the colour
equals the ambient-only colour) for the hard raster's shadow edge; the truth a dataset
was rendered with for the fits.
"""

import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import accuracy_choices  # noqa: E402
import accuracy_shadows  # noqa: E402

pytestmark = pytest.mark.cost(45)  # one quick study shared by the module

PUBLISHED = json.loads((ROOT / accuracy_choices.OUT).read_text())
STUDY = json.loads((ROOT / "benchmarks" / "results" / "accuracy_vs_time.json").read_text())


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    folder = tmp_path_factory.mktemp("choices")
    results = accuracy_choices.main(["--quick", "--out", str(folder / "choices.json"),
                                     "--plots", str(folder / "img")])
    return folder, results


def test_quick_run_writes_every_section_its_record_and_plots(quick):
    folder, results = quick
    saved = json.loads((folder / "choices.json").read_text())
    assert saved["quick"] is True and set(accuracy_choices.SECTIONS) <= set(saved)
    assert {"commit", "start_utc", "minutes", "load_before", "load_after"} <= set(saved["run"])
    assert len(list((folder / "img").glob("accuracy_choices_*.png"))) == len(
        accuracy_choices.SECTIONS)
    for name, rows in results.items():
        times = [v for r in rows for k, v in r.items() if k.endswith("_ms") and "iqr" not in k]
        assert rows and np.isfinite(times).all() and min(times) > 0, name


def test_float64_gradients_match_central_differences(quick):
    _, results = quick
    by_dtype = {r["dtype"]: r["rel_error"] for r in results["gradients"]}
    assert by_dtype["float64"] < 1e-6
    assert by_dtype["float64"] < by_dtype["float32"] < 1e-3


def test_jax_kernels_render_the_host_image(quick):
    _, results = quick
    for row in results["kernels"]:
        if row["raster"] == "hard":
            assert row["vs_host_max_abs"] < 1e-5, row
        else:
            # the soft blend sums its K layers in another order: a few pixels move a little
            assert row["differing_px"] <= 0.01 * row["size"] ** 2 and row["vs_host_max_abs"] < 0.02


def test_supersampling_lowers_the_error_and_factor_one_is_the_mesh_row(quick):
    _, results = quick
    rows = {r["factor"]: r for r in results["supersample_levels"]}
    assert rows[2]["rmse_255"] < 0.6 * rows[1]["rmse_255"]
    mesh = [r for r in STUDY["mesh"] if (r["subdivisions"], r["shading"], r["size"])
            == (3, "phong", 64)]
    assert rows[1]["rmse_255"] == pytest.approx(mesh[0]["rmse_255"], rel=1e-4)


def test_soft_raster_departs_from_the_hard_render(quick):
    _, results = quick
    hard, *soft = results["soft_overlap"]
    assert hard["raster"] == "hard" and hard["vs_hard_rmse_255"] == 0.0
    assert all(0.5 < r["vs_hard_rmse_255"] < 100 for r in soft)
    assert all("fwd_bwd_vertices_ms" in r for r in soft)


def test_highlight_front_is_the_pareto_front_of_the_published_rows(quick):
    _, results = quick
    front = results["highlight_front"]
    rows = STUDY["mesh"] + STUDY["supersample"]
    times = [r["fwd_ms"] for r in front]
    errors = [r["highlight_rmse_255"] for r in front]
    assert times == sorted(times) and errors == sorted(errors, reverse=True)
    assert times[0] == min(r["fwd_ms"] for r in rows)
    assert errors[-1] == min(r["highlight_rmse_255"] for r in rows)
    # every row off the front is beaten by a front row in both columns
    for r in rows:
        assert any(f["fwd_ms"] <= r["fwd_ms"] and f["highlight_rmse_255"]
                   <= r["highlight_rmse_255"] for f in front)


def test_hard_shadow_edge_agrees_with_the_shadows_study(quick):
    _, results = quick
    hard = next(r for r in results["soft_shadows"] if r["raster"] == "hard")
    scene, settings = accuracy_shadows.config(hard["size"], hard["map"])
    wrong, edge = accuracy_shadows.edge_error(accuracy_shadows.render(scene, settings),
                                              scene.camera)
    assert (hard["wrong_px"], hard["edge_px"]) == (wrong, edge)


def test_fits_recover_the_truth_only_with_the_model_they_need(quick):
    _, results = quick
    rows = results["fit_effects"]
    error = {r["model"]: r["max_rel_error"] for r in rows if "model" in r}
    assert error["with shadows"] < 1e-4 and error["without shadows"] > 1e-2
    # the targets' own light model recovers the truth; fewer samples are biased
    assert error["disk, 64 samples"] < 1e-4 < 1e-3 < error["disk, 4 samples"]
    # a transparent box: kd and kt fitted together come back from the targets' own model
    glass = {r["model"]: r["max_rel_error"] for r in rows if r["case"] == "transparency"}
    assert glass["glass box, kd + kt"] < 1e-4
    noisy = [r["max_rel_error"] for r in rows if r["case"] == "views × lights"]
    assert all(1e-4 < e < 0.1 for e in noisy)  # noise sigma 0.01: not exact, not lost
    eight_bit = next(r for r in results["fit_resolution"] if r["quantized"] and r["size"] == 32)
    study = next(r for r in STUDY["fitting"] if r["study"] == "noise" and r["size"] == 32)
    assert eight_bit["max_rel_error"] == pytest.approx(study["max_rel_error"], rel=1e-3)


def test_doc_block_is_the_tables_of_the_published_json():
    assert PUBLISHED["quick"] is False
    doc = (ROOT / "docs" / "accuracy-vs-time.md").read_text()
    found = re.search(r"<!-- study:choices:begin -->\n(.*?)\n<!-- study:choices:end -->", doc,
                      re.S)
    assert found is not None
    assert found.group(1).strip() == accuracy_choices.tables(PUBLISHED).strip()

"""The quick mode of benchmarks/accuracy_vs_time.py completes and its numbers are sane.

Only sanity is asserted (timings are not): the error against the analytic sphere falls
with subdivision for Phong shading, supersampling reduces the silhouette error, float64
changes nothing visible, and the linear solver recovers the material.
"""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import accuracy_vs_time  # noqa: E402


@pytest.mark.cost(90)
def test_quick_study_is_sane(tmp_path):
    out = tmp_path / "accuracy.json"
    results = accuracy_vs_time.main(["--quick", "--out", str(out), "--plots",
                                     str(tmp_path / "img")])
    saved = json.loads(out.read_text())
    assert saved["quick"] is True and len(saved["mesh"]) == len(results["mesh"])
    assert len(list((tmp_path / "img").glob("accuracy_*.png"))) == 5

    phong = sorted((r for r in results["mesh"] if r["shading"] == "phong"),
                   key=lambda r: r["subdivisions"])
    errors = [r["highlight_rmse_255"] for r in phong]
    assert all(a > b for a, b in zip(errors, errors[1:], strict=False)), errors
    assert phong[0]["rmse_255"] > phong[-1]["rmse_255"]

    by_factor = {r["factor"]: r["silhouette_rmse_255"] for r in results["supersample"]}
    assert by_factor[2] < 0.6 * by_factor[1]

    f32, f64 = results["precision"]
    assert abs(f32["rmse_255"] - f64["rmse_255"]) < 0.05

    linear = [r for r in results["fitting"] if r["study"] == "method" and
              r["method"] == "linear"]
    assert linear[0]["max_rel_error"] < 1e-3
    for row in results["mesh"] + results["soft"] + results["supersample"]:
        assert np.isfinite([row["fwd_ms"], row["fwd_bwd_ms"], row["rmse_255"]]).all()

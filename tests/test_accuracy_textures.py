"""The quick run of benchmarks/accuracy_textures.py completes, its figures agree with
independent expectations and reproduce the published JSON.

Timings are not asserted. References: texels_per_pixel against a render that reads it off
(a texture whose value is v, lit head-on: the step between two pixels at the sphere's
nearest point is the texels they span); the reference render against one with half its
samples a side (it is converged well below the errors the rows report); the published
rows that the quick rows repeat (same texture, size, sampling and reference).
"""

import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import accuracy_textures as study  # noqa: E402

import diffshade as ds  # noqa: E402
from diffshade.pipeline import render_supersampled  # noqa: E402

pytestmark = pytest.mark.cost(20)  # one quick study shared by the module


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    folder = tmp_path_factory.mktemp("textures")
    payload = study.main(["--quick", "--out", str(folder / "textures.json"),
                          "--plots", str(folder / "img")])
    return folder, payload["rows"]


def test_quick_run_writes_rows_record_and_plot(quick):
    folder, rows = quick
    saved = json.loads((folder / "textures.json").read_text())
    assert saved["quick"] is True and len(saved["rows"]) == len(rows) == 3
    assert (folder / "img" / "accuracy_textures.png").exists()
    assert all(r["fwd_ms"] > 0 and np.isfinite(r["inside_rmse_255"]) for r in rows)


def test_supersampling_and_prefiltering_lower_a_minified_textures_error(quick):
    _, rows = quick
    error = {r["sampling"]: r["inside_rmse_255"] for r in rows}
    assert rows[0]["texels_per_pixel"] > 1.5  # minified: aliasing to lower
    assert error["2×2 samples"] < 0.7 * error["1 sample"]
    assert error["prefiltered to 128²"] < 0.7 * error["1 sample"]


def test_quick_rows_reproduce_the_published_rows(quick):
    _, rows = quick
    published = json.loads((ROOT / study.OUT).read_text())
    assert published["quick"] is False
    for row in rows:
        found = [p for p in published["rows"] if (p["texels"], p["size"], p["sampling"])
                 == (row["texels"], row["size"], row["sampling"])]
        assert len(found) == 1, row
        for key in ("rmse_255", "inside_rmse_255", "texels_per_pixel"):
            assert row[key] == pytest.approx(found[0][key], rel=1e-4), key


def test_texels_per_pixel_is_what_a_render_reads_off():
    size, texels = 64, 256
    v = 1.0 - (np.arange(texels) + 0.5) / texels          # row j holds its v
    ramp = np.repeat(np.repeat(v[:, None, None], texels, 1), 3, 2).astype(np.float32)
    scene = study.textured_scene(ramp, size)
    eye = np.asarray(scene.camera.eye)
    head_on = ds.directional_light(-eye / np.linalg.norm(eye), 1.0)
    scene = ds.make_scene(scene.mesh, scene.camera, [head_on],
                          ds.material(ka=0.0, kd=ds.texture(ramp), ks=None))
    image = np.asarray(ds.render(scene, ds.RenderSettings()))[..., 0]
    centre = size // 2
    # the value is v times a lighting factor within 1e-3 of 1 here: the step in v between
    # two vertical neighbours at the nearest point is their texel count / texels
    step = (image[centre - 2, centre] - image[centre + 2, centre]) / 4
    assert step * texels == pytest.approx(study.texels_per_pixel(texels, size), rel=0.03)


def test_reference_is_converged_well_below_the_rows_errors(quick):
    _, rows = quick
    scene = study.textured_scene(study.random_texels(256), 64)
    fine = np.asarray(render_supersampled(scene, ds.RenderSettings(), study.REFERENCE_SIDE // 64))
    half = np.asarray(render_supersampled(scene, ds.RenderSettings(),
                                          study.REFERENCE_SIDE // 128))
    gap = study.errors(half, fine.astype(np.float64))["inside_rmse_255"]
    assert gap < 0.1 * min(r["inside_rmse_255"] for r in rows)

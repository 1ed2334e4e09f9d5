"""Fitting what photographs contain (fitting.spec.gains, fitting.data.folder): per-view exposure and
white balance, pixels outside a mask or saturated, and a dataset made by hand from a mesh
file and one scene file with several cameras, fitted by `diffshade fit`.

References: targets rendered unclamped, multiplied by known gains and clipped (as a
sensor would), so the true gains and material are known independently of the model's
material-scaling; garbage written into the masked or saturated pixels, which must not
matter, and does matter once the mask is ignored."""

import dataclasses
import json
import math

import imageio.v3 as iio
import numpy as np
import pytest
import trimesh

import diffshade as ds
from data_synth import make_dataset, save_dataset
from diffshade import cli
from fitting import FitSpec, fit, load_dataset
from fitting.spec import material_values

TRUTH = ds.material(ka=(0.35, 0.3, 0.45), kd=(0.6, 0.45, 0.3), ks=(0.4, 0.5, 0.3),
                    shininess=35.0)
NAMES = ("ka", "kd", "ks", "shininess")


def worst_error(values, truth=TRUTH):
    return max(float(np.max(np.abs(np.asarray(values[k]) / np.asarray(getattr(truth, k)) - 1)))
               for k in NAMES)


# ---- exposure and white balance ----


def test_per_view_exposure_is_fitted_back_with_the_material():
    """Views at exposures 1 (the reference), 0.7 and 1.3: the fit recovers both gains and
    the material."""
    exposures = [1.0, 0.7, 1.3]
    dataset = make_dataset(ds.icosphere(2), TRUTH, n_views=3, n_lights=1, size=24, seed=3,
                           gains=exposures)
    result = fit(dataset, FitSpec(exposure=True), with_uncertainty=False)
    np.testing.assert_allclose(result.values["exposure"], exposures[1:], rtol=1e-4)
    assert worst_error(result.values) < 1e-4, result.summary()
    assert "exposure[2]" in result.summary()


def test_gains_need_a_reference_view():
    with pytest.raises(ValueError, match="exposure: got a dataset of 1 view; expected at "
                                         "least 2 views"):
        material_values(TRUTH, FitSpec(exposure=True), n_views=1)


# ---- masks and saturation ----

PATCH = (slice(10, 18), slice(9, 17))


def codes_of(path):
    return iio.imread(path)


def corrupt_folder(folder, rng):
    """Write garbage into one patch of each target PNG, each time left out another way:
    view 0 an RGBA alpha of 0, view 1 a mask file, view 2 a red channel at 255."""
    meta = json.loads((folder / "dataset.json").read_text())
    for entry in meta["views"]:
        (folder / entry.pop("target")).unlink()  # the fit reads the 8-bit sRGB PNGs
    garbage = rng.integers(0, 200, (8, 8, 3))
    rgb = codes_of(folder / "view_000.png")
    rgba = np.concatenate([rgb, np.full(rgb.shape[:2] + (1,), 255, np.uint8)], -1)
    rgba[PATCH] = np.concatenate([garbage, np.zeros((8, 8, 1), int)], -1)
    iio.imwrite(folder / "view_000.png", rgba.astype(np.uint8))
    rgb = codes_of(folder / "view_001.png")
    rgb[PATCH] = garbage[::-1]
    iio.imwrite(folder / "view_001.png", rgb)
    mask = np.full(rgb.shape[:2], 255, np.uint8)
    mask[PATCH] = 0
    iio.imwrite(folder / "view_001_mask.png", mask)
    meta["views"][1]["mask"] = "view_001_mask.png"
    rgb = codes_of(folder / "view_002.png")
    rgb[PATCH + (0,)] = 255
    rgb[PATCH + (slice(1, 3),)] = garbage[..., 1:]
    iio.imwrite(folder / "view_002.png", rgb)
    (folder / "dataset.json").write_text(json.dumps(meta))


def test_masked_and_saturated_pixels_are_left_out(tmp_path):
    dataset = make_dataset(ds.icosphere(2), TRUTH, n_views=2, n_lights=2, size=28, seed=5)
    folder = tmp_path / "photos"
    save_dataset(dataset, folder)
    corrupt_folder(folder, np.random.default_rng(0))
    loaded = load_dataset(folder)
    for i in range(3):
        assert not loaded.views[i].mask[PATCH].any()
    good = fit(loaded, with_uncertainty=False)
    assert worst_error(good.values) < 0.02, good.summary()  # 8-bit sRGB rounding

    ignored = load_dataset(folder, saturation=math.inf)
    ignored = dataclasses.replace(ignored, views=[dataclasses.replace(v, mask=None)
                                                  for v in ignored.views])
    bad = fit(ignored, with_uncertainty=False)
    assert worst_error(bad.values) > 0.1, bad.summary()


# ---- your own mesh and scene file, fitted by `diffshade fit` ----

CAMERAS = [{"eye": [3.0 * math.sin(a), 0.8 * (-1) ** k, 3.0 * math.cos(a)],
            "target": [0, 0, 0], "fov_y": 40, "width": 40, "height": 40}
           for k, a in enumerate(np.radians([20.0, 140.0, 260.0]))]
LIGHTS = [{"type": "directional", "direction": [-0.6, -0.5, -0.6], "color": 0.8},
          {"type": "point", "position": [1.5, 2.5, 3.0], "color": 0.7}]
GAINS = [(1.0, 1.0, 1.0), (0.7 * 1.1, 0.7, 0.7 * 0.85), (1.3 * 0.9, 1.3, 1.3 * 1.15)]


def capsule_folder(folder):
    """An OBJ from trimesh, one scene file with three cameras, 8-bit sRGB PNG targets
    rendered by diffshade at the GAINS, and a dataset.json naming them."""
    folder.mkdir()
    trimesh.creation.capsule(height=1.0, radius=0.6, count=[16, 16]).export(
        folder / "capsule.obj")
    scene = {"mesh": {"path": "capsule.obj"}, "transform": {"rotate_deg": [80, 0, 0]},
             "cameras": CAMERAS, "lights": LIGHTS, "global_ambient": 0.4}
    (folder / "scene.json").write_text(json.dumps(scene))
    scenes, settings = ds.load_scenes(folder / "scene.json")
    unclamped = dataclasses.replace(settings, clamp=False)
    views = []
    for i, view in enumerate(scenes):
        image = np.asarray(ds.render(ds.replace(view, material=TRUTH), unclamped))[..., :3]
        ds.write_png(folder / f"photo_{i}.png", image * np.asarray(GAINS[i]))
        views.append({"scene": "scene.json", "camera": i, "image": f"photo_{i}.png"})
    (folder / "dataset.json").write_text(json.dumps(
        {"format": "diffshade-dataset", "version": 1, "views": views}))


def test_fit_cli_on_a_mesh_file_and_a_scene_file_with_cameras(tmp_path, capsys):
    folder = tmp_path / "capsule"
    capsule_folder(folder)
    out = tmp_path / "result"
    code = cli.main(["fit", str(folder), "-o", str(out), "--quiet",
                     "--fit", "ka,kd,ks,shininess,exposure,white_balance"])
    stdout, err = capsys.readouterr()
    assert code == 0, err
    result = json.loads((out / "result.json").read_text())
    assert result["fit"]["exposure"] is True and result["fit"]["white_balance"] is True
    values = result["values"]
    assert worst_error(values) < 0.03, stdout
    np.testing.assert_allclose(values["exposure"], [g[1] for g in GAINS[1:]], rtol=0.01)
    np.testing.assert_allclose(values["white_balance"],
                               [[g[0] / g[1], g[2] / g[1]] for g in GAINS[1:]], rtol=0.01)
    assert "exposure[1]" in stdout and "white_balance[2][b]" in stdout

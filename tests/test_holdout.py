"""Evaluation on views the fit did not see: `diffshade fit --holdout`, `diffshade render
--material RESULT.json --camera N`, and scene folders that keep working when moved.

The references are independent: PSNR by NumPy over the covered pixels of a diffshade.render
of the fitted material, eroded by one 4-neighbour step (the fit's edge_margin 1)."""

import json
import os
import shutil

import numpy as np
import pytest

import diffshade as ds
from data_synth import make_dataset, save_dataset
from diffshade import cli
from fitting.data.folder import load_dataset
from fitting.report.holdout import rounding_limits

TRUTH = ds.material(ka=0.3, kd=(0.6, 0.4, 0.3), ks=0.4, shininess=25.0)
SIZE = 24


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Three 24 px views (3 cameras x 1 light) with 8-bit targets: view 1 is held out."""
    root = tmp_path_factory.mktemp("holdout") / "data"
    dataset = make_dataset(ds.icosphere(2), TRUTH, n_views=3, n_lights=1, size=SIZE, seed=2,
                           quantize_8bit=True)
    return save_dataset(dataset, root)


def run_cli(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def eroded(covered):
    """covered [H, W] bool minus its pixels with an uncovered 4-neighbour (or the edge)."""
    inside = np.zeros_like(covered)
    for r in range(covered.shape[0]):
        for c in range(covered.shape[1]):
            inside[r, c] = covered[r, c] and all(
                0 <= r + dr < covered.shape[0] and 0 <= c + dc < covered.shape[1]
                and covered[r + dr, c + dc] for dr, dc in ((1, 0), (-1, 0), (0, 1), (0, -1)))
    return inside


def reference_psnr(dataset, index, material):
    """(PSNR linear, PSNR sRGB, counted pixels) of view `index` rendered with `material`."""
    view = dataset.views[index]
    scene = ds.make_scene(dataset.mesh, view.camera, view.lights, material,
                          model=dataset.model, global_ambient=dataset.global_ambient)
    image = np.asarray(ds.render(scene, dataset.settings), np.float64)
    counted = eroded(image[..., 3] > 0.5)
    fitted, target = np.clip(image[..., :3], 0, 1), np.asarray(view.target, np.float64)

    def psnr(a, b):
        return 10 * np.log10(1 / np.mean((a[counted] - b[counted]) ** 2))
    srgb = [srgb_encode(x) for x in (fitted, target)]
    return psnr(fitted, target), psnr(*srgb), int(counted.sum())


@pytest.mark.cost(20)
def test_holdout_fits_the_other_views_and_scores_the_held_one(data, tmp_path, capsys):
    out = tmp_path / "result"
    code, stdout, err = run_cli(["fit", data, "-o", out, "--holdout", "1"], capsys)
    assert code == 0, err
    result = json.loads((out / "result.json").read_text())
    assert result["views"] == [0, 2]
    assert sorted(os.listdir(out)) == sorted(
        ["checkpoint.json", "material.mtl", "result.json", "loss.png", "holdout_001.png"]
        + [f"{kind}_{i:03d}.{ext}" for i in (0, 2) for kind, ext in (
            ("view", "png"), ("residual", "npy"), ("residual", "png"), ("mask", "png"))])
    (entry,) = result["holdout"]
    fitted = ds.material(**{k: result["material"][k] for k in ("ka", "kd", "ks", "shininess")})
    linear, srgb, pixels = reference_psnr(load_dataset(data), 1, fitted)
    assert entry["view"] == 1 and entry["image"] == "holdout_001.png"
    assert entry["pixels"] == pixels
    assert entry["psnr_linear"] == pytest.approx(linear, abs=0.01)
    assert entry["psnr_srgb"] == pytest.approx(srgb, abs=0.01)
    # 8-bit linear targets of the right model: the error is the rounding, whose uniform
    # error over 1/255 steps allows 10 log10(12 * 255^2) dB
    assert entry["psnr_linear_8bit"] == pytest.approx(10 * np.log10(12 * 255**2))
    assert abs(entry["psnr_linear"] - entry["psnr_linear_8bit"]) < 2
    row = stdout.splitlines()[stdout.splitlines().index(next(
        line for line in stdout.splitlines() if line.startswith("held-out view"))) + 1]
    assert row.split()[:3] == ["1", str(pixels), f"{entry['psnr_linear']:.2f}"]
    panel = ds.read_image(out / "holdout_001.png")
    assert panel.shape == (SIZE, 3 * SIZE + 2 * 2, 3)


@pytest.mark.parametrize("holdout, expected", [
    ("3", "--holdout: got 3; expected view indices below 3"),
    ("0,1,2", "--holdout: got 0,1,2; expected at most 2 of the 3 views"),
    ("1,1", "argument --holdout: got '1,1'; expected distinct view indices"),
    ("one", "argument --holdout: got 'one'; expected distinct view indices"),
])
def test_bad_holdout_is_one_line_and_writes_nothing(data, tmp_path, capsys, holdout, expected):
    out = tmp_path / "result"
    code, _, err = run_cli(["fit", data, "-o", out, "--holdout", holdout], capsys)
    assert code == 2 and err.startswith(f"diffshade: error: {expected}"), err
    assert len(err.splitlines()) == 1 and not out.exists()


def srgb_encode(x):
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def srgb_decode(y):
    return np.where(y <= 0.04045, y / 12.92, ((y + 0.055) / 1.055) ** 2.4)


def test_rounding_limits_of_8bit_targets():
    """Linear codes: 10 log10(3 / h^2) with h = 0.5/255 on linear values; sRGB codes: that
    on sRGB values, and on linear values h is half the code's interval through the curve
    (the larger side), computed here code by code."""
    rng = np.random.default_rng(3)
    codes = rng.integers(1, 255, size=(6, 5, 3))
    counted = rng.random((6, 5)) < 0.7
    flat = 10 * np.log10(3 / (0.5 / 255) ** 2)
    linear, _ = rounding_limits(codes / 255.0, counted)
    assert linear == pytest.approx(flat)
    linear, srgb = rounding_limits(srgb_decode(codes / 255.0), counted)
    half = [max(srgb_decode((c + 0.5) / 255) - srgb_decode(c / 255),
                srgb_decode(c / 255) - srgb_decode((c - 0.5) / 255))
            for c in codes[counted].ravel()]
    assert srgb == pytest.approx(flat)
    assert linear == pytest.approx(10 * np.log10(3 / np.mean(np.square(half))), rel=1e-6)
    assert rounding_limits(codes / 255.0 + 1e-3, counted) == (None, None)


def two_camera_scene(folder):
    """A scene file with two cameras and its mesh in a file beside it ('mesh.obj')."""
    folder.mkdir()
    mesh = ds.icosphere(1)
    lines = [f"v {x} {y} {z}" for x, y, z in np.asarray(mesh.vertices)]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.asarray(mesh.faces)]
    (folder / "mesh.obj").write_text("\n".join(lines) + "\n")
    scene = {"mesh": {"path": "mesh.obj"}, "material": {"kd": 0.5},
             "cameras": [{"eye": [0, 0, 3], "target": [0, 0, 0], "width": 16, "height": 16},
                         {"eye": [3, 0, 0], "target": [0, 0, 0], "width": 16, "height": 16}],
             "lights": [{"type": "point", "position": [2, 2, 2], "color": 20.0,
                         "attenuation": [0, 0, 1]}]}
    (folder / "scene.json").write_text(json.dumps(scene))
    return folder / "scene.json"


def test_render_picks_a_camera_and_takes_a_fitted_material(tmp_path, capsys, monkeypatch):
    path = two_camera_scene(tmp_path / "capture")
    material = {"ka": 0.1, "kd": [0.2, 0.5, 0.7], "ks": 0.3, "shininess": 12.0,
                "emission": None, "kt": None}
    result = tmp_path / "result.json"
    result.write_text(json.dumps({"format": "diffshade-fit-result", "material": material}))
    out = tmp_path / "view1.npy"
    assert run_cli(["render", path, "--camera", "1", "--material", result, "-o", out],
                   capsys)[0] == 0
    scenes, settings = ds.load_scenes(path)
    want = ds.render(ds.replace(scenes[1], material=ds.material(**material)), settings)
    np.testing.assert_allclose(np.load(out), np.asarray(want), atol=1e-6)
    code, _, err = run_cli(["render", path, "-o", tmp_path / "x.png"], capsys)
    assert code == 2 and "has 2 cameras; expected --camera N to pick one (0 to 1)" in err
    code, _, err = run_cli(["render", path, "--camera", "2", "-o", tmp_path / "x.png"], capsys)
    assert code == 2 and "--camera: got 2; expected an index below 2" in err
    result.write_text(json.dumps({"material": {"kd": "red"}}))
    code, _, err = run_cli(["render", path, "--camera", "0", "--material", result, "-o",
                            tmp_path / "x.png"], capsys)
    assert code == 2 and f"{result}: material.kd: got \"red\"" in err, err
    assert not (tmp_path / "x.png").exists()


def test_a_scene_folder_keeps_working_when_moved(tmp_path, capsys, monkeypatch):
    """Mesh paths are relative to the scene file: a moved folder renders the same from any
    working directory; save_scene writes an absolute mesh path relative to the file."""
    path = two_camera_scene(tmp_path / "capture")
    before = tmp_path / "before.npy"
    assert run_cli(["render", path, "--camera", "0", "-o", before], capsys)[0] == 0
    moved = tmp_path / "elsewhere" / "copy"
    shutil.copytree(path.parent, moved)
    shutil.rmtree(path.parent)
    monkeypatch.chdir(tmp_path / "elsewhere")
    assert run_cli(["render", "copy/scene.json", "--camera", "0", "-o", "after.npy"],
                   capsys)[0] == 0
    np.testing.assert_array_equal(np.load(tmp_path / "elsewhere" / "after.npy"),
                                  np.load(before))
    scenes, settings = ds.load_scenes(moved / "scene.json")
    ds.save_scene(moved / "saved.json", scenes[0], settings, mesh_ref=moved / "mesh.obj")
    assert json.loads((moved / "saved.json").read_text())["mesh"] == {"path": "mesh.obj"}
    shutil.move(moved, tmp_path / "third")
    assert ds.load_scene(tmp_path / "third" / "saved.json")[0].mesh.faces.shape == (80, 3)


def test_resume_keeps_the_views_held_out(data, tmp_path, capsys):
    out = tmp_path / "result"
    assert run_cli(["fit", data, "-o", out, "--holdout", "2", "--method", "adam", "--steps",
                    "2"], capsys)[0] == 0
    code, _, err = run_cli(["fit", data, "-o", out, "--resume", "--holdout", "0"], capsys)
    assert code == 2 and "--holdout: got 0; the checkpoint" in err and "[2]" in err, err
    assert run_cli(["fit", data, "-o", out, "--resume", "--steps", "4"], capsys)[0] == 0
    result = json.loads((out / "result.json").read_text())
    assert result["views"] == [0, 1] and [e["view"] for e in result["holdout"]] == [2]
    assert result["n_steps"] == 4

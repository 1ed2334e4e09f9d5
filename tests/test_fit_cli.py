"""Tests for `diffshade synth` and `diffshade fit` (data_synth.cli, fitting.cli) and the
files they write (fitting.report.result, fitting.checkpoint).

References: datasets made through the API (make_dataset), the known true material,
relative errors and panels recomputed with numpy from the files, an uninterrupted run
for resumed ones, and the folders' listings (no partial or temporary file may remain).
The interrupt tests run `diffshade fit` in a subprocess and signal it."""

import dataclasses
import io
import json
import math
import os
import signal
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffshade as ds
import fitting.run as run_module
from data_synth import load_dataset, make_dataset, save_dataset
from diffshade import cli
from diffshade.io.images import image_transfer
from fitting import FitOptions, FitSpec, fit
from fitting.cli import _progress
from fitting.inputs import fit_spec, parse_material
from fitting.report.result import (
    CURVE_COLOR,
    CURVE_SIZE,
    ERROR_GAIN,
    PANEL_GAP,
    loss_curve,
    mtl_text,
    result_dict,
)

TRUTH = dict(ka=(0.35, 0.3, 0.5), kd=(0.6, 0.45, 0.3), ks=(0.4, 0.5, 0.3), shininess=35.0)
SIZE = 32
MAIN = "import sys; from diffshade.cli import main; sys.exit(main())"


def truth_material():
    return ds.material(**TRUTH)


@pytest.fixture(scope="module")
def data_root(tmp_path_factory):
    """Two 32 px datasets of a subdivision-2 icosphere (1 camera x 2 lights): 'clean'
    (float targets) and 'noisy' (noise 0.01, so that Adam never reaches the loss floor)."""
    root = tmp_path_factory.mktemp("datasets")
    for name, noise in (("clean", 0.0), ("noisy", 0.01)):
        dataset = make_dataset(ds.icosphere(2), truth_material(), n_views=1, n_lights=2,
                               size=SIZE, noise_std=noise, seed=4)
        save_dataset(dataset, root / name)
    return root


def copy_dataset(src, dst):
    dst.mkdir()
    for name in os.listdir(src):
        (dst / name).write_bytes((src / name).read_bytes())
    return dst


def run_cli(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def one_error_line(err):
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("diffshade: error: "), err
    assert "Traceback" not in err
    return lines[0]


def strict_json(path):
    def reject(name):
        raise AssertionError(f"{path} holds {name}")
    with open(path, encoding="utf-8") as file:
        return json.load(file, parse_constant=reject)


def listing(folder):
    """Every file and folder under `folder`, hidden ones included."""
    return sorted(os.path.relpath(os.path.join(d, n), folder)
                  for d, dirs, files in os.walk(folder) for n in dirs + files)


def assert_no_temporaries(folder):
    hidden = [name for name in listing(folder) if os.path.basename(name).startswith(".")]
    assert hidden == [], hidden


# ---- synth ----


def test_synth_writes_the_api_dataset_atomically(tmp_path, capsys):
    out = tmp_path / "data"
    argv = ["synth", "--shape", "box", "--material", "0.3,0.5,0.4,30", "--views", "1",
            "--lights", "2", "--size", "24", "--seed", "3", "--noise", "0.02",
            "--quantize-8bit", "-o", out]
    code, stdout, err = run_cli(argv, capsys)
    assert (code, stdout, err) == (0, f"{out}\n", "")
    want = make_dataset("box", ds.material(ka=0.3, kd=0.5, ks=0.4, shininess=30.0), n_views=1,
                        n_lights=2, size=24, seed=3, noise_std=0.02, quantize_8bit=True)
    got = load_dataset(out)
    assert len(got.views) == 2
    for a, b in zip(got.views, want.views, strict=True):
        np.testing.assert_array_equal(a.target, b.target)
        assert np.all(np.abs(a.target * 255 - np.round(a.target * 255)) < 1e-3)  # 8-bit
    for name in ("ka", "kd", "ks", "shininess"):
        np.testing.assert_allclose(getattr(got.truth, name), getattr(want.truth, name))
    # a second run replaces the dataset folder and leaves nothing else beside it
    code, _, _ = run_cli(["synth", "--size", "16", "--views", "1", "--lights", "1",
                          "--material", tmp_path / "data" / "truth.json", "-o", out], capsys)
    assert code == 0 and len(load_dataset(out).views) == 1
    assert listing(tmp_path) == ["data"] + [f"data/{n}" for n in sorted(os.listdir(out))]


@pytest.mark.parametrize("args, message", [
    (["--views", "0"], "argument --views: got '0'; expected a positive integer"),
    (["--size", "-3"], "argument --size: got '-3'; expected a positive integer"),
    (["--noise", "nan"], "argument --noise: got 'nan'; expected a finite number >= 0"),
    (["--seed", "-1"], "--seed: got -1; expected an integer >= 0"),
    (["--material", "1,2"], "--material: got '1,2'; expected KA,KD,KS,N"),
    (["--material", "0.2,0.5,0.3,-4"], "--material: shininess: got -4.0"),
    (["--material", "missing.json"], "--material: material file not found"),
    (["--shape", "sphere"], "shape: got 'sphere'; expected one of"),
    (["--shape", "missing.obj"], "missing.obj"),
    (["--shading", "toon"], "argument --shading: invalid choice: 'toon'"),
])
def test_synth_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, args, message):
    code, out, err = run_cli(["synth", "--size", "8", *args, "-o", tmp_path / "data"], capsys)
    assert code == 2 and out == ""
    assert message in one_error_line(err)
    assert listing(tmp_path) == []


@pytest.mark.parametrize("existing", ["file", "other_folder"])
def test_synth_refuses_to_overwrite_what_is_not_a_dataset(tmp_path, capsys, existing):
    target = tmp_path / "out"
    if existing == "file":
        target.write_text("keep me")
    else:
        target.mkdir()
        (target / "notes.txt").write_text("keep me")
    before = listing(tmp_path)
    code, _, err = run_cli(["synth", "--size", "8", "-o", target], capsys)
    assert code == 2 and "--output:" in one_error_line(err)
    assert listing(tmp_path) == before


# ---- fit: results ----


def test_fit_writes_results_that_match_the_truth(data_root, tmp_path, capsys):
    out = tmp_path / "result"
    code, stdout, err = run_cli(["fit", data_root / "clean", "-o", out], capsys)
    assert code == 0 and err == ""
    result = strict_json(out / "result.json")
    assert result["status"] == "converged" and result["interrupted"] is False
    assert result["method"] == "linear" and result["loss_kind"] == "mse"
    for name, true in TRUTH.items():
        fitted = np.asarray(result["values"][name])
        np.testing.assert_allclose(fitted, true, rtol=1e-3)
        stored = np.asarray(result["truth"][name])  # float32, as the targets were made
        np.testing.assert_allclose(stored, true, rtol=1e-6)
        np.testing.assert_allclose(result["errors"][name],
                                   np.abs(fitted - stored) / stored, rtol=1e-6, atol=1e-12)
    assert set(result["std_errors"]) == {f"{c}[{x}]" for c in ("ka", "kd", "ks")
                                         for x in "rgb"} | {"shininess"}
    assert len(result["loss_history"]) == result["n_steps"] + 1
    assert result["loss"] == min(result["loss_history"])
    # the table: one row per scalar with the true value first, the fitted value second
    rows = {line.split()[0]: line.split() for line in stdout.splitlines()
            if line.split() and line.split()[0] in ("ka[r]", "kd[b]", "shininess")}
    assert float(rows["kd[b]"][1]) == pytest.approx(TRUTH["kd"][2], rel=1e-4)
    assert float(rows["shininess"][2]) == pytest.approx(result["values"]["shininess"], rel=1e-4)
    assert stdout.splitlines()[-11:] == [str(out / n) for n in (
        "material.mtl", "result.json", "loss.png", "view_000.png", "view_001.png",
        "residual_000.npy", "residual_000.png", "mask_000.png", "residual_001.npy",
        "residual_001.png", "mask_001.png")]
    assert result["at_bound"] == [] and result["misfit"]["explained"] is True
    assert_no_temporaries(out)


def test_fit_panels_mtl_and_loss_curve(data_root, tmp_path, capsys):
    out = tmp_path / "result"
    assert run_cli(["fit", data_root / "clean", "-o", out], capsys)[0] == 0
    result = strict_json(out / "result.json")
    dataset = load_dataset(data_root / "clean")
    panel = ds.read_image(out / "view_001.png")
    assert panel.shape == (SIZE, 4 * SIZE + 3 * PANEL_GAP, 3)
    tiles = [panel[:, k * (SIZE + PANEL_GAP):k * (SIZE + PANEL_GAP) + SIZE] for k in range(4)]
    target = dataset.views[1].target
    assert image_transfer(out / "view_001.png") == "srgb"
    tiles = [ds.linear_to_srgb(tile) for tile in tiles]  # compared as the file's 8-bit codes
    levels = lambda x: np.round(ds.linear_to_srgb(np.clip(x, 0, 1)) * 255) / 255  # noqa: E731
    np.testing.assert_allclose(tiles[0], levels(target), atol=1e-6)
    scene = ds.make_scene(dataset.mesh, dataset.views[1].camera, dataset.views[1].lights,
                          ds.material(0.3, 0.5, 0.3, 20.0), model=dataset.model,
                          global_ambient=dataset.global_ambient)
    initial = np.asarray(ds.render(scene, dataset.settings))[..., :3]
    np.testing.assert_allclose(tiles[1], levels(initial), atol=1.5 / 255)
    np.testing.assert_allclose(tiles[2], levels(target), atol=1.5 / 255)  # fit ~ truth
    assert ds.srgb_to_linear(tiles[3]).max() <= ERROR_GAIN * 1.5 / 255 + 1.5 / 255
    mtl = dict(line.split(maxsplit=1) for line in (out / "material.mtl").read_text().splitlines()
               if line and not line.startswith("#"))
    assert mtl["newmtl"] == "diffshade_fit" and mtl["illum"] == "2"
    for key, name in (("Ka", "ka"), ("Kd", "kd"), ("Ks", "ks")):
        np.testing.assert_allclose([float(x) for x in mtl[key].split()],
                                   result["material"][name], atol=1e-6)
    assert float(mtl["Ns"]) == pytest.approx(result["material"]["shininess"], abs=1e-5)
    curve = ds.read_image(out / "loss.png")
    assert curve.ndim == 3 and curve.shape[2] == 3 and curve.std() > 0.05


def curve_pixels(history):
    """(rows, columns) of the loss line's pixels in loss_curve(history)."""
    image = loss_curve(history, "title")
    assert image.shape == (CURVE_SIZE[1], CURVE_SIZE[0], 3)
    assert image.min() >= 0.0 and image.max() <= 1.0
    codes = np.round(ds.linear_to_srgb(image) * 255)
    return np.nonzero(np.all(codes == CURVE_COLOR, axis=-1))


@pytest.mark.parametrize("steps", [8, 300])  # with a marker per step, and without
def test_loss_curve_has_a_log_axis(steps):
    # a loss that falls by the same factor every step is a straight line on a log axis
    # (on a linear one it would bend), falling from left to right across the plot
    rows, cols = curve_pixels(1e-2 * 0.3 ** np.arange(steps))
    slope, intercept = np.polyfit(cols, rows, 1)
    assert slope > 0.2  # image rows grow downwards
    assert np.abs(rows - (slope * cols + intercept)).max() <= 4.5  # marker radius, width
    assert cols.max() - cols.min() > CURVE_SIZE[0] // 2
    # a loss that falls and then stays: the line ends level
    rows, cols = curve_pixels(np.r_[1e-2 * 0.3 ** np.arange(10), np.full(30, 1e-2 * 0.3**9)])
    right = cols > np.percentile(cols, 60)
    assert np.ptp(rows[right]) <= 7  # markers of radius 3 on a level line


@pytest.mark.parametrize("history", [[0.003], [0.0, 0.0], [1e-3, 0.0, 1e-5], [2.0, 2.0]])
def test_loss_curve_draws_single_zero_and_flat_histories(history):
    rows, _ = curve_pixels(history)
    assert rows.size > 0


def test_fit_without_truth_has_no_error_columns(data_root, tmp_path, capsys):
    data = copy_dataset(data_root / "clean", tmp_path / "data")
    os.remove(data / "truth.json")
    out = tmp_path / "result"
    code, stdout, _ = run_cli(["fit", data, "-o", out], capsys)
    assert code == 0
    result = strict_json(out / "result.json")
    assert "errors" not in result and "truth" not in result
    np.testing.assert_allclose(result["values"]["kd"], TRUTH["kd"], rtol=1e-3)
    header = next(line for line in stdout.splitlines() if line.startswith("parameter"))
    assert header.split() == ["parameter", "fitted", "±", "s.e."]


def test_fit_subset_holds_the_rest_at_init(data_root, tmp_path, capsys):
    init = tmp_path / "init.json"
    init.write_text(json.dumps(TRUTH | {"kd": 0.5, "shininess": 10.0}))
    out = tmp_path / "result"
    argv = ["fit", data_root / "clean", "-o", out, "--fit", "kd,shininess", "--grey", "kd",
            "--init", init]
    assert run_cli(argv, capsys)[0] == 0
    result = strict_json(out / "result.json")
    assert result["fit"] == {"ka": None, "kd": "grey", "ks": None, "shininess": True,
                             "kt": None, "light_colors": False, "light_positions": False,
                             "exposure": False, "white_balance": False}
    assert set(result["values"]) == {"kd", "shininess"} and set(result["errors"]) == {
        "kd", "shininess"}
    np.testing.assert_allclose(result["material"]["ka"], TRUTH["ka"], rtol=1e-6)
    np.testing.assert_allclose(result["material"]["ks"], TRUTH["ks"], rtol=1e-6)
    assert np.ndim(result["values"]["kd"]) == 0
    # a grey kd cannot match an RGB truth: the errors are per channel, against each one
    kd = result["values"]["kd"]
    np.testing.assert_allclose(result["errors"]["kd"],
                               np.abs(kd - np.array(TRUTH["kd"])) / np.array(TRUTH["kd"]),
                               rtol=1e-6)


def test_fit_spec_from_names():
    assert fit_spec() == FitSpec()
    assert fit_spec("ka,shininess", "ka") == FitSpec(ka="grey", kd=None, ks=None)
    assert fit_spec("kd,ks", None) == FitSpec(ka=None, shininess=False)
    material = parse_material("0.1,0.2,0.3,40", "--init")
    np.testing.assert_allclose(material.kd, [0.2] * 3)
    assert float(material.shininess) == 40.0


@pytest.mark.parametrize("content, message", [
    ('{"ka": 0.2, "kd": 0.3, "shininess": "abc"}', "shininess: got 'abc'; expected a number"),
    ('{"ka": 0.2, "kd": [0.3, true, 1], "shininess": 3}', "kd: got [0.3, True, 1]"),
    ('{"ka": 0.2, "gloss": 3}', "has ['gloss']; expected an object with keys"),
    ('{"ka": 0.2, "kd": [0.3, 0.1], "shininess": 3}', "material.json': kd: got [0.3, 0.1]"),
    ("[1, 2]", "has list; expected an object"),
    ("{oops", "is not valid JSON"),
])
def test_parse_material_names_the_problem(tmp_path, content, message):
    path = tmp_path / "material.json"
    path.write_text(content)
    with pytest.raises(ValueError, match="^--init: ") as caught:
        parse_material(str(path), "--init")
    assert message in str(caught.value)


# ---- fit: bad input ----


def break_dataset(folder, how):
    if how == "missing_scene_file":
        os.remove(folder / "view_001.json")
    elif how == "wrong_target_size":
        np.save(folder / "view_001.npy", np.zeros((SIZE, SIZE + 1, 3), np.float32))
    elif how == "nan_target":
        target = np.load(folder / "view_001.npy")
        target[5, 7, 1] = np.nan
        np.save(folder / "view_001.npy", target)
    elif how in ("face_out_of_range", "nan_vertex"):
        scene = json.loads((folder / "view_001.json").read_text())
        if how == "face_out_of_range":
            scene["mesh"]["faces"][2][1] = 10**6
        else:
            scene["mesh"]["vertices"][4][0] = float("nan")
        (folder / "view_001.json").write_text(json.dumps(scene))
    elif how == "bad_dataset_json":
        (folder / "dataset.json").write_text("{not json")
    elif how == "no_views":
        meta = json.loads((folder / "dataset.json").read_text())
        (folder / "dataset.json").write_text(json.dumps(meta | {"views": []}))
    elif how == "negative_target":
        target = np.load(folder / "view_001.npy")
        target[3, 4, 2] = -0.5
        np.save(folder / "view_001.npy", target)
    elif how == "huge_width":
        scene = json.loads((folder / "view_001.json").read_text())
        scene["camera"]["width"] = 10**30
        (folder / "view_001.json").write_text(json.dumps(scene))
    elif how in ("deep_dataset_json", "deep_scene_file"):
        name = "dataset.json" if how == "deep_dataset_json" else "view_001.json"
        (folder / name).write_text("[" * 100_000 + "]" * 100_000)
    elif how == "other_mesh":
        scene = json.loads((folder / "view_001.json").read_text())
        scene["mesh"]["vertices"][4][0] += 0.5
        (folder / "view_001.json").write_text(json.dumps(scene))


@pytest.mark.parametrize("how, message", [
    ("missing_scene_file", "scene file not found: "),
    ("wrong_target_size", "views[1].target: got shape (32, 33, 3); expected (32, 32, 3)"),
    ("nan_target", "target image of view 1 (view_001.npy) contains NaN at pixel "
                   "(row 5, column 7)"),
    ("bad_dataset_json", "dataset.json: line 1, column 2: invalid JSON"),
    ("face_out_of_range", "view_001.json: mesh.faces: index 1e+06 out of range for 162 "
                          "vertices"),
    ("nan_vertex", "view_001.json: mesh.vertices: row 4 is [nan,"),
    ("no_views", "dataset.json: views: got []; expected a non-empty list of view objects"),
    ("negative_target", "target image of view 1 (view_001.npy) contains -0.5 at pixel "
                        "(row 3, column 4)"),
    ("huge_width", "view_001.json: camera.width: got 1000000000000000000000000000000; "
                   "expected a positive integer of pixels, at most 16384"),
    ("deep_dataset_json", "dataset.json: nested too deeply to parse"),
    ("deep_scene_file", "view_001.json: nested too deeply to parse"),
    ("other_mesh", "views[1] (view_001.json): its mesh differs from views[0]'s"),
])
def test_fit_rejects_a_broken_dataset(data_root, tmp_path, capsys, how, message):
    data = copy_dataset(data_root / "clean", tmp_path / "data")
    break_dataset(data, how)
    code, out, err = run_cli(["fit", data, "-o", tmp_path / "result"], capsys)
    assert code == 2 and out == ""
    assert message in one_error_line(err)
    assert not (tmp_path / "result").exists()


@pytest.mark.parametrize("args, message", [
    (["--fit", "ka,gloss"], "--fit: got 'ka,gloss'; expected distinct comma-separated names"),
    (["--fit", ""], "--fit: got ''"),
    (["--fit", "kd", "--grey", "ks"], "--grey: 'ks' is not fitted (--fit kd)"),
    (["--steps", "0"], "argument --steps: got '0'; expected a positive integer"),
    (["--steps", "-5"], "argument --steps: got '-5'; expected a positive integer"),
    (["--method", "newton"], "argument --method: invalid choice: 'newton'"),
    (["--init", "0.1,0.2,x,4"], "--init: got '0.1,0.2,x,4'; expected KA,KD,KS,N"),
    (["--resume"], "checkpoint not found"),
    (["--lr", "0"], "argument --lr: got '0'; expected a finite number > 0"),
    (["--gtol", "-1"], "argument --gtol: got '-1'; expected a finite number >= 0"),
    (["--shininess-range", "5,2"], "argument --shininess-range: got '5,2'; expected LOW,HIGH"),
    (["--fit", "kd,lights"], "--fit: got 'kd,lights'; expected distinct comma-separated"),
    (["--devices", "0"], "argument --devices: got '0'; expected 'all' or an integer >= 1"),
    (["--devices", "4096"], "--devices: got 4096; expected at most"),
    (["--method", "lbfgs", "--chunk", "2"], "--chunk: got 2; 'lbfgs' evaluates its line"),
])
def test_fit_rejects_bad_options(data_root, tmp_path, capsys, args, message):
    code, out, err = run_cli(["fit", data_root / "clean", "-o", tmp_path / "result", *args],
                             capsys)
    assert code == 2 and out == ""
    assert message in one_error_line(err)
    assert listing(tmp_path) == []


def test_fit_rejects_missing_dataset_and_file_output(data_root, tmp_path, capsys):
    code, _, err = run_cli(["fit", tmp_path / "nowhere", "-o", tmp_path / "result"], capsys)
    assert code == 2 and "DATASET: folder not found" in one_error_line(err)
    blocker = tmp_path / "result.txt"
    blocker.write_text("keep me")
    code, _, err = run_cli(["fit", data_root / "clean", "-o", blocker], capsys)
    assert code == 2 and "is a file; expected a folder" in one_error_line(err)
    assert listing(tmp_path) == ["result.txt"] and blocker.read_text() == "keep me"


# ---- fit: no silent NaN ----


LOG_SHININESS_LIMIT = math.log(25.0)


@jax.custom_jvp
def nan_slope_beyond_limit(log_shininess):
    """0, with a derivative that is NaN beyond LOG_SHININESS_LIMIT and 0 below it."""
    return jnp.zeros_like(log_shininess)


@nan_slope_beyond_limit.defjvp
def _nan_slope_jvp(primals, tangents):
    slope = jnp.where(primals[0] > LOG_SHININESS_LIMIT, jnp.nan, 0.0)
    return nan_slope_beyond_limit(primals[0]), slope * tangents[0]


@pytest.fixture
def fresh_steps():
    """The compiled steps and gradients are cached per configuration: a test that swaps
    the loss needs them rebuilt before and after."""
    steps, gradients = run_module.optax_step, run_module.gradients

    def clear():
        steps.cache_clear()
        gradients.clear_cache()
    clear()
    yield
    clear()


def test_non_finite_gradient_stops_the_fit_naming_the_parameter(
        data_root, tmp_path, capsys, monkeypatch, fresh_steps):
    """Beyond shininess 25 the gradient with respect to shininess is NaN (the loss stays
    finite): the steps are rejected and the fit stops with exit 3, naming shininess only;
    the result holds the best parameters with a finite loss."""
    real = run_module.make_loss

    def poisoned(spec, kind):
        loss = real(spec, kind)
        return lambda p, data: loss(p, data) + nan_slope_beyond_limit(p["shininess"])
    monkeypatch.setattr(run_module, "make_loss", poisoned)
    out = tmp_path / "result"
    code, stdout, err = run_cli(["fit", data_root / "clean", "-o", out, "--method", "adam",
                                 "--steps", "200"], capsys)
    assert code == 3
    line = one_error_line(err)
    assert "fit stopped" in line and "non-finite gradient with respect to: shininess = " in line
    assert "ka[" not in line and "kd[" not in line
    result = strict_json(out / "result.json")
    assert result["status"] == "non-finite" and result["rejected_steps"] == 5
    assert 0 < result["n_steps"] < 200 and 20.0 < result["values"]["shininess"] < 35.0
    assert all(math.isfinite(x) for x in result["loss_history"])
    assert "result.json" in stdout


def test_transient_non_finite_losses_are_skipped(data_root, tmp_path, capsys, monkeypatch):
    """Two steps in a row on NaN targets (fewer than the 5 that stop a fit) go through the
    real step: optax.apply_if_finite rejects them, they are not counted, and the fit
    finishes its budget."""
    real = run_module.optax_step
    calls = []

    def flaky(*config):
        step, optimizer = real(*config)

        def step_fn(params, state, data):
            calls.append(1)
            if len(calls) in (4, 5):  # the steps read the views stacked (fitting.model.batch)
                views = data.views
                data = dataclasses.replace(data, views=dataclasses.replace(views, samples=tuple(
                    dataclasses.replace(v, target=v.target * jnp.nan) for v in views.samples)))
            return step(params, state, data)
        return step_fn, optimizer
    monkeypatch.setattr(run_module, "optax_step", flaky)
    out = tmp_path / "result"
    code, _, err = run_cli(["fit", data_root / "clean", "-o", out, "--method", "adam",
                            "--steps", "12"], capsys)
    # 12 Adam steps do not fit the images: the misfit warning says so, nothing else does
    assert code == 0 and [line for line in err.splitlines() if "warning" not in line] == []
    assert "the fit has not converged (status 'budget')" in err
    result = strict_json(out / "result.json")
    assert result["rejected_steps"] == 2 and result["n_steps"] == 12 and len(calls) == 14
    assert len(result["loss_history"]) == 13


def test_a_fit_without_any_finite_loss_writes_nothing(data_root, tmp_path, capsys,
                                                      monkeypatch):
    monkeypatch.setattr(run_module, "loss_at", lambda *args: jnp.asarray(jnp.nan))
    out = tmp_path / "result"
    code, stdout, err = run_cli(["fit", data_root / "clean", "-o", out], capsys)
    assert code == 3 and stdout == ""
    line = one_error_line(err)
    assert "the loss or its gradient was not finite at step 0" in line
    assert "none (the loss itself is not finite)" in line and "nothing written" in line
    assert not out.exists()


def test_result_dict_never_holds_nan():
    class Stub:
        material = truth_material()
        values, object_names = {}, None

        def as_dict(self):
            return {"loss": float("nan"), "std_errors": {"ka[r]": float("inf")},
                    "errors": None, "notes": []}
    out = result_dict(Stub(), truth_material(), None)
    assert out["loss"] is None and out["std_errors"] == {"ka[r]": None}
    assert "errors" not in out and "truth" not in out
    assert out["notes"] == ["non-finite values written as null: loss, std_errors.ka[r]"]
    json.dumps(out, allow_nan=False)


def test_mtl_notes_a_shininess_viewers_clamp():
    text = mtl_text(ds.material(ka=0.1, kd=0.2, ks=0.3, shininess=1500.0))
    assert "Ns 1500.000000" in text and "# note: Ns = 1500 > 1000" in text
    no_specular = mtl_text(ds.material(ka=0.1, kd=0.2))
    assert "Ks 0.000000 0.000000 0.000000" in no_specular and "illum 1" in no_specular


# ---- fit: checkpoints, resume, interrupts ----


# the linear method's search is held below the true shininess (35) so that
# Levenberg-Marquardt has real steps to take: from the unrestricted closed form its first
# step changes the loss by ~2e-7 relative, at float32 rounding, and may be rejected
@pytest.mark.parametrize("method, options, first, total", [
    ("adam", ["--tol", "0.003", "--patience", "3", "--lr", "0.03", "--lr-shininess", "0.1",
              "--gtol", "1e-9"], 12, 60),
    ("linear", ["--tol", "1e-12", "--shininess-range", "2,20", "--edge-margin", "2"], 1, 10),
])
def test_resume_continues_the_same_trajectory(data_root, tmp_path, capsys, method, options,
                                              first, total):
    """A fit stopped after `first` steps and resumed with --resume --steps only ends
    exactly where an uninterrupted one ends: every option (here all unlike the defaults;
    --tol makes the Adam run converge at step 44 instead of running to 60) and the
    optimizer state (Adam's moments, Levenberg-Marquardt's damping) come from the
    checkpoint."""
    straight, split = tmp_path / "straight", tmp_path / "split"
    base = ["fit", data_root / "noisy", "--method", method, "--checkpoint-every", "5", *options]
    assert run_cli([*base, "-o", straight, "--steps", total], capsys)[0] == 0
    assert run_cli([*base, "-o", split, "--steps", first], capsys)[0] == 0
    assert strict_json(split / "checkpoint.json")["step"] == first
    code, _, err = run_cli(["fit", data_root / "noisy", "-o", split, "--resume", "--steps",
                            total], capsys)
    assert (code, err) == (0, "")
    a, b = strict_json(straight / "result.json"), strict_json(split / "result.json")
    assert b["n_steps"] == a["n_steps"] and a["method"] == b["method"] == method
    assert (a["status"], a["n_steps"]) == (("converged", 44) if method == "adam"
                                           else (a["status"], a["n_steps"]))
    assert a["options"] == b["options"]
    np.testing.assert_allclose(b["loss_history"], a["loss_history"], rtol=1e-6)
    for name in TRUTH:
        np.testing.assert_allclose(b["values"][name], a["values"][name], rtol=1e-6)


def test_resume_rejects_other_options_or_data(data_root, tmp_path, capsys):
    out = tmp_path / "result"
    assert run_cli(["fit", data_root / "clean", "-o", out, "--method", "adam", "--steps",
                    "3"], capsys)[0] == 0
    before = (out / "result.json").read_bytes()
    for argv, message in (
            ([data_root / "clean", "--method", "lbfgs"],
             "--method: got 'lbfgs'; the checkpoint"),
            ([data_root / "clean", "--fit", "kd"], "--fit/--grey: describe another fit"),
            ([data_root / "clean", "--tol", "0.5"],
             "--tol: got 0.5; the checkpoint"),
            ([data_root / "clean", "--lr", "0.2"], "--lr: got 0.2; the checkpoint"),
            ([data_root / "noisy"], "holds other targets than the dataset the checkpoint")):
        code, _, err = run_cli(["fit", argv[0], "-o", out, "--resume", *argv[1:]], capsys)
        assert code == 2 and message in one_error_line(err)
    assert (out / "result.json").read_bytes() == before
    # where the fit runs may change: views streamed in chunks of one (fitting.solve.distribute)
    code, _, err = run_cli(["fit", data_root / "clean", "-o", out, "--resume", "--steps",
                            "5", "--chunk", "1"], capsys)
    assert code == 0 and "error" not in err  # (a warning: 5 Adam steps do not converge)
    saved = strict_json(out / "checkpoint.json")
    assert saved["step"] == 5 and saved["options"]["chunk"] == 1


def start_fit(data, out, env):
    """`diffshade fit` in a subprocess (environment `env`: conftest's cli_env), with a step
    budget it will not reach; returns it once its first checkpoint is on disk."""
    argv = [sys.executable, "-c", MAIN, "fit", str(data), "-o", str(out), "--method", "adam",
            "--steps", "100000", "--tol", "0", "--checkpoint-every", "50"]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)
    deadline = time.monotonic() + 240
    while not (out / "checkpoint.json").exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "no checkpoint"
        time.sleep(0.2)
    return proc


def interrupt(proc, signum):
    proc.send_signal(signum)
    stdout, stderr = proc.communicate(timeout=240)
    return proc.returncode, stdout, stderr


def assert_complete_interrupted_result(out, name):
    result = strict_json(out / "result.json")
    assert result["interrupted"] is True and result["signal"] == name
    assert result["status"] == "stopped" and result["n_steps"] >= 50
    assert set(result["values"]) == set(TRUTH)
    for value in result["values"].values():
        assert np.all(np.isfinite(value))
    assert (out / "material.mtl").read_text().count("newmtl") == 1
    assert {"view_000.png", "view_001.png", "loss.png", "checkpoint.json"} <= set(
        os.listdir(out))
    assert_no_temporaries(out)
    return result


def test_sigint_writes_a_complete_result(data_root, tmp_path, cli_env):
    out = tmp_path / "result"
    code, stdout, stderr = interrupt(start_fit(data_root / "noisy", out, cli_env),
                                     signal.SIGINT)
    assert code == 130, stderr
    assert "Traceback" not in stderr and "interrupted by SIGINT" in stderr
    result = assert_complete_interrupted_result(out, "SIGINT")
    assert f"after {result['n_steps']} steps" in stdout


def test_sigterm_then_resume_finishes(data_root, tmp_path, capsys, cli_env):
    out = tmp_path / "result"
    code, _, stderr = interrupt(start_fit(data_root / "noisy", out, cli_env), signal.SIGTERM)
    assert code == 143 and "Traceback" not in stderr
    first = assert_complete_interrupted_result(out, "SIGTERM")
    steps = first["n_steps"]
    assert strict_json(out / "checkpoint.json")["step"] == steps
    code, _, err = run_cli(["fit", data_root / "noisy", "-o", out, "--resume", "--steps",
                            steps + 25], capsys)
    assert (code, err) == (0, "")
    second = strict_json(out / "result.json")
    # the step budget ends the resumed run, unless the fit converges first (how far the
    # first run got before the signal depends on the machine's speed)
    assert second["interrupted"] is False and second["status"] in ("budget", "converged")
    n = second["n_steps"]
    assert (n == steps + 25) if second["status"] == "budget" else (steps < n <= steps + 25)
    assert len(second["loss_history"]) == n + 1
    np.testing.assert_array_equal(second["loss_history"][:steps + 1],
                                  first["loss_history"][:steps + 1])
    assert_no_temporaries(out)


# ---- one driver: the CLI runs fitting.fit's loop with the same options ----


def test_every_fit_option_is_a_flag():
    actions = {a.dest for a in cli.build_parser()._subparsers._group_actions[0]
               .choices["fit"]._actions}
    assert {f.name for f in dataclasses.fields(FitOptions)} <= actions


def test_cli_and_python_fit_are_the_same_fit(data_root, tmp_path, capsys):
    """The options given to `diffshade fit` reach the same driver as fitting.fit's
    keywords: the same values and loss history, step for step."""
    out = tmp_path / "result"
    argv = ["fit", data_root / "noisy", "-o", out, "--method", "adam", "--steps", "15",
            "--lr", "0.08", "--lr-shininess", "0.02", "--loss", "huber", "--edge-margin", "2"]
    assert run_cli(argv, capsys)[0] == 0
    got = strict_json(out / "result.json")
    want = fit(load_dataset(data_root / "noisy"), method="adam", steps=15, lr=0.08,
               lr_shininess=0.02, loss="huber", edge_margin=2, with_uncertainty=False)
    np.testing.assert_allclose(got["loss_history"], want.loss_history, rtol=1e-6)
    for name in TRUTH:
        np.testing.assert_allclose(got["values"][name], want.values[name], rtol=1e-6)


def test_cli_fits_light_colours(data_root, tmp_path, capsys):
    """From the true material and the dataset's own lights, a fit of the light colours
    stays at those lights (read back from the scene files)."""
    out = tmp_path / "result"
    argv = ["fit", data_root / "clean", "-o", out, "--fit", "light_colors", "--init",
            data_root / "clean" / "truth.json"]
    code, stdout, _ = run_cli(argv, capsys)
    assert code == 0
    result = strict_json(out / "result.json")
    assert result["fit"]["light_colors"] is True and set(result["values"]) == {"lights"}
    dataset = load_dataset(data_root / "clean")
    for view, fitted in zip(dataset.views, result["values"]["lights"], strict=True):
        for group, fields in fitted.items():
            np.testing.assert_allclose(fields["color"],
                                       np.asarray(getattr(view.lights, group).diffuse),
                                       rtol=1e-3)
    assert "lights[1]." in stdout


# ---- a fit that says when it is wrong ----


@pytest.fixture(scope="module")
def srgb_png_dataset(data_root, tmp_path_factory):
    """The clean dataset with only its 8-bit sRGB PNG targets (no .npy)."""
    folder = copy_dataset(data_root / "clean", tmp_path_factory.mktemp("png") / "data")
    for name in os.listdir(folder):
        if name.startswith("view_") and name.endswith(".npy"):
            os.remove(folder / name)
    return folder


def test_wrong_colour_encoding_is_flagged(srgb_png_dataset, tmp_path, capsys):
    """sRGB PNGs read as linear (the issue's walk-through): exit 0, but a warning on
    stderr naming the likely causes, ka at its upper bound without a standard error, and
    the misfit in result.json; read as sRGB, no warning."""
    out = tmp_path / "wrong"
    code, stdout, err = run_cli(["fit", srgb_png_dataset, "-o", out, "--color-space",
                                 "linear"], capsys)
    assert code == 0
    line = [x for x in err.splitlines() if x.startswith("diffshade: warning:")]
    assert len(line) == 1 and "does not explain the images" in line[0]
    for cause in ("mesh", "cameras", "lights", "colour encoding"):
        assert cause in line[0]
    result = strict_json(out / "result.json")
    assert result["misfit"]["explained"] is False and result["misfit"]["ratio"] > 3
    bounded = result["at_bound"]
    assert bounded and all(result["std_errors"][n] is None for n in bounded)
    assert all(result["std_errors"][n] is not None for n in result["std_errors"]
               if n not in bounded)
    for name in bounded:
        channel = "rgb".index(name[3]) if "[" in name else 0
        value = np.atleast_1d(result["values"][name[:2]])[channel]
        assert value < 1e-3 or value > 1 - 1e-3
        row = next(x for x in stdout.splitlines() if x.startswith(name + " "))
        assert "at bound" in row
    code, _, err = run_cli(["fit", srgb_png_dataset, "-o", tmp_path / "right"], capsys)
    assert (code, err) == (0, "")
    assert strict_json(tmp_path / "right" / "result.json")["misfit"]["explained"] is True


def test_residual_files(data_root, tmp_path, capsys):
    """residual_*.npy is render(fitted material) - target in linear float32; residual_*.png
    is |that| / residual_scale, clipped, sRGB-encoded, on the pixels mask_*.png says the
    fit counted (the covered ones, one pixel in from the silhouette: edge_margin 1)."""
    out = tmp_path / "result"
    assert run_cli(["fit", data_root / "noisy", "-o", out], capsys)[0] == 0
    result = strict_json(out / "result.json")
    dataset = load_dataset(data_root / "noisy")
    fitted = ds.material(**{k: result["material"][k] for k in ("ka", "kd", "ks",
                                                              "shininess")})
    scale = result["residual_scale"]
    assert scale >= 1 / 255
    # the right model on noise 0.01: the residual is that noise, and the check says so
    misfit = result["misfit"]
    assert misfit["explained"] and misfit["ratio"] < 1.5
    assert misfit["noise"] == pytest.approx(0.01, rel=0.05)
    for i, view in enumerate(dataset.views):
        scene = ds.make_scene(dataset.mesh, view.camera, view.lights, fitted,
                              model=dataset.model, global_ambient=dataset.global_ambient)
        expected = np.asarray(ds.render(scene, dataset.settings))[..., :3] - view.target
        got = np.load(out / f"residual_{i:03d}.npy")
        assert got.dtype == np.float32 and got.shape == (SIZE, SIZE, 3)
        np.testing.assert_allclose(got, expected, atol=2e-5)
        assert image_transfer(out / f"residual_{i:03d}.png") == "srgb"
        covered = np.asarray(ds.render(scene, dataset.settings))[..., 3] > 0.5
        inside = covered.copy()  # eroded by one 4-neighbour step
        inside[1:] &= covered[:-1]
        inside[:-1] &= covered[1:]
        inside[:, 1:] &= covered[:, :-1]
        inside[:, :-1] &= covered[:, 1:]
        counted = ds.read_image(out / f"mask_{i:03d}.png", color_space="linear").reshape(
            SIZE, SIZE, -1)[..., 0] > 0.5
        np.testing.assert_array_equal(counted, inside)
        png = ds.read_image(out / f"residual_{i:03d}.png")
        np.testing.assert_allclose(png, np.clip(np.abs(expected) / scale, 0, 1)
                                   * counted[..., None], atol=0.02)


def test_progress_estimate_leaves_out_the_compiling_step():
    """The first step takes 1 s (compilation), the next ones 20 ms: the remaining time
    shown comes from the 20 ms steps."""
    class State:
        step, method, history, spec = 0, "adam", [0.1], FitSpec()
        params = {"ka": jnp.zeros(3), "kd": jnp.zeros(3), "ks": jnp.zeros(3),
                  "shininess": jnp.asarray(3.0)}
    state = State()
    bar, on_step = _progress(state, 1000, disable=False, file=io.StringIO())
    with bar:
        for pause in (1.0, *[0.02] * 8):
            time.sleep(pause)
            state.step += 1
            on_step(state)
        info = bar.format_dict
    rate = info["rate"] or (info["n"] - info["initial"]) / info["elapsed"]
    remaining = (info["total"] - info["n"]) / rate
    assert info["n"] == 9 and remaining < 0.02 * 991 * 2.5, remaining

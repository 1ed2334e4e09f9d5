"""`diffshade synth`, `fit` and `render` on scenes of several objects (issue 14, item 1).

References: the materials written in the scene file (the truth a fit must recover), the
world-space bounds the synth layout promises (unit bounding sphere), the API's render of
the same objects, an uninterrupted run for a resumed one, and the .mtl and result.json
text parsed back. Tiny scenes (32 px, a subdivision-1 sphere on a box) keep it fast.
"""

import json
import os

import numpy as np
import pytest

import diffshade as ds
from diffshade import cli
from diffshade.scene.transform import transform_points
from fitting.data.folder import load_dataset

SIZE = 32
TRUTH = {"table": {"ka": [0.1, 0.15, 0.2], "kd": [0.2, 0.35, 0.7], "ks": [0.3, 0.3, 0.35],
                   "shininess": 12.0},
         "ball": {"ka": [0.25, 0.2, 0.15], "kd": [0.6, 0.3, 0.2], "ks": [0.5, 0.45, 0.4],
                  "shininess": 30.0}}


def scene_dict(named=True):
    objects = [{"mesh": {"builtin": {"box": {"size": [2.0, 0.2, 1.6]}}},
                "transform": {"translate": [0, -0.1, 0]}, "material": TRUTH["table"]},
               {"mesh": {"builtin": {"icosphere": {"subdivisions": 1, "radius": 0.5}}},
                "transform": {"translate": [0, 0.5, 0]}, "material": TRUTH["ball"]}]
    if named:
        objects = [{"name": name, **o} for name, o in zip(TRUTH, objects, strict=True)]
    return {"objects": objects, "global_ambient": 0.3,
            "camera": {"eye": [0, 1.5, 2.5], "target": [0, 0.2, 0], "width": SIZE,
                       "height": SIZE},
            "lights": [{"type": "directional", "direction": [-0.4, -1, -0.6]}]}


def write_json(path, data):
    path.write_text(json.dumps(data))
    return str(path)


def run(argv, capsys):
    """(exit status, stdout, stderr) of diffshade.cli.main(argv)."""
    status = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return status, out, err


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    return tmp_path_factory.mktemp("objects")


@pytest.fixture(scope="module")
def dataset_dir(root):
    """`diffshade synth --scene` of the named two-object scene: 2 cameras x 2 lights."""
    scene = write_json(root / "scene.json", scene_dict())
    assert cli.main(["synth", "--scene", scene, "--views", "2", "--lights", "2", "--size",
                     str(SIZE), "-o", str(root / "data")]) == 0
    return root / "data"


@pytest.fixture(scope="module")
def fitted_dir(dataset_dir, root):
    assert cli.main(["fit", str(dataset_dir), "-o", str(root / "fit"), "--quiet"]) == 0
    return root / "fit"


def test_synth_writes_each_objects_material_and_the_layout(dataset_dir):
    dataset = load_dataset(dataset_dir)
    assert dataset.objects.names == ("table", "ball") and len(dataset.views) == 4
    for i, name in enumerate(TRUTH):
        for key, value in TRUTH[name].items():
            np.testing.assert_allclose(np.asarray(getattr(dataset.truth, key))[i], value,
                                       rtol=1e-6, err_msg=f"{name}.{key}")
    # the layout normalizes the scene: bounding-box centre at 0, bounding sphere radius 1
    world = np.asarray(transform_points(dataset.model, dataset.mesh.vertices), np.float64)
    np.testing.assert_allclose((world.min(0) + world.max(0)) / 2, 0.0, atol=1e-5)
    assert np.linalg.norm(world, axis=1).max() == pytest.approx(1.0, abs=1e-5)
    truth = json.loads((dataset_dir / "truth.json").read_text())
    assert list(truth["objects"]) == ["table", "ball"]
    assert all(np.any(v.target > 0.05) for v in dataset.views)


def test_render_of_a_dataset_view_file_is_its_target(dataset_dir, tmp_path, capsys):
    status, _, _ = run(["render", dataset_dir / "view_003.json", "-o", tmp_path / "r.npy"],
                       capsys)
    assert status == 0
    target = np.load(dataset_dir / "view_003.npy")
    np.testing.assert_allclose(np.load(tmp_path / "r.npy")[..., :3], target, atol=1e-6)


def test_render_of_an_objects_scene_file_is_the_api_render(root, tmp_path, capsys):
    path = write_json(root / "render.json", scene_dict())
    status, out, err = run(["render", path, "-o", tmp_path / "r.npy"], capsys)
    assert status == 0 and err == ""
    objects = [ds.scene_object(ds.box((2.0, 0.2, 1.6)), ds.material(**TRUTH["table"]),
                               transform=ds.model_matrix((0.0, -0.1, 0.0))),
               ds.scene_object(ds.icosphere(1, 0.5), ds.material(**TRUTH["ball"]),
                               transform=ds.model_matrix((0.0, 0.5, 0.0)))]
    scene = ds.make_scene(objects=objects, global_ambient=0.3,
                          camera=ds.look_at((0, 1.5, 2.5), (0, 0.2, 0), width=SIZE,
                                            height=SIZE),
                          lights=[ds.directional_light((-0.4, -1, -0.6))])
    np.testing.assert_allclose(np.load(tmp_path / "r.npy"), np.asarray(ds.render(scene)),
                               atol=1e-6)


def test_fit_recovers_every_objects_material_with_a_report_each(fitted_dir, capsys):
    result = json.loads((fitted_dir / "result.json").read_text())
    assert [o["name"] for o in result["objects"]] == ["table", "ball"]
    for report in result["objects"]:
        for key, value in TRUTH[report["name"]].items():
            np.testing.assert_allclose(report["material"][key], value, rtol=1e-3,
                                       err_msg=f"{report['name']}.{key}")
        assert sorted(report["std_errors"]) == sorted(
            [f"{k}[{c}]" for k in ("ka", "kd", "ks") for c in "rgb"] + ["shininess"])
        assert all(np.isfinite(s) and s > 0 for s in report["std_errors"].values())
    assert list(result["material"]["objects"]) == ["table", "ball"]
    # one newmtl per object, named after it, with its recovered Kd and Ns
    entries = (fitted_dir / "material.mtl").read_text().split("newmtl ")[1:]
    assert [e.split("\n")[0] for e in entries] == ["table", "ball"]
    for entry, name in zip(entries, TRUTH, strict=True):
        lines = {line.split()[0]: [float(x) for x in line.split()[1:]]
                 for line in entry.strip().split("\n")[1:]}
        np.testing.assert_allclose(lines["Kd"], TRUTH[name]["kd"], atol=1e-3)
        assert lines["Ns"][0] == pytest.approx(TRUTH[name]["shininess"], rel=1e-3)


def test_fit_table_has_each_objects_rows(dataset_dir, tmp_path, capsys):
    status, out, _ = run(["fit", dataset_dir, "-o", tmp_path / "fit", "--quiet"], capsys)
    assert status == 0
    rows = {line.split()[0]: [float(x) for x in line.split()[1:3]]
            for line in out.splitlines() if line.startswith(("table.", "ball."))}
    assert len(rows) == 2 * 10
    for name, material in TRUTH.items():
        true, fitted = rows[f"{name}.kd[b]"]
        assert true == pytest.approx(material["kd"][2], rel=1e-6)
        assert fitted == pytest.approx(material["kd"][2], rel=1e-3)


def test_resumed_fit_continues_as_one_run(dataset_dir, tmp_path, capsys):
    whole, part = tmp_path / "whole", tmp_path / "part"
    base = ["fit", dataset_dir, "--quiet", "--method", "adam"]
    assert run([*base, "-o", whole, "--steps", "6"], capsys)[0] == 0
    assert run([*base, "-o", part, "--steps", "3"], capsys)[0] == 0
    assert run(["fit", dataset_dir, "--quiet", "--resume", "-o", part, "--steps", "6"],
               capsys)[0] == 0
    one, resumed = (json.loads((p / "result.json").read_text()) for p in (whole, part))
    assert resumed["n_steps"] == 6
    np.testing.assert_allclose(resumed["loss_history"], one["loss_history"], rtol=1e-5)
    for a, b in zip(resumed["objects"], one["objects"], strict=True):
        np.testing.assert_allclose(a["material"]["kd"], b["material"]["kd"], rtol=1e-5)


def test_unnamed_objects_fit_with_indexed_names(root, tmp_path, capsys):
    scene = write_json(root / "unnamed.json", scene_dict(named=False))
    data = tmp_path / "data"
    assert run(["synth", "--scene", scene, "--views", "1", "--lights", "2", "--size",
                SIZE, "-o", data], capsys)[0] == 0
    assert isinstance(json.loads((data / "truth.json").read_text())["objects"], list)
    status, out, _ = run(["fit", data, "-o", tmp_path / "fit", "--quiet"], capsys)
    assert status == 0 and "objects[1].kd[r]" in out
    mtl = (tmp_path / "fit" / "material.mtl").read_text()
    assert "newmtl diffshade_fit_0" in mtl and "newmtl diffshade_fit_1" in mtl


def _init_file(tmp_path, objects, name):
    return write_json(tmp_path / name, {"objects": objects})


def _bad_cases(tmp_path, dataset_dir):
    """(argv, the start of the message) of inputs that must be refused."""
    out = tmp_path / "out"
    one = {"ka": 0.3, "kd": 0.5, "ks": 0.3, "shininess": 20}
    both_mesh = scene_dict() | {"mesh": {"builtin": {"icosphere": {}}}}
    missing = scene_dict()
    missing["objects"][1]["mesh"] = {"path": "no_such_mesh.obj"}
    twice = scene_dict()
    twice["objects"][1]["name"] = "table"
    return [
        (["fit", dataset_dir, "-o", out, "--init",
          _init_file(tmp_path, {"table": one, "cup": one}, "cup.json")],
         "--init: objects: 'cup': unknown object name; expected names among 'table', 'ball'"),
        (["fit", dataset_dir, "-o", out, "--init",
          _init_file(tmp_path, {"table": one}, "table.json")],
         "--init: objects: no material for 'ball'"),
        (["fit", dataset_dir, "-o", out, "--init",
          _init_file(tmp_path, [one] * 3, "three.json")],
         "--init: got materials for 3 objects; expected one material, or 2"),
        (["synth", "--scene", write_json(tmp_path / "both.json", both_mesh), "-o", out],
         "mesh: not allowed with objects"),
        (["synth", "--scene", write_json(tmp_path / "missing.json", missing), "-o", out],
         "objects[1].mesh.path: mesh file 'no_such_mesh.obj' not found"),
        (["render", write_json(tmp_path / "missing.json", missing), "-o", tmp_path / "o.png"],
         "objects[1].mesh.path: mesh file 'no_such_mesh.obj' not found"),
        (["synth", "--scene", write_json(tmp_path / "twice.json", twice), "-o", out],
         "objects[1].name: got 'table' again"),
        (["synth", "--scene", write_json(tmp_path / "ok.json", scene_dict()), "--material",
          "0.3,0.5,0.3,20", "-o", out], "--material: got '0.3,0.5,0.3,20' with --scene"),
    ]


def test_bad_object_input_is_one_line_exit_2_and_writes_nothing(dataset_dir, tmp_path,
                                                                capsys):
    for argv, message in _bad_cases(tmp_path, dataset_dir):
        before = set(os.listdir(tmp_path))
        status, out, err = run(argv, capsys)
        assert status == 2, (argv, err)
        assert err.count("\n") == 1 and err.startswith("diffshade: error: "), err
        assert message in err, (message, err)
        assert set(os.listdir(tmp_path)) == before, argv  # nothing written


def test_dataset_truth_and_views_must_agree_on_the_objects(dataset_dir, tmp_path, capsys):
    def copy(name):
        folder = tmp_path / name
        folder.mkdir()
        for f in os.listdir(dataset_dir):
            (folder / f).write_bytes((dataset_dir / f).read_bytes())
        return folder
    unknown = copy("unknown")
    truth = json.loads((unknown / "truth.json").read_text())
    truth["objects"]["cup"] = truth["objects"].pop("ball")
    write_json(unknown / "truth.json", truth)
    renamed = copy("renamed")
    view = json.loads((renamed / "view_002.json").read_text())
    view["objects"][1]["name"] = "sphere"
    write_json(renamed / "view_002.json", view)
    for folder, message in ((unknown, "truth.json: objects: 'cup': unknown object name"),
                            (renamed, "views[2] (view_002.json): its objects differ")):
        status, _, err = run(["fit", folder, "-o", tmp_path / "out"], capsys)
        assert status == 2 and message in err, err
        assert not (tmp_path / "out").exists()


def test_synth_scene_of_one_mesh_makes_a_one_object_dataset(root, tmp_path, capsys):
    one = {"mesh": {"builtin": {"icosphere": {"subdivisions": 1}}},
           "material": TRUTH["ball"], "global_ambient": 0.3,
           "camera": {"eye": [0, 0, 3], "target": [0, 0, 0], "width": SIZE, "height": SIZE}}
    scene = write_json(root / "one.json", one)
    assert run(["synth", "--scene", scene, "--views", "1", "--lights", "1", "--size", SIZE,
                "-o", tmp_path / "data"], capsys)[0] == 0
    dataset = load_dataset(tmp_path / "data")
    assert dataset.objects is None and len(dataset.views) == 1
    np.testing.assert_allclose(dataset.truth.kd, TRUTH["ball"]["kd"], rtol=1e-6)
    np.testing.assert_allclose(dataset.global_ambient, 0.3, rtol=1e-6)


def test_init_from_a_result_json_starts_every_object_there(dataset_dir, fitted_dir, tmp_path,
                                                           capsys):
    status, _, err = run(["fit", dataset_dir, "-o", tmp_path / "again", "--quiet", "--method",
                          "adam", "--steps", "1", "--init", fitted_dir / "result.json"], capsys)
    assert status == 0, err
    before = json.loads((fitted_dir / "result.json").read_text())["material"]
    after = json.loads((tmp_path / "again" / "result.json").read_text())["initial"]
    assert list(after["objects"]) == ["table", "ball"]
    for name in TRUTH:
        np.testing.assert_allclose(after["objects"][name]["kd"], before["objects"][name]["kd"],
                                   rtol=1e-6)

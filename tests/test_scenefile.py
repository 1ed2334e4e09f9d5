"""Tests for diffshade.io.scenefile. References: the same scene built directly through the
public API (an independent construction path), closed-form normals of a regular
tetrahedron, and hand-written error messages naming each key path."""

import copy
import dataclasses
import json
from pathlib import Path

import jax
import numpy as np
import pytest

import diffshade as ds
from diffshade.io.scenefile import (
    SceneFileError,
    load_scene,
    load_scenes,
    save_scene,
    scene_from_dict,
    scene_to_dict,
    scenes_from_dict,
)
from diffshade.scene.builtin import builtin_scene

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def assert_same_tree(got, want, rtol=0.0):
    """Same pytree structure (static fields included) and the same leaf values."""
    assert jax.tree.structure(got) == jax.tree.structure(want)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, rtol=rtol, atol=rtol), got, want)


# A scene using every part of the format, written as JSON and, below, through the API.
FULL = {
    "version": 1,
    "mesh": {"builtin": {"icosphere": {"subdivisions": 1, "radius": 0.9}}},
    "transform": {"translate": [0.1, -0.2, 0], "rotate_deg": [10, 20, 30], "scale": [1, 1.2, 0.8]},
    "camera": {"eye": [0.5, 0.4, 3.0], "target": [0, 0, 0], "up": [0, 1, 0], "fov_y": 50,
               "near": 0.5, "far": 20, "width": 24, "height": 16},
    "lights": [
        {"type": "ambient", "color": [0.1, 0.05, 0.0]},
        {"type": "directional", "direction": [1, -1, -1], "color": 0.7, "ambient": 0.1},
        {"type": "point", "position": [2, 1, 2], "diffuse": [0.5, 0.4, 0.3], "specular": 0.9,
         "attenuation": [1, 0.1, 0.02]},
        {"type": "spot", "position": [0, 0, 3], "direction": [0, 0, -1], "color": 0.8,
         "cutoff": 20, "exponent": 4},
    ],
    "material": {"ka": 0.3, "kd": [0.6, 0.2, 0.1], "ks": 0.5, "shininess": 30,
                 "emission": [0.05, 0.0, 0.1]},
    "back_material": {"ka": 0.1, "kd": [0.1, 0.5, 0.1], "ks": 0.2, "shininess": 5,
                      "emission": 0},
    "global_ambient": [0.2, 0.25, 0.3],
    "background": [0.0, 0.1, 0.2],
    "local_viewer": True,
    "two_sided": True,
    "settings": {"shading": "gouraud", "specular": "phong", "spot_edge": "smooth",
                 "spot_softness": 3},
}


def full_scene_by_api():
    lights = [
        ds.ambient_light((0.1, 0.05, 0.0)),
        ds.directional_light((1, -1, -1), 0.7, ambient=0.1),
        ds.point_light((2, 1, 2), diffuse=(0.5, 0.4, 0.3), specular=0.9,
                       attenuation=(1, 0.1, 0.02)),
        ds.spot_light((0, 0, 3), (0, 0, -1), 0.8, cutoff=20, exponent=4),
    ]
    camera = ds.look_at((0.5, 0.4, 3.0), (0, 0, 0), (0, 1, 0), fov_y=50, near=0.5, far=20,
                        width=24, height=16)
    scene = ds.make_scene(
        ds.icosphere(1, 0.9), camera, lights,
        ds.material(ka=0.3, kd=(0.6, 0.2, 0.1), ks=0.5, shininess=30, emission=(0.05, 0, 0.1)),
        model=ds.model_matrix((0.1, -0.2, 0.0), (10, 20, 30), (1, 1.2, 0.8)),
        global_ambient=(0.2, 0.25, 0.3), background=(0.0, 0.1, 0.2),
        back_material=ds.material(ka=0.1, kd=(0.1, 0.5, 0.1), ks=0.2, shininess=5, emission=0),
        local_viewer=True,
        two_sided=True)
    settings = ds.RenderSettings(shading="gouraud", specular="phong", spot_edge="smooth",
                                 spot_softness=3.0)
    return scene, settings


def test_scene_dict_builds_the_api_scene():
    scene, settings = scene_from_dict(copy.deepcopy(FULL))
    want_scene, want_settings = full_scene_by_api()
    assert_same_tree(scene, want_scene)
    assert settings == want_settings


def test_round_trip_through_json_renders_the_same_image():
    scene, settings = full_scene_by_api()
    text = json.dumps(scene_to_dict(scene, settings))
    back, back_settings = scene_from_dict(json.loads(text))
    assert back_settings == settings
    # Inline normals are renormalized on reading: equal to float32 rounding.
    assert_same_tree(back, scene, rtol=1e-6)
    image = np.asarray(ds.render(scene, settings))
    assert 0.1 < image[..., 3].mean() < 0.9  # the sphere and the background both show
    np.testing.assert_allclose(ds.render(back, settings), image, atol=1e-6)


def test_round_trip_with_a_mesh_reference_through_a_file(tmp_path):
    scene = ds.make_scene(ds.torus(1.0, 0.3, 12, 6), ds.look_at(
        (0, 2, 2), (0, 0, 0), width=8, height=6, projection="orthographic", ortho_height=3.0))
    ref = {"builtin": {"torus": {"minor_radius": 0.3, "major_segments": 12,
                                 "minor_segments": 6}}}
    path = save_scene(tmp_path / "torus.json", scene, ds.RenderSettings(), mesh_ref=ref)
    back, settings = load_scene(path)
    assert_same_tree(back, scene)
    assert settings == ds.RenderSettings()
    assert json.loads(Path(path).read_text())["mesh"] == ref


def test_example_sphere_is_the_builtin_sphere():
    scene, settings = load_scene(EXAMPLES / "sphere.json")
    assert_same_tree(scene, builtin_scene("sphere"))
    assert settings == ds.RenderSettings()


def test_example_spot_torus_matches_the_api():
    scene, settings = load_scene(EXAMPLES / "spot_torus.json")
    lights = [
        ds.spot_light((0, 3, 2), (0.7, -3.1, -1.3), (1, 0.9, 0.7), cutoff=12, exponent=5,
                      attenuation=(1, 0, 0.01)),
        ds.spot_light((-3, 0.5, 2), (2, -0.7, -1.7), (0.3, 0.4, 0.9), cutoff=10, exponent=2),
        ds.ambient_light(0.1),
    ]
    want = ds.make_scene(
        ds.torus(1.0, 0.35, 48, 24),
        ds.look_at((0, 1.2, 4), (0, 0, 0), fov_y=40, width=256, height=192), lights,
        ds.material(ka=0.3, kd=(0.2, 0.6, 0.35), ks=0.7, shininess=80),
        model=ds.model_matrix((0, -0.2, 0), (30, 0, 0)), global_ambient=0.05,
        background=0.02, local_viewer=True)
    assert_same_tree(scene, want)
    assert settings == ds.RenderSettings(spot_edge="smooth", spot_softness=3.0)


# A regular tetrahedron centred at the origin: every vertex normal, whatever the
# weighting, is the unit vector to the vertex.
TETRA_VERTICES = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], np.float64)
TETRA_OBJ = """v 1 1 1
v 1 -1 -1
v -1 1 -1
v -1 -1 1
f 1 2 3
f 1 4 2
f 1 3 4
f 2 4 3
"""


def scene_file(folder, mesh):
    """Write a minimal scene file with the given mesh object into folder."""
    folder.mkdir(parents=True, exist_ok=True)
    data = {"mesh": mesh, "camera": {"eye": [0, 0, 4], "target": [0, 0, 0], "width": 8,
                                     "height": 8}}
    path = folder / "scene.json"
    path.write_text(json.dumps(data))
    return path


@pytest.mark.parametrize("weighting", ["angle", "area", "uniform"])
def test_mesh_path_is_relative_to_the_scene_file(tmp_path, monkeypatch, weighting):
    (tmp_path / "scenes" / "meshes").mkdir(parents=True)
    (tmp_path / "scenes" / "meshes" / "tetra.obj").write_text(TETRA_OBJ)
    path = scene_file(tmp_path / "scenes", {"path": "meshes/tetra.obj",
                                            "normals": {"weighting": weighting}})
    monkeypatch.chdir(tmp_path)
    scene, _ = load_scene(path)
    vertices, normals = np.asarray(scene.mesh.vertices), np.asarray(scene.mesh.normals)
    order = np.lexsort(vertices.T)
    np.testing.assert_allclose(vertices[order], TETRA_VERTICES[np.lexsort(TETRA_VERTICES.T)])
    np.testing.assert_allclose(normals, vertices / np.sqrt(3.0), atol=1e-6)
    assert scene.mesh.faces.shape == (4, 3)


def test_missing_mesh_file_is_looked_for_beside_the_scene_file(tmp_path, monkeypatch):
    # The mesh exists relative to the working directory, but not beside the scene file.
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "tetra.obj").write_text(TETRA_OBJ)
    path = scene_file(tmp_path / "scenes", {"path": "meshes/tetra.obj"})
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SceneFileError) as err:
        load_scene(path)
    message = str(err.value)
    assert message.startswith(f"{path}: mesh.path: mesh file 'meshes/tetra.obj' not found")
    assert str(tmp_path / "scenes" / "meshes" / "tetra.obj") in message


def test_inline_mesh_with_normals_and_crease_options():
    faces = [[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]]
    data = {"camera": {"eye": [0, 0, 4], "target": [0, 0, 0], "width": 8, "height": 8}}
    data["mesh"] = {"vertices": TETRA_VERTICES.tolist(), "faces": faces,
                    "normals": (2 * TETRA_VERTICES).tolist()}
    scene, _ = scene_from_dict(data)
    np.testing.assert_allclose(scene.mesh.normals, TETRA_VERTICES / np.sqrt(3.0), rtol=1e-6)
    # Every tetrahedron edge is a 109.5 degree crease: 30 degrees splits all 4 x 3 corners.
    data["mesh"]["normals"] = {"crease_angle": 30}
    scene, _ = scene_from_dict(data)
    assert scene.mesh.vertices.shape == (12, 3)


BASE = {
    "mesh": {"builtin": {"icosphere": {"subdivisions": 0}}},
    "camera": {"eye": [0, 0, 3], "target": [0, 0, 0], "width": 16, "height": 16},
    "lights": [{"type": "directional", "direction": [0, 0, -1]},
               {"type": "spot", "position": [0, 0, 3], "direction": [0, 0, -1], "cutoff": 30}],
}
DELETE = object()


def edited(keys, value, base=None):
    """A deep copy of `base` (default BASE) with base[keys[0]][keys[1]]... set to value
    (or deleted)."""
    data = copy.deepcopy(BASE if base is None else base)
    parent = data
    for key in keys[:-1]:
        parent = parent[key]
    if value is DELETE:
        del parent[keys[-1]]
    else:
        parent[keys[-1]] = value
    return data


@pytest.mark.parametrize("keys, value, message", [
    (("camera", "width"), DELETE, "camera.width: missing; expected a positive integer"),
    (("camera", "width"), 0, "camera.width: got 0; expected a positive integer"),
    (("camera", "width"), 10**30, "camera.width: got 1000000000000000000000000000000; "
                                  "expected a positive integer of pixels, at most 16384"),
    (("camera",), DELETE, 'camera: missing; expected an object (or "cameras": an array'),
    (("cameras",), [], 'camera, cameras: got both; expected exactly one of "camera"'),
    (("camera", "fov_y"), "45", 'camera.fov_y: got "45"; expected a number'),
    (("camera", "eye"), [0, 3], "camera.eye: got [0, 3]; expected 3 numbers"),
    (("camera", "target"), [0, 0, 3], "camera.eye, camera.target: both are [0.0, 0.0, 3.0]"),
    (("camera", "near"), 200, "camera.near, camera.far: got near=200, far=100.0"),
    (("camera", "projection"), "fisheye", 'camera.projection: got "fisheye"; expected one of'),
    (("camera", "colour"), 1, "camera.colour: unknown key; expected one of: eye, far, fov_y"),
    (("lights", 1, "colour"), 1, 'lights[1].colour: unknown key; did you mean "color"?'),
    (("lights", 0, "cutoff"), 10, "lights[0].cutoff: unknown key"),
    (("lights", 0, "type"), "panel",
     'lights[0].type: got "panel"; expected one of "ambient", "directional", "point", "spot", '
     '"area", "sphere"'),
    (("lights", 0, "type"), DELETE, "lights[0].type: missing; expected one of"),
    (("lights", 1, "cutoff"), 120,
     "lights[1].cutoff: got 120; expected degrees in [0, 90], or 180"),
    (("lights", 1, "direction"), DELETE, "lights[1].direction: missing; expected 3 numbers"),
    (("lights", 1, "direction"), [0, 0, 0], "lights[1].direction: got [0, 0, 0]; expected a"),
    (("lights", 1, "attenuation"), [0, 0, 0], "lights[1].attenuation: got [0, 0, 0]"),
    (("lights", 0, "color"), [1, 1], "lights[0].color: got [1, 1]; expected a number (grey)"),
    (("lights",), {"type": "point"}, 'lights: got {"type": "point"}; expected an array'),
    (("material",), {"kd": -1}, "material.kd: got -1; expected a non-negative"),
    (("material",), {"shininess": True}, "material.shininess: got true; expected a number"),
    (("back_material",), {"ks": "shiny"}, 'back_material.ks: got "shiny"; expected null or'),
    (("settings",), {"shading": "toon"}, "settings.shading: got 'toon'; expected one of"),
    (("settings",), {"faces_per_pixel": 2.5},
     "settings.faces_per_pixel: got 2.5; expected an integer"),
    (("settings",), {"clamp": 1}, "settings.clamp: got 1; expected true or false"),
    (("settings",), {"shadng": "flat"}, 'settings.shadng: unknown key; did you mean "shading"?'),
    (("transform",), {"matrix": np.eye(4).tolist(), "translate": [1, 0, 0]},
     "transform: got matrix and translate; expected matrix alone"),
    (("transform",), {"matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]},
     "transform.matrix: got [[1, 0, 0], [0, 1, 0], [0, 0, 1]]; expected a 4x4 matrix"),
    (("transform",), {"scale": 0}, "transform: the upper 3x3 block is singular"),
    (("mesh",), {"path": "a.obj", "builtin": {"box": {}}},
     'mesh: got keys "path", "builtin"; expected exactly one of "path", "builtin", "vertices"'),
    (("mesh",), {}, "mesh: got none of them; expected exactly one of"),
    (("mesh",), {"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "faces": [[0, 1, 3]]},
     "mesh.faces: index 3 out of range for 3 vertices"),
    (("mesh",), {"vertices": [[0, 0, 0], [1, 0], [0, 1, 0]], "faces": [[0, 1, 2]]},
     "mesh.vertices[1]: got [1, 0]; expected 3 numbers"),
    (("mesh",), {"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]]},
     "mesh.faces: missing; expected mesh.vertices"),
    (("mesh",), {"builtin": {"box": {}}, "faces": [[0, 1, 2]]},
     "mesh.faces: only allowed with mesh.vertices"),
    (("mesh",), {"builtin": {"icosphere": {"subdivisions": 9}}},
     "mesh.builtin.icosphere.subdivisions: 9; expected an int in [0, 8]"),
    (("mesh",), {"builtin": {"cone": {}}},
     "mesh.builtin.cone: unknown key; expected one of: box, icosphere, torus"),
    (("mesh",), {"builtin": {}}, 'mesh.builtin: got none of them; expected exactly one of'),
    (("mesh", "normals"), {"crease_angle": 200}, "mesh.normals.crease_angle: 200; expected"),
    (("mesh", "normals"), {"weighting": "max"},
     'mesh.normals.weighting: got "max"; expected one of "angle", "area", "uniform"'),
    (("version",), 2, "version: got 2; expected 1"),
    (("global_ambient",), [1, 2], "global_ambient: got [1, 2]; expected a number (grey)"),
    (("background",), -1, "background: got -1; expected a non-negative number"),
    (("two_sided",), "yes", 'two_sided: got "yes"; expected true or false'),
    (("materail",), {}, 'materail: unknown key; did you mean "material"? expected one of: '
                        "back_material, background, camera"),
])
def test_errors_name_the_key_path(keys, value, message):
    with pytest.raises(SceneFileError) as err:
        scene_from_dict(edited(keys, value))
    assert str(err.value).startswith(message), str(err.value)


def test_the_base_of_the_error_cases_is_valid():
    scene, _ = scene_from_dict(copy.deepcopy(BASE))
    assert scene.lights.spot.cutoff.tolist() == [30.0]


@pytest.mark.parametrize("data", [[1, 2], "scene", None])
def test_top_level_must_be_an_object(data):
    with pytest.raises(SceneFileError, match=r"^top level: got .*; expected an object"):
        scene_from_dict(data)


def test_unknown_settings_key_lists_every_render_setting():
    with pytest.raises(SceneFileError) as err:
        scene_from_dict({**BASE, "settings": {"speed": 1}})
    for field in dataclasses.fields(ds.RenderSettings):
        assert field.name in str(err.value)


def test_scene_file_errors_start_with_the_file_name(tmp_path):
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(edited(("lights", 1, "cutoff"), 120)))
    with pytest.raises(SceneFileError) as err:
        load_scene(path)
    assert str(err.value) == (f"{path}: lights[1].cutoff: got 120; expected degrees in "
                              "[0, 90], or 180 (no cone)")
    assert isinstance(err.value, ValueError)


def test_invalid_json_names_line_and_column(tmp_path):
    path = tmp_path / "scene.json"
    path.write_text('{\n  "mesh": {"builtin": {"box": {}}}\n  "camera": {}\n}\n')
    with pytest.raises(SceneFileError, match=r"scene\.json: line 3, column 3: invalid JSON"):
        load_scene(path)


def test_duplicate_keys_are_errors(tmp_path):
    path = tmp_path / "scene.json"
    path.write_text('{"mesh": {}, "camera": {}, "mesh": {}}')
    with pytest.raises(SceneFileError, match='scene.json: key "mesh" appears 2 times'):
        load_scene(path)


def test_missing_scene_file_names_the_path(tmp_path):
    path = tmp_path / "nowhere" / "scene.json"
    with pytest.raises(FileNotFoundError, match=str(path)):
        load_scene(path)


def test_the_documented_example_is_valid():
    text = (EXAMPLES.parent / "docs" / "scene-format.md").read_text()
    example = text.split("## Example", 1)[1].split("```json\n", 1)[1].split("```", 1)[0]
    scene, settings = scene_from_dict(json.loads(example))
    assert scene.lights.spot.cutoff.tolist() == [15.0]
    assert settings.spot_edge == "smooth"


# ---- several cameras ----


def test_several_cameras_give_one_scene_each(tmp_path):
    """"cameras": one scene per camera, each the API scene with that camera."""
    second = {**FULL["camera"], "eye": [2, 1, 2], "width": 10, "height": 8}
    data = {k: v for k, v in copy.deepcopy(FULL).items() if k != "camera"}
    data["cameras"] = [FULL["camera"], second]
    want, want_settings = full_scene_by_api()
    want_second = ds.replace(want, camera=ds.look_at((2, 1, 2), (0, 0, 0), (0, 1, 0), fov_y=50,
                                                     near=0.5, far=20, width=10, height=8))
    path = tmp_path / "shots.json"
    path.write_text(json.dumps(data))
    for scenes, settings in (scenes_from_dict(data), load_scenes(path)):
        assert len(scenes) == 2 and settings == want_settings
        assert_same_tree(scenes[0], want)
        assert_same_tree(scenes[1], want_second)
    with pytest.raises(SceneFileError, match="shots.json: cameras: got 2 cameras; expected "
                                             "one here"):
        load_scene(path)
    path.write_text(json.dumps({**data, "cameras": [FULL["camera"], {**second, "width": 10**30}]}))
    with pytest.raises(SceneFileError, match=r"cameras\[1\].width: got 1000000000000000000000000"
                                             r"000000; expected a positive integer of pixels"):
        load_scenes(path)
    with pytest.raises(SceneFileError, match="cameras: got \\[\\]; expected at least one"):
        scenes_from_dict({**data, "cameras": []})
    # one camera given as a one-element list is a single-camera file
    assert_same_tree(scene_from_dict({**data, "cameras": [FULL["camera"]]})[0], want)


def test_json_nested_too_deeply_is_a_scene_file_error(tmp_path):
    path = tmp_path / "deep.json"
    path.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(SceneFileError, match="deep.json: nested too deeply to parse"):
        load_scene(path)


def test_the_documented_objects_examples_are_valid():
    for page in ("scene-format.md", "objects.md"):
        text = (EXAMPLES.parent / "docs" / page).read_text()
        blocks = [b.split("```", 1)[0] for b in text.split("```json\n")[1:]]
        scenes = [scene_from_dict(json.loads(b))[0] for b in blocks if '"objects"' in b]
        assert len(scenes) == 1 and scenes[0].material.kd.shape == (2, 3), page


# ------------------------------------------------------------------- several objects

OBJECTS = {
    "objects": [
        {"mesh": {"builtin": {"icosphere": {"subdivisions": 0}}},
         "transform": {"translate": [-1, 0, 0], "scale": 0.5},
         "material": {"kd": [0.8, 0.1, 0.1]}},
        {"mesh": {"builtin": {"box": {"size": [1, 0.5, 1]}}},
         "transform": {"matrix": [[1, 0, 0, 1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]},
         "material": {"kd": 0.3, "ks": 0.5, "shininess": 12},
         "back_material": {"kd": [0.1, 0.6, 0.1]}},
    ],
    "transform": {"rotate_deg": [0, 30, 0]},
    "camera": {"eye": [0, 1, 4], "target": [0, 0, 0], "width": 16, "height": 12},
    "lights": [{"type": "point", "position": [1, 2, 3]}],
    "two_sided": True,
}


def objects_scene_by_api():
    objects = [
        ds.scene_object(ds.icosphere(0), ds.material(kd=(0.8, 0.1, 0.1)),
                        transform=ds.model_matrix((-1, 0, 0), scale=(0.5, 0.5, 0.5))),
        ds.scene_object(ds.box((1, 0.5, 1)), ds.material(kd=0.3, ks=0.5, shininess=12),
                        transform=ds.model_matrix((1, 0, 0)),
                        back_material=ds.material(kd=(0.1, 0.6, 0.1)))]
    camera = ds.look_at((0, 1, 4), (0, 0, 0), width=16, height=12)
    return ds.make_scene(objects=objects, camera=camera, lights=[ds.point_light((1, 2, 3))],
                         model=ds.model_matrix(rotate_deg=(0, 30, 0)), two_sided=True)


def test_objects_build_the_api_scene_and_round_trip():
    scene, _ = scene_from_dict(copy.deepcopy(OBJECTS))
    want = objects_scene_by_api()
    assert_same_tree(scene, want)
    assert scene.material.kd.shape == (2, 3) and scene.objects.faces.shape == (20 + 12,)
    data = json.loads(json.dumps(scene_to_dict(scene, ds.RenderSettings())))
    assert [sorted(o) for o in data["objects"]] == [["back_material", "material", "mesh"]] * 2
    back, _ = scene_from_dict(data)
    # inline normals are renormalized on reading: equal to float32 rounding
    assert_same_tree(back, scene, rtol=1e-6)
    with pytest.raises(ValueError, match="mesh_ref: got 'a.obj'; expected None for a scene of"):
        scene_to_dict(scene, ds.RenderSettings(), mesh_ref="a.obj")


def test_example_table_is_the_objects_figure_scene():
    import importlib.util
    path = Path(__file__).resolve().parents[1] / "docs" / "make_objects_figure.py"
    spec = importlib.util.spec_from_file_location("make_objects_figure", path)
    figure = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(figure)
    scene, _ = load_scene(EXAMPLES / "table.json")
    assert_same_tree(scene, figure.table_scene(), rtol=1e-6)


def edited_objects(keys, value):
    return edited(keys, value, OBJECTS)


@pytest.mark.parametrize("keys, value, message", [
    (("objects", 1, "mesh"), DELETE, "objects[1].mesh: missing; expected an object"),
    (("objects", 1, "transform"), {"scale": [1, 0, 1]},
     "objects[1].transform: the upper 3x3 block is singular"),
    (("objects", 1, "transform"), {"matrix": [[1, 0], [0, 1]]},
     "objects[1].transform.matrix: got [[1, 0], [0, 1]]; expected a 4x4 matrix"),
    (("objects", 1, "transform"), {"rotate": [0, 1, 0]},
     'objects[1].transform.rotate: unknown key; did you mean "rotate_deg"?'),
    (("objects", 0, "material"), {"kd": -1}, "objects[0].material.kd: got -1; expected a"),
    (("objects", 1, "back_material"), {"ks": "x"}, 'objects[1].back_material.ks: got "x"'),
    (("objects", 0, "mesh"), {"path": "missing.obj"},
     "objects[0].mesh.path: mesh file 'missing.obj' not found"),
    (("objects", 0, "colour"), 1, 'objects[0].colour: unknown key; expected one of: '
                                  "back_material, material, mesh, name, transform"),
    (("objects", 1, "name"), 3, "objects[1].name: got 3; expected a string"),
    (("objects", 1, "name"), "", "objects[1].name: got ''; expected a non-empty string"),
    (("objects", 1, "name"), "my box", "objects[1].name: got 'my box'; expected a non-empty "
                                        "string without spaces"),
    (("objects", 1), "box", 'objects[1]: got "box"; expected an object'),
    (("objects",), [], "objects: got []; expected a non-empty array of objects"),
    (("objects",), {"mesh": {}}, 'objects: got {"mesh": {}}; expected an array'),
    (("mesh",), {"builtin": {"box": {}}}, "mesh: not allowed with objects"),
    (("material",), {}, "material: not allowed with objects"),
    (("objects",), DELETE, "mesh: missing; expected an object (or objects"),
])
def test_objects_errors_name_the_key_path(keys, value, message):
    with pytest.raises(SceneFileError) as err:
        scene_from_dict(edited_objects(keys, value))
    assert str(err.value).startswith(message), str(err.value)

"""float64 end to end under x64: every builder and loader keeps the float dtype it is given.

Under `jax.enable_x64(True)` float64 input stays float64 and float32 input float32;
generated geometry and values read from lists, JSON and files take JAX's default float
dtype (float64 under x64). Without x64 everything is float32, as before. The reference is
the input itself: a float64 vertex such as 0.1 must come back bit for bit, which float32
(0.100000001490116...) cannot hold. Each test builds under its own x64 setting.
"""

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from jax.test_util import check_grads

import diffshade as ds
from data_synth import load_dataset, make_dataset, save_dataset
from diffshade.io.scenefile import scene_to_dict
from diffshade.scene.mesh import check_mesh, transform_mesh, vertex_normals

F32, F64 = np.dtype(np.float32), np.dtype(np.float64)
# 0.1 and 1/3 are not float32 numbers: float32 storage would change them.
TENT = np.array([[0.0, 0.0, 0.0], [2.0, 0.1, 0.0], [0.0, 1.0, 1 / 3], [0.0, -1.0, 1.0]])
TENT_FACES = np.array([[0, 1, 2], [0, 3, 1]])


def mesh_dtypes(mesh):
    return mesh.vertices.dtype, mesh.normals.dtype


@pytest.fixture(params=[True, False], ids=["x64", "x32"])
def x64_mode(request):
    """(x64 on?, the default float dtype) with x64 set accordingly for the test."""
    with jax.enable_x64(request.param):
        yield request.param, F64 if request.param else F32


ARRAY_BUILDERS = {
    "plain": lambda v: ds.mesh_from_arrays(v, TENT_FACES),
    "area": lambda v: ds.mesh_from_arrays(v, TENT_FACES, weighting="area"),
    "normals": lambda v: ds.mesh_from_arrays(v, TENT_FACES, np.ones_like(v)),
    "crease": lambda v: ds.mesh_from_arrays(v, TENT_FACES, crease_angle=30.0),
    "check_mesh": lambda v: check_mesh(ds.Mesh(v, TENT_FACES, np.zeros_like(v))),
    "transform": lambda v: transform_mesh(ds.mesh_from_arrays(v, TENT_FACES),
                                             ds.model_matrix(scale=(1, 2, 3))),
}


@pytest.mark.parametrize("build", ARRAY_BUILDERS.values(), ids=ARRAY_BUILDERS)
@pytest.mark.parametrize("given", [F32, F64])
def test_array_builders_keep_the_given_dtype(x64_mode, build, given):
    x64, _ = x64_mode
    mesh = build(TENT.astype(given))
    want = given if x64 else F32
    assert mesh_dtypes(mesh) == (want, want)
    assert mesh.faces.dtype == jnp.int32


def test_float64_vertices_are_kept_exactly_under_x64(x64_mode):
    x64, _ = x64_mode
    mesh = ds.mesh_from_arrays(TENT, TENT_FACES)
    want = TENT if x64 else TENT.astype(np.float32)
    np.testing.assert_array_equal(np.asarray(mesh.vertices), want)
    normals = vertex_normals(mesh.vertices, mesh.faces)
    assert normals.dtype == want.dtype


def test_lists_integers_and_generated_shapes_take_the_default_dtype(x64_mode):
    _, default = x64_mode
    meshes = [ds.mesh_from_arrays(TENT.tolist(), TENT_FACES),
              ds.mesh_from_arrays(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]]), [[0, 1, 2]]),
              ds.mesh_from_trimesh(trimesh.creation.box()),
              ds.icosphere(1), ds.torus(), ds.box()]
    for mesh in meshes:
        assert mesh_dtypes(mesh) == (default, default)
    assert ds.model_matrix(rotate_deg=(10, 20, 30)).dtype == default


@pytest.mark.parametrize("ext", ["obj", "ply", "stl"])
def test_mesh_files_load_in_the_default_dtype(x64_mode, tmp_path, ext):
    _, default = x64_mode
    trimesh.creation.icosphere(subdivisions=1).export(tmp_path / f"s.{ext}")
    assert mesh_dtypes(ds.load_mesh(tmp_path / f"s.{ext}")) == (default, default)


def scene_leaves(scene):
    return [leaf for leaf in jax.tree.leaves(scene) if jnp.issubdtype(leaf.dtype, jnp.floating)]


def test_scene_builders_and_files_take_the_default_dtype(x64_mode, tmp_path):
    _, default = x64_mode
    scenes = [ds.builtin_scene(name, 8, 8) for name in ds.BUILTIN_SCENES]
    camera = ds.look_at(np.array([0.0, 0.1, 3.0]), (0, 0, 0), width=8, height=8)
    lights = [ds.ambient_light(0.1), ds.directional_light(np.array([0.1, -1.0, -1.0])),
              ds.point_light((1, 2, 3), 0.5), ds.spot_light((0, 0, 3), (0, 0, -1), 0.5)]
    mat = ds.material(ka=np.array([0.1, 0.2, 0.3]), kd=0.5, ks=0.3, shininess=10.0,
                      emission=0.01)
    direct = ds.make_scene(ds.mesh_from_arrays(TENT, TENT_FACES), camera, lights, mat,
                           model=ds.model_matrix(translate=(0.1, 0, 0)))
    scenes.append(direct)
    inline = scene_to_dict(direct, ds.RenderSettings())
    scenes.append(ds.scene_from_dict(json.loads(json.dumps(inline)))[0])
    trimesh.creation.box().export(tmp_path / "box.obj")
    path_scene = {**inline, "mesh": {"path": "box.obj"}}
    (tmp_path / "scene.json").write_text(json.dumps(path_scene))
    scenes.append(ds.load_scene(tmp_path / "scene.json")[0])
    for scene in scenes:
        assert {leaf.dtype for leaf in scene_leaves(scene)} == {default}
    if default == F64:  # the inline scene file wrote 0.1 and 1/3 in full
        np.testing.assert_array_equal(np.asarray(scenes[-2].mesh.vertices), TENT)


def test_dataset_round_trip_keeps_float64_under_x64(x64_mode, tmp_path):
    _, default = x64_mode
    mesh = ds.mesh_from_arrays(TENT, TENT_FACES)
    data = make_dataset(mesh, ds.material(ks=0.3, shininess=10.0), n_views=1, n_lights=1,
                        size=8)
    assert mesh_dtypes(data.mesh) == (default, default)
    loaded = load_dataset(save_dataset(data, tmp_path / "data"))
    assert mesh_dtypes(loaded.mesh) == (default, default)
    np.testing.assert_array_equal(np.asarray(loaded.mesh.vertices), np.asarray(mesh.vertices))
    assert {leaf.dtype for leaf in scene_leaves(loaded.views[0].camera)} == {default}


def test_float64_vertex_gradient_check_runs_on_float64_vertices():
    with jax.enable_x64(True):
        mesh = ds.mesh_from_arrays(np.asarray(ds.icosphere(1).vertices), ds.icosphere(1).faces)
        camera = ds.look_at((0.3, 0.2, 3.4), (0.0, 0.0, 0.0), width=12, height=10, fov_y=40.0)
        scene = ds.make_scene(mesh, camera, [ds.directional_light((-0.3, -0.5, -1.0), 0.7)],
                              ds.material(ka=0.2, kd=0.5, ks=0.3, shininess=8.0))
        settings = ds.RenderSettings(raster="soft", faces_per_pixel=40, sigma=2.0, gamma=1e-2)
        weights = jnp.asarray(np.random.default_rng(3).normal(size=(10, 12, 4)))

        def image(vertices):
            normals = vertex_normals(vertices, mesh.faces)
            return ds.render(ds.replace(scene, mesh=ds.Mesh(vertices, mesh.faces, normals)),
                             settings)

        assert mesh_dtypes(mesh) == (F64, F64)
        assert image(mesh.vertices).dtype == F64
        check_grads(lambda v: jnp.sum(weights * image(v)), (mesh.vertices,), order=1,
                    modes=["rev"], eps=1e-6, atol=1e-6, rtol=1e-4)

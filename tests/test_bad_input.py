"""Bad input gets a clear error at the API boundary (issue 5): a ValueError, TypeError or
FileNotFoundError raised by diffshade itself (never by JAX, nor numpy's own message)
whose text names the argument, shows the value and says what was expected; through the
command line, one line on stderr, exit status 2, no traceback and no output file.

Each row of the tables below is (call, exception type, argument name, value as shown);
"expected" must follow in the message.
"""

import dataclasses
import json
import os
import re
import subprocess
import sys

import jax
import numpy as np
import pytest

import diffshade as ds
import fitting
from data_synth import make_dataset
from diffshade import cli
from diffshade.pipeline import render_supersampled

NAN, INF = float("nan"), float("inf")
TRIANGLE = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
FACE = [[0, 1, 2]]


def assert_clear(info, name, value):
    """The raised error names `name`, shows `value` and says what was expected."""
    err = info.value
    assert isinstance(err, (ValueError, TypeError, FileNotFoundError)), type(err)
    assert not type(err).__module__.startswith(("jax", "jaxlib", "numpy")), type(err)
    message = str(err)
    assert name in message and value in message and "expected" in message, message


def camera(**kw):
    return ds.look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), **{"width": 8, "height": 8, **kw})


# ------------------------------------------------------------------------------ meshes

MESHES = {
    "nan_vertex": (lambda: ds.mesh_from_arrays([[NAN, 0, 0], *TRIANGLE[1:]], FACE),
                   "vertices", "nan"),
    "inf_vertex": (lambda: ds.mesh_from_arrays([TRIANGLE[0], [1, INF, 0], TRIANGLE[2]], FACE),
                   "vertices", "inf"),
    # finite in float64, but a float32 mesh would hold inf
    "vertex_beyond_float32": (lambda: ds.mesh_from_arrays([[0, 0, 1e39], *TRIANGLE[1:]], FACE),
                              "vertices", "1e+39"),
    "face_out_of_range": (lambda: ds.mesh_from_arrays(TRIANGLE, [[0, 1, 3]]), "faces", "3"),
    "face_negative": (lambda: ds.mesh_from_arrays(TRIANGLE, [[0, -1, 2]]), "faces", "-1"),
    "vertices_n_by_2": (lambda: ds.mesh_from_arrays([[0, 0], [1, 0], [0, 1]], FACE),
                        "vertices", "(3, 2)"),
    "faces_n_by_2": (lambda: ds.mesh_from_arrays(TRIANGLE, [[0, 1]]), "faces", "(1, 2)"),
    "faces_1d": (lambda: ds.mesh_from_arrays(TRIANGLE, [0, 1, 2]), "faces", "(3,)"),
    "no_faces": (lambda: ds.mesh_from_arrays(TRIANGLE, np.zeros((0, 3), int)), "faces",
                 "(0, 3)"),
    "faces_not_integral": (lambda: ds.mesh_from_arrays(TRIANGLE, [[0, 1, 1.5]]), "faces", "1.5"),
    "vertices_complex": (lambda: ds.mesh_from_arrays(np.array(TRIANGLE, complex), FACE),
                         "vertices", "complex"),
    "faces_complex": (lambda: ds.mesh_from_arrays(TRIANGLE, np.array(FACE, complex)), "faces",
                      "complex"),
    "vertices_strings": (lambda: ds.mesh_from_arrays([["a", "b", "c"]] * 3, FACE), "vertices",
                         "<U1"),
    "faces_strings": (lambda: ds.mesh_from_arrays(TRIANGLE, [["0", "1", "2"]]), "faces", "<U1"),
    "faces_bool": (lambda: ds.mesh_from_arrays(TRIANGLE, [[True, False, True]]), "faces",
                   "bool"),
    "vertices_ragged": (lambda: ds.mesh_from_arrays([[0, 0, 0], [1, 0], [0, 1, 0]], FACE),
                        "vertices", "ragged"),
    "vertices_none": (lambda: ds.mesh_from_arrays(None, FACE), "vertices", "()"),
    "normals_nan": (lambda: ds.mesh_from_arrays(TRIANGLE, FACE, [[0, 0, NAN]] * 3), "normals",
                    "nan"),
    "icosphere_subdivisions": (lambda: ds.icosphere(-1), "subdivisions", "-1"),
    "icosphere_radius": (lambda: ds.icosphere(1, radius=0.0), "radius", "0.0"),
    "box_size": (lambda: ds.box((1.0, -1.0, 1.0)), "size", "-1.0"),
    "model_matrix_nan": (lambda: ds.model_matrix(scale=(1.0, NAN, 1.0)), "scale", "nan"),
    "model_matrix_text": (lambda: ds.model_matrix(rotate_deg=("x", 0, 0)), "rotate_deg", "'x'"),
    "box_text": (lambda: ds.box("big"), "size", "'big'"),
    "radius_beyond_float32": (lambda: ds.icosphere(1, radius=1e39), "radius", "1e+39"),
}


@pytest.mark.parametrize("call, name, value", MESHES.values(), ids=MESHES)
def test_bad_mesh_input_raises_a_clear_value_error(call, name, value):
    with pytest.raises(ValueError) as info:
        call()
    assert_clear(info, name, value)


# ------------------------------------------------------------------- material and camera

MATERIALS = {
    "shininess_negative": (dict(shininess=-1.0), "shininess", "-1.0"),
    "shininess_nan": (dict(shininess=NAN), "shininess", "nan"),
    "shininess_inf": (dict(shininess=INF), "shininess", "inf"),
    "shininess_beyond_float32": (dict(shininess=1e39), "shininess", "1e+39"),
    "shininess_text": (dict(shininess="shiny"), "shininess", "'shiny'"),
    "shininess_rgb": (dict(shininess=[1.0, 2.0, 3.0]), "shininess", "[1.0, 2.0, 3.0]"),
    "ka_negative": (dict(ka=-0.1), "ka", "-0.1"),
    "kd_nan_channel": (dict(kd=[0.5, NAN, 0.5]), "kd", "nan"),
    "ks_negative_channel": (dict(ks=[0.5, -1.0, 0.5]), "ks", "-1.0"),
    "emission_inf": (dict(emission=INF), "emission", "inf"),
    "kd_text": (dict(kd="red"), "kd", "'red'"),
    "kd_two_channels": (dict(kd=[0.5, 0.5]), "kd", "[0.5, 0.5]"),
    # named by its size, not printed texel by texel; and the fields that take one are said
    "ka_texture": (dict(ka=ds.texture(np.full((4, 6, 1), 0.5))), "ka",
                   "a texture of 6x4 texels; expected a non-negative finite number or 3 of "
                   "them (RGB): only kd, ks, shininess take textures"),
}


@pytest.mark.parametrize("kwargs, name, value", MATERIALS.values(), ids=MATERIALS)
def test_bad_material_raises_a_clear_value_error(kwargs, name, value):
    with pytest.raises(ValueError) as info:
        ds.material(**kwargs)
    assert_clear(info, name, value)


CAMERAS = {
    "width_zero": (dict(width=0), "width", "0"),
    "height_negative": (dict(height=-5), "height", "-5"),
    "width_fractional": (dict(width=2.5), "width", "2.5"),
    "width_text": (dict(width="8"), "width", "'8'"),
    "width_bool": (dict(width=True), "width", "True"),
    "eye_equals_target": (dict(eye=(1.0, 2.0, 3.0), target=(1.0, 2.0, 3.0)), "eye, target",
                          "[1.0, 2.0, 3.0]"),
    "up_parallel": (dict(up=(0.0, 0.0, 2.0)), "up", "[0.0, 0.0, 2.0]"),
    "up_zero": (dict(up=(0.0, 0.0, 0.0)), "up", "[0.0, 0.0, 0.0]"),
    "near_equals_far": (dict(near=10.0, far=10.0), "near, far", "near=10.0, far=10.0"),
    "near_beyond_far": (dict(near=20.0, far=10.0), "near, far", "near=20.0, far=10.0"),
    "near_zero": (dict(near=0.0), "near, far", "near=0.0"),
    "near_negative": (dict(near=-1.0), "near, far", "near=-1.0"),
    "near_none": (dict(near=None), "near", "None"),
    "far_inf": (dict(far=INF), "far", "inf"),
    "fov_zero": (dict(fov_y=0.0), "fov_y", "0.0"),
    "fov_180": (dict(fov_y=180.0), "fov_y", "180.0"),
    "fov_negative": (dict(fov_y=-10.0), "fov_y", "-10.0"),
    "fov_nan": (dict(fov_y=NAN), "fov_y", "nan"),
    "fov_text": (dict(fov_y="wide"), "fov_y", "'wide'"),
    "fov_pair": (dict(fov_y=[45.0, 50.0]), "fov_y", "[45.0, 50.0]"),
    "eye_nan": (dict(eye=(0.0, NAN, 3.0)), "eye", "nan"),
    "eye_beyond_float32": (dict(eye=(0.0, 0.0, 1e39)), "eye", "1e+39"),
    "eye_two_numbers": (dict(eye=(0.0, 3.0)), "eye", "(0.0, 3.0)"),
    "eye_text": (dict(eye="here"), "eye", "'here'"),
    "projection": (dict(projection="fisheye"), "projection", "'fisheye'"),
    "ortho_height": (dict(ortho_height=0.0), "ortho_height", "0.0"),
    # a lens that scales eye space by more than 1e8: clip coordinates' products overflow
    # float32 (at 1e-20 degrees the images were empty, and the host search hung)
    "fov_below_float32_reach": (dict(fov_y=1e-20), "fov_y", "1e-20"),
    "ortho_height_below_float32_reach": (dict(projection="orthographic", ortho_height=1e-30),
                                         "ortho_height", "1e-30"),
}


@pytest.mark.parametrize("kwargs, name, value", CAMERAS.values(), ids=CAMERAS)
def test_bad_camera_raises_a_clear_value_error(kwargs, name, value):
    args = {"eye": (0.0, 0.0, 3.0), "target": (0.0, 0.0, 0.0), "width": 8, "height": 8, **kwargs}
    with pytest.raises(ValueError) as info:
        ds.look_at(args.pop("eye"), args.pop("target"), **args)
    assert_clear(info, name, value)


# ---------------------------------------------------------------------------- lights

LIGHTS = {
    "attenuation_all_zero": (lambda: ds.point_light((0, 0, 1), attenuation=(0, 0, 0)),
                             "attenuation", "(0, 0, 0)"),
    "attenuation_negative": (lambda: ds.point_light((0, 0, 1), attenuation=(1, -1, 0)),
                             "attenuation", "(1, -1, 0)"),
    "attenuation_nan": (lambda: ds.spot_light((0, 0, 1), (0, 0, -1), attenuation=(1, NAN, 0)),
                        "attenuation", "nan"),
    "attenuation_text": (lambda: ds.point_light((0, 0, 1), attenuation="none"), "attenuation",
                         "'none'"),
    "directional_zero_direction": (lambda: ds.directional_light((0, 0, 0)), "direction",
                                   "(0, 0, 0)"),
    "spot_zero_direction": (lambda: ds.spot_light((0, 0, 1), (0.0, 0.0, 0.0)), "direction",
                            "(0.0, 0.0, 0.0)"),
    "spot_cutoff_120": (lambda: ds.spot_light((0, 0, 1), (0, 0, -1), cutoff=120.0), "cutoff",
                        "120.0"),
    "spot_cutoff_negative": (lambda: ds.spot_light((0, 0, 1), (0, 0, -1), cutoff=-1.0),
                             "cutoff", "-1.0"),
    "spot_cutoff_text": (lambda: ds.spot_light((0, 0, 1), (0, 0, -1), cutoff="wide"), "cutoff",
                         "'wide'"),
    "spot_exponent_200": (lambda: ds.spot_light((0, 0, 1), (0, 0, -1), exponent=200.0),
                          "exponent", "200.0"),
    "spot_exponent_nan": (lambda: ds.spot_light((0, 0, 1), (0, 0, -1), exponent=NAN),
                          "exponent", "nan"),
    "colour_negative": (lambda: ds.point_light((0, 0, 1), -1.0), "color", "-1.0"),
    "colour_text": (lambda: ds.point_light((0, 0, 1), "white"), "color", "'white'"),
    "specular_nan": (lambda: ds.directional_light((0, 0, -1), specular=NAN), "specular", "nan"),
    "position_nan": (lambda: ds.point_light((0, NAN, 1)), "position", "nan"),
    "position_beyond_float32": (lambda: ds.point_light((0, 0, 1e39)), "position", "1e+39"),
    "position_two_numbers": (lambda: ds.point_light((0, 1)), "position", "(0, 1)"),
    "ambient_text": (lambda: ds.ambient_light("grey"), "color", "'grey'"),
}


@pytest.mark.parametrize("call, name, value", LIGHTS.values(), ids=LIGHTS)
def test_bad_light_raises_a_clear_value_error(call, name, value):
    with pytest.raises(ValueError) as info:
        call()
    assert_clear(info, name, value)


# ----------------------------------------------------------------- scene and settings

SCENES = {
    "mesh_not_a_mesh": (dict(mesh="sphere.obj"), TypeError, "mesh", "str"),
    "camera_not_a_camera": (dict(camera=(0, 0, 3)), TypeError, "camera", "tuple"),
    "material_not_a_material": (dict(material="red"), TypeError, "material", "str"),
    "back_material_not_a_material": (dict(back_material={"kd": 0.5}), TypeError,
                                     "back_material", "dict"),
    "lights_one_light": (dict(lights=ds.point_light((0, 0, 2))), TypeError, "lights",
                         "PointLight"),
    "lights_none": (dict(lights=None), TypeError, "lights", "NoneType"),
    "lights_text": (dict(lights="sun"), TypeError, "lights", "str"),
    "lights_junk_item": (dict(lights=[ds.ambient_light(0.1), "sun"]), TypeError, "lights[1]",
                         "str"),
    "model_singular": (dict(model=np.diag([1.0, 0.0, 1.0, 1.0])), ValueError, "model",
                       "singular"),
    "model_nan": (dict(model=np.full((4, 4), NAN)), ValueError, "model", "(4, 4)"),
    "model_3x3": (dict(model=np.eye(3)), ValueError, "model", "(3, 3)"),
    "model_text": (dict(model="identity"), ValueError, "model", "'identity'"),
    "global_ambient_negative": (dict(global_ambient=-1.0), ValueError, "global_ambient",
                                "-1.0"),
    "background_nan": (dict(background=[0.0, NAN, 0.0]), ValueError, "background", "nan"),
    "background_text": (dict(background="black"), ValueError, "background", "'black'"),
}


@pytest.mark.parametrize("kwargs, error, name, value", SCENES.values(), ids=SCENES)
def test_bad_scene_raises_a_clear_error(kwargs, error, name, value):
    args = {"mesh": ds.icosphere(0), "camera": camera(), **kwargs}
    with pytest.raises(error) as info:
        ds.make_scene(args.pop("mesh"), args.pop("camera"), **args)
    assert_clear(info, name, value)


SETTINGS = {
    "shading": (dict(shading="toon"), "shading", "'toon'"),
    "raster": (dict(raster="wireframe"), "raster", "'wireframe'"),
    "specular": (dict(specular="cook-torrance"), "specular", "'cook-torrance'"),
    "spot_edge": (dict(spot_edge=None), "spot_edge", "None"),
    "faces_per_pixel_zero": (dict(faces_per_pixel=0), "faces_per_pixel", "0"),
    "faces_per_pixel_float": (dict(faces_per_pixel=2.5), "faces_per_pixel", "2.5"),
    "sigma_zero": (dict(sigma=0.0), "sigma", "0.0"),
    "sigma_negative": (dict(sigma=-1.0), "sigma", "-1.0"),
    "sigma_nan": (dict(sigma=NAN), "sigma", "nan"),
    "sigma_inf": (dict(sigma=INF), "sigma", "inf"),
    # 1/gamma overflows float32 below ~3e-39: the soft blend would be inf - inf = NaN
    "gamma_below_float32": (dict(gamma=1e-40), "gamma", "1e-40"),
    "gamma_text": (dict(gamma="small"), "gamma", "'small'"),
    "spot_softness_zero": (dict(spot_softness=0.0), "spot_softness", "0.0"),
    "soft_threshold": (dict(soft_threshold=0.7), "soft_threshold", "0.7"),
    "soft_threshold_text": (dict(soft_threshold="x"), "soft_threshold", "'x'"),
    "clamp_text": (dict(clamp="no"), "clamp", "'no'"),
    "cull_backfaces_int": (dict(cull_backfaces=1), "cull_backfaces", "1"),
}


@pytest.mark.parametrize("kwargs, name, value", SETTINGS.values(), ids=SETTINGS)
def test_bad_render_settings_raise_a_clear_value_error(kwargs, name, value):
    with pytest.raises(ValueError) as info:
        ds.RenderSettings(**kwargs)
    assert_clear(info, name, value)


RENDERS = {
    "scene_is_a_mesh": (lambda scene: ds.render(ds.icosphere(0)), "scene", "Mesh"),
    "scene_is_a_path": (lambda scene: ds.render("scene.json"), "scene", "str"),
    "settings_is_text": (lambda scene: ds.render(scene, "phong"), "settings", "str"),
    "settings_is_a_dict": (lambda scene: ds.render(scene, {"shading": "phong"}), "settings",
                           "dict"),
    "parts_settings_is_text": (lambda scene: ds.render_parts(scene, "flat"), "settings", "str"),
}


@pytest.mark.parametrize("call, name, value", RENDERS.values(), ids=RENDERS)
def test_render_rejects_what_is_not_a_scene_or_settings(call, name, value):
    with pytest.raises(TypeError) as info:
        call(ds.make_scene(ds.icosphere(0), camera()))
    assert_clear(info, name, value)


def test_the_narrowest_camera_accepted_renders_finite_on_both_kernel_paths():
    narrowest = camera(fov_y=ds.scene.camera.MIN_FOV_Y)
    scene = ds.make_scene(ds.icosphere(1), narrowest)
    for raster in ("hard", "soft"):
        for kernels in ("host", "jax"):
            image = np.asarray(ds.render(scene, ds.RenderSettings(raster=raster,
                                                                  kernels=kernels)))
            # the view's centre is the sphere's nearest point: covered (soft coverage stays
            # below 1 near the edges between faces, a pixel or so away at this magnification)
            assert np.all(np.isfinite(image)) and image[4, 4, 3] > 0.9, (raster, kernels)


def test_an_opencv_focal_length_beyond_float32_reach_is_refused():
    K = [[1e9, 0.0, 3.0], [0.0, 100.0, 3.0], [0.0, 0.0, 1.0]]
    with pytest.raises(ValueError) as info:
        ds.camera_from_opencv(K, np.eye(3), [0.0, 0.0, 3.0], 6, 6)
    assert_clear(info, "K: fx", "1000000000.0")


def test_vertex_normals_of_a_mesh_at_1e19_are_those_at_1():
    """Normals do not depend on the mesh's scale: float32's squares of coordinates
    overflowed from ~1e19 (a NaN normal for finite vertices)."""
    corners, faces = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]]), [[0, 1, 2]]
    for scale in (1.0, 1e19, 1e-30):
        normals = np.asarray(ds.mesh_from_arrays(corners * scale, faces).normals)
        np.testing.assert_array_equal(normals, np.tile([0.0, 0.0, 1.0], (3, 1)))


def test_a_render_that_overflows_float32_is_refused_not_returned_as_nan():
    """Every builder takes a point light 1e20 away (a finite float32), but its squared
    distance overflows: render raises instead of returning NaN pixels."""
    scene = ds.make_scene(ds.icosphere(1), camera(), lights=[ds.point_light((0.0, 0.0, 1e20))])
    for call in (lambda: ds.render(scene), lambda: ds.render_views(scene, [camera()] * 2),
                 lambda: render_supersampled(scene, factor=2)):
        with pytest.raises(ValueError) as info:
            call()
        assert_clear(info, "scene", "not finite")
    # under the caller's jit the image comes back as it is (NaN), unchecked
    assert np.isnan(np.asarray(jax.jit(ds.render)(scene))).any()


def _mesh_made_directly(change):
    m = ds.icosphere(1)
    return {"no_faces": lambda: ds.Mesh(m.vertices, m.faces[:0], m.normals),
            "float_faces": lambda: ds.Mesh(m.vertices, m.faces.astype(np.float32), m.normals),
            "lists": lambda: ds.Mesh(np.asarray(m.vertices).tolist(),
                                     np.asarray(m.faces).tolist(),
                                     np.asarray(m.normals).tolist()),
            "nan_vertex": lambda: ds.replace(m, vertices=m.vertices.at[0, 0].set(NAN)),
            "index_out_of_range": lambda: ds.replace(m, faces=m.faces.at[3, 1].set(10**8)),
            "negative_index": lambda: ds.replace(m, faces=m.faces.at[0, 0].set(-1))}[change]()


DIRECT_MESHES = {
    "no_faces": (ValueError, "scene.mesh.faces", "(0, 3)"),
    "float_faces": (TypeError, "scene.mesh.faces", "float32"),
    "lists": (TypeError, "scene.mesh.vertices", "list"),
    "nan_vertex": (ValueError, "scene.mesh.vertices", "nan"),
    "index_out_of_range": (ValueError, "scene.mesh.faces", "1e+08"),
    "negative_index": (ValueError, "scene.mesh.faces", "-1"),
}


@pytest.mark.parametrize("change, error, name, value", [(k, *v) for k, v in DIRECT_MESHES.items()],
                         ids=DIRECT_MESHES)
def test_a_mesh_made_directly_is_checked_when_rendered(change, error, name, value):
    """make_scene takes a Mesh as it is; render checks its data as mesh_from_arrays would
    (an index out of range made the host rasterizer read outside the vertices: a
    segmentation fault, or a silently wrong image)."""
    scene = ds.make_scene(_mesh_made_directly(change), camera())
    with pytest.raises(error) as info:
        ds.render(scene)
    assert_clear(info, name, value)


# ----------------------------------------------------------------------------- files


def test_missing_or_unreadable_mesh_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="mesh file not found: .*missing.obj"):
        ds.load_mesh(tmp_path / "missing.obj")
    with pytest.raises(ValueError) as info:
        ds.load_mesh(tmp_path)  # a folder is not a mesh file
    assert_clear(info, "path", "is a directory")
    for name, content in [("garbage.obj", b"this is not a mesh\x00\x01"), ("empty.obj", b""),
                          ("points.obj", b"v 0 0 0\nv 1 0 0\n"),
                          ("truncated.ply", b"ply\nformat ascii 1.0\nelement vertex 3\n"),
                          ("bad_index.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 7\n")]:
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ValueError) as info:
            ds.load_mesh(tmp_path / name)
        assert_clear(info, "path", name)


PLY_HEADER = ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
              "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
              "end_header\n")
OBJ_TRIANGLE = "v 0 0 0\nv 1 0 0\nv 0 1 0\n"
# file name -> (contents, what the message shows after "path: ... <file name>")
BAD_MESH_FILES = {
    "face_truncated_to_one.obj": (OBJ_TRIANGLE + "v 1 1 0\nf 1 2 3\nf 1\n", "line 6: 'f 1'"),
    "face_truncated_to_two.obj": (OBJ_TRIANGLE + "f 1 2 3\nf 3 2", "line 5: 'f 3 2'"),
    "face_with_index_0.obj": (OBJ_TRIANGLE + "f 0 1 2\n", "line 4: 'f 0 1 2'"),
    "face_beyond_vertices.obj": (OBJ_TRIANGLE + "f 1 2 7\n", "line 4: a face refers to vertex 7"),
    "face_relative_too_far.obj": (OBJ_TRIANGLE + "f -1 -2 -4\n", "line 4: 'f -1 -2 -4'"),
    "face_text.obj": (OBJ_TRIANGLE + "f 1 b 3\n", "line 4: 'f 1 b 3'"),
    "vertex_truncated.obj": ("v 0 0 0\nv 1 0 0\nv 0 1\nf 1 2 3\n", "line 3: 'v 0 1'"),
    "vertex_text.obj": ("v 0 0 0\nv 1 zero 0\nv 0 1 0\nf 1 2 3\n", "line 2: 'v 1 zero 0'"),
    "vertex_nan.obj": ("v 0 0 0\nv nan 0 0\nv 0 1 0\nv 1 1 0\nf 1 2 3\nf 1 3 4\n",
                       "vertices: row 1 is [nan, 0.0, 0.0]; expected finite"),
    "vertex_inf.obj": (OBJ_TRIANGLE + "v 1e999 1 0\nf 1 2 3\nf 2 3 4\n", "row 3 is [inf"),
    "vertex_nan.ply": (PLY_HEADER + "0 0 0\nnan 0 0\n0 1 0\n3 0 1 2\n", "row 1 is [nan"),
    "face_beyond_vertices.ply": (PLY_HEADER + "0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n",
                                 "faces: index 7 out of range for 3 vertices"),
}


@pytest.mark.parametrize("name", BAD_MESH_FILES)
def test_malformed_mesh_file_is_named_with_its_line(tmp_path, name):
    contents, shown = BAD_MESH_FILES[name]
    (tmp_path / name).write_text(contents)
    with pytest.raises(ValueError) as info:
        ds.load_mesh(tmp_path / name)
    assert_clear(info, "path", name)
    assert str(info.value).startswith(f"path: mesh file '{tmp_path / name}'")
    assert shown in str(info.value)


def test_obj_comments_normals_and_relative_indices_are_not_truncation(tmp_path):
    path = tmp_path / "ok.obj"
    path.write_text("# a comment line\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\n"
                    "f 1//1 2//1 3//1\nf -3//1 -2//1 -1//1\n")
    mesh = ds.load_mesh(path)
    np.testing.assert_array_equal(np.asarray(mesh.faces), [[0, 1, 2], [0, 1, 2]])


def test_missing_or_unreadable_image_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="image file not found: .*missing.png"):
        ds.read_image(tmp_path / "missing.png")
    with pytest.raises(FileNotFoundError, match="image file not found"):
        ds.read_image(tmp_path)
    (tmp_path / "junk.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="junk.png"):
        ds.read_image(tmp_path / "junk.png")


# ---------------------------------------------------------------- scene files and CLI

GOOD = {"mesh": {"builtin": {"icosphere": {"subdivisions": 0}}},
        "camera": {"eye": [0, 0, 3], "target": [0, 0, 0], "width": 8, "height": 8}}


def with_camera(**changes):
    return json.dumps({**GOOD, "camera": {**GOOD["camera"], **changes}})


# file name -> (contents, text that must appear after the file name in the message)
BAD_FILES = {
    "truncated.json": ('{"mesh": {"builtin": {"icosphere": {}}}, "camera": {"eye": [0,',
                       "line 1, column"),
    "no_camera.json": (json.dumps({"mesh": GOOD["mesh"]}), "camera: missing; expected"),
    "no_mesh.json": (json.dumps({"camera": GOOD["camera"]}), "mesh: missing; expected"),
    "empty.json": ("", "line 1, column 1: invalid JSON"),
    "array.json": ("[1, 2, 3]", "top level: got [1, 2, 3]; expected an object"),
    "width_text.json": (with_camera(width="abc"), 'camera.width: got "abc"; expected'),
    "width_zero.json": (with_camera(width=0), "camera.width: got 0; expected"),
    "near_far.json": (with_camera(near=10, far=1), "camera.near, camera.far: got near=10"),
    "eye_nan.json": (with_camera(eye=[0, "NaN", 3]), "camera.eye: got"),
    "eye_is_target.json": (with_camera(eye=[0, 0, 0]), "camera.eye, camera.target"),
    "up_parallel.json": (with_camera(up=[0, 0, 1]), "camera.up: [0.0, 0.0, 1.0] is parallel"),
    "shininess.json": (json.dumps({**GOOD, "material": {"shininess": -5}}),
                       "material.shininess: got -5; expected"),
    "typo.json": (json.dumps({**GOOD, "materail": {}}), 'materail: unknown key; did you mean'),
    "faces.json": (json.dumps({**GOOD, "mesh": {"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]],
                                                "faces": [[0, 1, 5]]}}),
                   "mesh.faces: index 5 out of range"),
    "missing_mesh.json": (json.dumps({**GOOD, "mesh": {"path": "nowhere.obj"}}),
                          "mesh.path: mesh file 'nowhere.obj' not found"),
    "garbage_mesh.json": (json.dumps({**GOOD, "mesh": {"path": "garbage.obj"}}),
                          "mesh.path: mesh file"),
    "truncated_mesh.json": (json.dumps({**GOOD, "mesh": {"path": "truncated.obj"}}),
                            "mesh.path: mesh file"),
    "folder_mesh.json": (json.dumps({**GOOD, "mesh": {"path": "."}}), "mesh.path: "),
    "faces_negative.json": (json.dumps({**GOOD, "mesh": {"vertices": [[0, 0, 0], [1, 0, 0],
                                                                      [0, 1, 0]],
                                                         "faces": [[0, -1, 2]]}}),
                            "mesh.faces: index -1 out of range"),
    "vertex_nan.json": (json.dumps({**GOOD, "mesh": {"vertices": [[0, 0, 0], [1, "NaN", 0],
                                                                  [0, 1, 0]],
                                                     "faces": [[0, 1, 2]]}}),
                        "mesh.vertices: row 1 is [1.0, nan, 0.0]; expected finite"),
    "binary.json": (b"\xff\xfe\x00garbage", "byte 0: not UTF-8 text"),
}


def write_bad(tmp_path, name):
    """The bad scene file `name` in tmp_path (and the garbage mesh it may refer to)."""
    contents, _ = BAD_FILES[name]
    (tmp_path / "garbage.obj").write_bytes(b"not a mesh at all\n")
    (tmp_path / "truncated.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2")
    path = tmp_path / name
    if isinstance(contents, bytes):
        path.write_bytes(contents)
    else:
        path.write_text(contents.replace('"NaN"', "NaN"))  # JSON's NaN extension
    return path


@pytest.mark.parametrize("name", BAD_FILES)
def test_bad_scene_file_raises_a_value_error_naming_file_and_key(tmp_path, name):
    with pytest.raises(ValueError) as info:
        ds.load_scene(write_bad(tmp_path, name))
    assert isinstance(info.value, ds.SceneFileError)
    assert f"{name}: {BAD_FILES[name][1]}" in str(info.value)


@pytest.mark.parametrize("name, shown", [
    ("truncated_mesh.json", "truncated.obj', line 5: 'f 1 2'; expected a face"),
    ("folder_mesh.json", "is a directory; expected a mesh file"),
])
def test_bad_mesh_of_a_scene_file_is_named_in_full(tmp_path, name, shown):
    with pytest.raises(ds.SceneFileError, match=re.escape(shown)):
        ds.load_scene(write_bad(tmp_path, name))


def test_missing_scene_file_raises_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError, match="scene file not found: .*missing.json"):
        ds.load_scene(tmp_path / "missing.json")


def one_error_line(capsys):
    out, err = capsys.readouterr()
    lines = err.splitlines()
    assert out == "" and len(lines) == 1 and lines[0].startswith("diffshade: error: "), err
    assert "Traceback" not in err
    return lines[0]


@pytest.mark.parametrize("name", [*BAD_FILES, "missing.json"])
def test_cli_render_of_a_bad_scene_prints_one_line_and_writes_nothing(tmp_path, capsys, name):
    scene = tmp_path / name if name == "missing.json" else write_bad(tmp_path, name)
    before = set(os.listdir(tmp_path))
    assert cli.main(["render", str(scene), "-o", str(tmp_path / "out" / "img.png")]) == 2
    line = one_error_line(capsys)
    assert name in line
    assert set(os.listdir(tmp_path)) == before  # no image, no output folder, no temporary


@pytest.mark.parametrize("size", ["0x8", "8x0", "-5x8", "2.5x8", "8"])
def test_cli_render_rejects_a_bad_size(tmp_path, capsys, size):
    argv = ["render", "--builtin", "box", "-o", str(tmp_path / "img.png"), f"--size={size}"]
    assert cli.main(argv) == 2
    assert f"got '{size}'; expected WxH" in one_error_line(capsys)
    assert os.listdir(tmp_path) == []


def test_console_script_reports_a_truncated_scene_without_traceback(tmp_path):
    scene, out = write_bad(tmp_path, "truncated.json"), tmp_path / "img.png"
    done = subprocess.run([sys.executable, "-m", "diffshade", "render", str(scene), "-o",
                           str(out)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 2 and done.stdout == ""
    assert done.stderr.splitlines() == [
        f"diffshade: error: {scene}: line 1, column 63: invalid JSON: Expecting value"]
    assert not out.exists()


# ------------------------------------------------------------------ fitting datasets


def view(target_shape=(12, 16, 3), **kw):
    """A View of a 16 x 12 camera with a target of `target_shape`."""
    return fitting.View(camera(width=16, height=12), [ds.directional_light((0, 0, -1))],
                        np.zeros(target_shape), **kw)


DATASETS = {
    "target_size": (lambda: fitting.Dataset(MESH, [view((16, 16, 3))]), ValueError,
                    "views[0].target", "(16, 16, 3)"),
    "target_transposed": (lambda: fitting.Dataset(MESH, [view(), view((16, 12, 3))]),
                          ValueError, "views[1].target", "(16, 12, 3)"),
    "target_rgba": (lambda: fitting.Dataset(MESH, [view((12, 16, 4))]), ValueError,
                    "views[0].target", "(12, 16, 4)"),
    "target_grey": (lambda: fitting.Dataset(MESH, [view((12, 16))]), ValueError,
                    "views[0].target", "(12, 16)"),
    "target_nan": (lambda: fitting.Dataset(MESH, [fitting.View(
        camera(width=16, height=12), [], np.full((12, 16, 3), NAN))]), ValueError,
        "views[0].target", "NaN"),
    "target_text": (lambda: fitting.View(camera(), [], "target.png"), ValueError, "target",
                    "'target.png'"),
    "target_ragged": (lambda: fitting.View(camera(), [], [[0.0, 0.0], [0.0]]), ValueError,
                      "target", "ragged"),
    "mask_size": (lambda: fitting.Dataset(MESH, [view(mask=np.ones((16, 16), bool))]),
                  ValueError, "views[0].mask", "(16, 16)"),
    "no_views": (lambda: fitting.Dataset(MESH, []), ValueError, "views", "empty"),
    "view_not_a_view": (lambda: fitting.Dataset(MESH, [view(), "view.png"]), TypeError,
                        "views[1]", "str"),
    "mesh_not_a_mesh": (lambda: fitting.Dataset("sphere.obj", [view()]), TypeError, "mesh",
                        "str"),
    "camera_not_a_camera": (lambda: fitting.Dataset(MESH, [fitting.View(
        "camera", [], np.zeros((12, 16, 3)))]), TypeError, "views[0].camera", "str"),
    "settings_not_settings": (lambda: fitting.Dataset(MESH, [view()], settings="phong"),
                              TypeError, "settings", "str"),
    "model_3x3": (lambda: fitting.Dataset(MESH, [view()], model=np.eye(3)), ValueError,
                  "model", "(3, 3)"),
    "model_text": (lambda: fitting.Dataset(MESH, [view()], model="identity"), ValueError,
                   "model", "'identity'"),
    "truth_not_a_material": (lambda: fitting.Dataset(MESH, [view()], truth={"kd": 0.5}),
                             TypeError, "truth", "dict"),
    "global_ambient_negative": (lambda: fitting.Dataset(MESH, [view()], global_ambient=-1.0),
                                ValueError, "global_ambient", "-1.0"),
    # a Mesh built directly is unchecked; a bad face index would crash the rasterizer
    "mesh_face_out_of_range": (lambda: fitting.Dataset(ds.replace(
        MESH, faces=MESH.faces.at[3, 1].set(12)), [view()]), ValueError, "mesh.faces", "12"),
    "mesh_face_negative": (lambda: fitting.Dataset(ds.replace(
        MESH, faces=MESH.faces.at[0, 0].set(-2)), [view()]), ValueError, "mesh.faces", "-2"),
    "mesh_vertex_nan": (lambda: fitting.Dataset(ds.replace(
        MESH, vertices=MESH.vertices.at[5, 2].set(NAN)), [view()]), ValueError,
        "mesh.vertices", "row 5"),
    "mesh_normals_shape": (lambda: fitting.Dataset(ds.replace(
        MESH, normals=MESH.normals[:4]), [view()]), ValueError, "mesh.normals", "(4, 3)"),
}
MESH = ds.icosphere(0)


@pytest.mark.parametrize("call, error, name, value", DATASETS.values(), ids=DATASETS)
def test_bad_fitting_data_raises_a_clear_error(call, error, name, value):
    with pytest.raises(error) as info:
        call()
    assert_clear(info, name, value)


FITS = {
    "dataset": (lambda d: fitting.fit("data/"), TypeError, "dataset", "str"),
    "spec": (lambda d: fitting.fit(d, spec="all"), TypeError, "spec", "str"),
    "method": (lambda d: fitting.fit(d, method="newton"), ValueError, "method", "'newton'"),
    "steps": (lambda d: fitting.fit(d, steps=-1), ValueError, "steps", "-1"),
    "loss": (lambda d: fitting.fit(d, loss="l3"), ValueError, "loss", "'l3'"),
    # finite in float64, inf in the fit's float32: it returned the starting values
    "lr_beyond_float32": (lambda d: fitting.fit(d, method="adam", lr=1e300), ValueError, "lr",
                          "1e+300"),
}


@pytest.mark.parametrize("call, error, name, value", FITS.values(), ids=FITS)
def test_bad_fit_arguments_raise_a_clear_error(call, error, name, value):
    with pytest.raises(error) as info:
        call(fitting.Dataset(MESH, [view()]))
    assert_clear(info, name, value)


def test_fit_without_truth_works_and_reports_no_errors():
    truth = ds.material(ka=0.3, kd=(0.6, 0.4, 0.2), ks=0.4, shininess=30.0)
    known = make_dataset(ds.icosphere(1), truth, n_views=1, n_lights=2, size=24)
    result = fitting.fit(dataclasses.replace(known, truth=None), with_uncertainty=False)
    assert result.errors is None and result.as_dict()["errors"] is None
    assert "%" not in result.summary()
    for name in ("ka", "kd", "ks", "shininess"):
        np.testing.assert_allclose(result.values[name], np.broadcast_to(getattr(truth, name),
                                                                        np.shape(result.values[name])),
                                   rtol=1e-3, err_msg=name)


# ------------------------------------------------- sizes beyond memory (issue 26)
# DIFFSHADE_MEMORY_LIMIT fixes the budget, so that each case is refused on any machine.

LIMIT = "4G"
SMALL_CAMERA = {"eye": [0, 0, 3], "target": [0, 0, 0], "width": 8, "height": 8}
SIZE_SCENES = {
    "camera_16384.json": ({**GOOD, "camera": {**SMALL_CAMERA, "width": 16384, "height": 16384}},
                          "camera width x height: got 16384x16384"),
    "faces_per_pixel.json": ({**GOOD, "settings": {"raster": "soft", "faces_per_pixel": 10**7}},
                             "faces_per_pixel: got 10000000"),
    "shadow_map_size.json": ({**GOOD, "lights": [{"type": "point", "position": [1, 1, 2],
                                                  "shadows": True}],
                              "settings": {"shadow_map_size": 10**6}},
                             "shadow_map_size: got 1000000"),
    "area_samples.json": ({**GOOD, "lights": [{"type": "area", "center": [0, 2, 2],
                                               "normal": [0, -1, -1], "radius": 0.3,
                                               "samples": 4096, "shadows": True}]},
                          "samples: got 4096"),
    "torus.json": ({**GOOD, "mesh": {"builtin": {"torus": {"major_segments": 65536,
                                                           "minor_segments": 65536}}}},
                   "mesh.builtin.torus.major_segments, mesh.builtin.torus.minor_segments: "
                   "got 65536 x 65536"),
}


def assert_costed(line):
    """The refusal says what the request needs and what is available."""
    assert re.search(r"needs (\S+ [kMGT]?B \(\d+ bytes\) of memory; expected at most 4.29 GB "
                     r"\(4294967296 bytes\)|an array of \d+ values; expected at most "
                     r"2147483647)", line), line


@pytest.mark.parametrize("name", SIZE_SCENES)
def test_cli_render_of_a_scene_beyond_memory_is_refused(tmp_path, capsys, monkeypatch, name):
    monkeypatch.setenv("DIFFSHADE_MEMORY_LIMIT", LIMIT)
    data, key = SIZE_SCENES[name]
    (tmp_path / name).write_text(json.dumps(data))
    assert cli.main(["render", str(tmp_path / name), "-o", str(tmp_path / "img.png")]) == 2
    line = one_error_line(capsys)
    assert f"{name}: {key}" in line or line.startswith(f"diffshade: error: {key}"), line
    assert_costed(line)
    assert os.listdir(tmp_path) == [name]


def test_cli_render_size_beyond_memory_names_the_bytes(tmp_path, capsys, monkeypatch):
    """The crash of issue 26 (an XLA abort): now one line, before anything is compiled."""
    monkeypatch.setenv("DIFFSHADE_MEMORY_LIMIT", LIMIT)
    argv = ["render", "--builtin", "sphere", "--size", "16384x16384", "-o",
            str(tmp_path / "img.png")]
    assert cli.main(argv) == 2
    faces = 20 * 4**4
    needed = 512 * 2**20 + 16384**2 * (256 + 256) + faces * 1024
    assert one_error_line(capsys) == (
        f"diffshade: error: camera width x height: got 16384x16384; a 16384x16384 render with "
        f"1 fragment slot a pixel and {faces} faces needs {needed / 1e9:.3g} GB ({needed} "
        "bytes) of memory; expected at most 4.29 GB (4294967296 bytes), the memory available "
        "(DIFFSHADE_MEMORY_LIMIT; set DIFFSHADE_MEMORY_LIMIT to change it)")
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize("size, named, shown", [
    ("16384", "n_views, n_lights, size: got 3, 2, 16384;",
     "6 images of 16384x16384 pixels needs 51.5 GB"),
    ("100000", "size: got 100000;", "expected at most 16384 pixels a side")])
def test_cli_synth_size_beyond_memory_is_refused_before_allocating(tmp_path, capsys,
                                                                   monkeypatch, size, named,
                                                                   shown):
    monkeypatch.setenv("DIFFSHADE_MEMORY_LIMIT", LIMIT)
    assert cli.main(["synth", "--size", size, "-o", str(tmp_path / "data")]) == 2
    line = one_error_line(capsys)
    assert named in line and shown in line, line
    assert os.listdir(tmp_path) == []


def test_cli_synth_views_beyond_memory_name_the_views(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("DIFFSHADE_MEMORY_LIMIT", LIMIT)
    assert cli.main(["synth", "--views", "100000", "--lights", "2", "--size", "64", "-o",
                     str(tmp_path / "data")]) == 2
    line = one_error_line(capsys)
    assert "n_views, n_lights, size: got 100000, 2, 64;" in line, line
    assert "a dataset of 200000 images" in line and "expected at most" in line, line
    assert os.listdir(tmp_path) == []


def test_a_huge_torus_is_refused_before_its_arrays_exist():
    with pytest.raises(ValueError) as info:
        ds.torus(1.0, 0.3, 65536, 65536)
    assert_clear(info, "major_segments, minor_segments", "65536 x 65536")


# ------------------------------------------------------ image files (issue 26)


def png_header_only(width, height):
    """A PNG whose IHDR claims width x height and whose pixel data is garbage: decoding it
    would fail, so a size error proves that the size was read first."""
    import struct
    import zlib

    def chunk(kind, payload):
        return (struct.pack(">I", len(payload)) + kind + payload
                + struct.pack(">I", zlib.crc32(kind + payload)))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", b"garbage")
            + chunk(b"IEND", b""))


def test_an_image_beyond_memory_is_refused_from_its_header(tmp_path, monkeypatch):
    monkeypatch.setenv("DIFFSHADE_MEMORY_LIMIT", LIMIT)
    path = tmp_path / "huge.png"
    path.write_bytes(png_header_only(20_000, 20_000))
    needed = 20_000**2 * 3 * 8
    with pytest.raises(ValueError) as info:
        ds.read_image(path)
    assert_clear(info, "path", "huge.png")
    assert "decoding its 20000x20000 pixels of 3 channels needs" in str(info.value)
    assert f"({needed} bytes)" in str(info.value)


def rgb_pixels():
    pixels = np.zeros((6, 8, 3), np.uint8)
    pixels[..., 0], pixels[..., 1], pixels[..., 2] = 200, 100, 30
    pixels[2:4, 3:6] = (10, 240, 120)
    return pixels


def srgb_linear(codes):
    return ds.io.srgb_to_linear(np.asarray(codes, np.float64) / 255.0)


def test_a_cmyk_jpeg_is_read_as_rgb_not_as_four_channels(tmp_path):
    from PIL import Image
    pixels = rgb_pixels()
    Image.fromarray(pixels).convert("CMYK").save(tmp_path / "cmyk.jpg", quality=100)
    image = ds.read_image(tmp_path / "cmyk.jpg")
    assert image.shape == (6, 8, 3)
    # JPEG's chroma subsampling blurs the colour edges: compare away from them
    np.testing.assert_allclose(image[0, 0], srgb_linear(pixels[0, 0]), atol=0.01)


def test_palette_and_grey_alpha_images_convert_as_defined(tmp_path):
    from PIL import Image
    pixels = rgb_pixels()
    palette = Image.fromarray(pixels).convert("P", palette=Image.Palette.ADAPTIVE, colors=4)
    palette.save(tmp_path / "palette.png", transparency=palette.getpixel((0, 0)))
    image = ds.read_image(tmp_path / "palette.png")
    assert image.shape == (6, 8, 4)
    np.testing.assert_allclose(image[3, 4, :3], srgb_linear(pixels[3, 4]), atol=1e-6)
    assert image[0, 0, 3] == 0.0 and image[3, 4, 3] == 1.0
    grey = np.stack([pixels[..., 0], np.full((6, 8), 128, np.uint8)], -1)
    Image.fromarray(grey, "LA").save(tmp_path / "grey_alpha.png")
    image = ds.read_image(tmp_path / "grey_alpha.png")
    assert image.shape == (6, 8, 2)
    np.testing.assert_allclose(image[0, 0], [srgb_linear(200), 128 / 255], atol=1e-6)


def test_a_mode_without_conversion_is_refused_by_name(tmp_path):
    from PIL import Image
    Image.new("LAB", (4, 4)).save(tmp_path / "lab.tif")
    with pytest.raises(ValueError) as info:
        ds.read_image(tmp_path / "lab.tif")
    assert_clear(info, "path", "lab.tif")
    assert "colour mode 'LAB' (CIE L*a*b* colour) has no conversion to RGB" in str(info.value)


def write_png_as(path, fmt):
    from PIL import Image
    Image.fromarray(rgb_pixels()).save(path, format=fmt)


# file name -> (how to make it, what the message says after the file's path)
MISLABELLED = {
    "empty.png": (lambda p: p.write_bytes(b""), "is empty (0 bytes); expected an image file"),
    "jpeg.png": (lambda p: write_png_as(p, "JPEG"),
                 "holds a JPEG image; expected a PNG image, as its extension '.png' says"),
    "png.npy": (lambda p: write_png_as(p, "PNG"), "holds a PNG image; expected a NumPy array "
                "(.npy), as its extension '.npy' says"),
    "npy.jpg": (lambda p: np.save(open(p, "wb"), np.zeros((2, 2, 3))),
                "holds a NumPy array (.npy); expected a JPEG image"),
    "text.png": (lambda p: p.write_text("hello"), "holds no image format diffshade reads "
                 "(first bytes 68 65 6c 6c 6f); expected a PNG image"),
    "pickle.npy": (lambda p: np.save(open(p, "wb"), np.array([{}], object), allow_pickle=True),
                   "holds Python objects (object), which only unpickling could read; "
                   "expected an array of numbers"),
    "text.img": (lambda p: p.write_text("hello"), "holds no image format diffshade reads; "
                 "expected PNG, JPEG"),
}


@pytest.mark.parametrize("name", MISLABELLED)
def test_an_image_file_is_judged_by_its_content_and_named(tmp_path, name):
    make, shown = MISLABELLED[name]
    make(tmp_path / name)
    with pytest.raises(ValueError) as info:
        ds.read_image(tmp_path / name)
    assert str(info.value) == f"path: {str(tmp_path / name)!r} {shown}" or \
        str(info.value).startswith(f"path: {str(tmp_path / name)!r} {shown}"), info.value


def test_a_jpeg_named_jpg_with_no_extension_rule_is_read_by_content(tmp_path):
    write_png_as(tmp_path / "photo.image", "JPEG")
    assert ds.read_image(tmp_path / "photo.image").shape == (6, 8, 3)


@pytest.mark.parametrize("space", ["sRGB", "SRGB", "Linear"])
def test_colour_space_names_are_read_in_any_case(tmp_path, space):
    ds.write_png(tmp_path / "img.png", np.full((2, 2, 3), 0.25), color_space=space)
    np.testing.assert_allclose(ds.read_image(tmp_path / "img.png", space), 0.25, atol=3e-3)
    args = cli.build_parser().parse_args(["fit", "data", "-o", "out", "--color-space", space])
    assert args.color_space == space.lower()


# ------------------------------------------------------ output paths (issue 26)


@pytest.fixture
def read_only(tmp_path):
    """A folder no one may write into: its mode bits, and for root (whom those do not
    stop) the immutable attribute."""
    folder = tmp_path / "read_only"
    folder.mkdir()
    folder.chmod(0o555)
    root = os.geteuid() == 0
    if root:
        subprocess.run(["chattr", "+i", str(folder)], check=True)
    yield folder
    if root:
        subprocess.run(["chattr", "-i", str(folder)], check=True)
    folder.chmod(0o755)


def test_write_into_a_read_only_folder_names_the_path_not_a_temporary(read_only):
    target = read_only / "img.png"
    with pytest.raises(OSError) as info:
        ds.write_png(target, np.zeros((2, 2, 3)))
    assert info.value.filename == str(target) and ".tmp" not in str(info.value)


OUTPUTS = {
    "render": (lambda ro: ["render", "--builtin", "box", "-o", str(ro / "img.png")],
               "--output: cannot write '{ro}/img.png': the folder '{ro}' is not writable"),
    "render_new_folder": (lambda ro: ["render", "--builtin", "box", "-o",
                                      str(ro / "new" / "img.png")],
                          "--output: cannot write '{ro}/new/img.png': the folder '{ro}' is"),
    "synth": (lambda ro: ["synth", "--size", "8", "-o", str(ro / "data")],
              "--output: cannot write '{ro}/data': the folder '{ro}' is not writable"),
    "fit_existing_folder": (lambda ro: ["fit", "no-such-dataset", "-o", str(ro)],
                            "--output: cannot write '{ro}': the folder '{ro}' is not "
                            "writable"),
}


@pytest.mark.parametrize("name", OUTPUTS)
def test_an_unwritable_output_is_refused_before_the_work(read_only, capsys, name):
    argv, shown = OUTPUTS[name]
    assert cli.main(argv(read_only)) == 2
    line = one_error_line(capsys)
    assert shown.format(ro=read_only) in line and ".tmp" not in line, line
    assert os.listdir(read_only) == []

"""Property tests (hypothesis): malformed mesh input loads cleanly or is refused cleanly.

Mesh files (OBJ text cut at a random point, with garbage lines, NaN or infinite numbers,
face indices changed at random; ASCII PLY likewise) and the mesh part of scene-file dicts
(inline vertices, faces and normals of any JSON type and shape, paths to missing,
malformed or folder targets, built-in shapes with any arguments) either give a Mesh whose
vertices and normals are finite and whose faces index its vertices, or raise ValueError
(SceneFileError is one) or FileNotFoundError: never another exception type, never a
crash in a compiled kernel further on.
"""

import re

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import diffshade as ds

PROPERTY_SETTINGS = settings(max_examples=80, deadline=None, derandomize=True, database=None,
                             suppress_health_check=[HealthCheck.too_slow])
CLEAN_ERRORS = (ValueError, FileNotFoundError)
CAMERA = {"eye": [0, 0, 3], "target": [0, 0, 0], "width": 8, "height": 8}

OBJ = ("# a square pyramid\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0.5 0.5 1\n"
       "f 1 3 2\nf 1 4 3\nf 1 2 5\nf 2 3 5\nf 3 4 5\nf 4 1 5\n")
PLY = ("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
       "property float z\nelement face 2\nproperty list uchar int vertex_indices\n"
       "end_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n3 0 1 2\n3 0 2 3\n")


def assert_valid(mesh):
    """The loaded mesh can be rendered: finite floats, faces inside [0, V)."""
    vertices, normals = np.asarray(mesh.vertices), np.asarray(mesh.normals)
    faces = np.asarray(mesh.faces)
    assert np.all(np.isfinite(vertices)) and np.all(np.isfinite(normals))
    assert vertices.shape == normals.shape and vertices.shape[1:] == (3,)
    assert faces.ndim == 2 and faces.shape[1] == 3 and len(faces) >= 1
    assert faces.min() >= 0 and faces.max() < len(vertices)


def load_or_refuse(load, *args):
    """Run load(*args): a valid mesh or a clean error; anything else fails the test."""
    try:
        mesh = load(*args)
    except CLEAN_ERRORS:
        return
    assert_valid(mesh.mesh if isinstance(mesh, ds.Scene) else mesh)


# ---------------------------------------------------------------------- mesh files

number_token = st.one_of(
    st.sampled_from(["nan", "-nan", "inf", "-inf", "1e999", "1e39", "-0", "", "x", "1/2",
                     "0x10", "1,5"]),
    st.floats(allow_nan=False, allow_infinity=False, width=32).map(repr),
    st.integers(-12, 12).map(str),
)
garbage_line = st.lists(st.one_of(st.sampled_from(["v", "f", "vn", "vt", "#", "o", "g", "/",
                                                   "//", "\t"]), number_token),
                        max_size=6).map(" ".join)


@st.composite
def mutated_text(draw, text):
    """text with its tokens changed, lines inserted or dropped, and its end cut off."""
    lines = text.splitlines()
    for _ in range(draw(st.integers(0, 4))):
        i = draw(st.integers(0, len(lines) - 1))
        kind = draw(st.sampled_from(["token", "insert", "drop"]))
        tokens = lines[i].split()
        if kind == "token" and tokens:
            tokens[draw(st.integers(0, len(tokens) - 1))] = draw(number_token)
            lines[i] = " ".join(tokens)
        elif kind == "insert":
            lines.insert(i, draw(garbage_line))
        elif len(lines) > 1:
            del lines[i]
    joined = "\n".join(lines) + "\n"
    return joined[: draw(st.integers(0, len(joined)))] if draw(st.booleans()) else joined


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    return tmp_path_factory.mktemp("malformed")


@PROPERTY_SETTINGS
@given(data=st.data())
@pytest.mark.parametrize("suffix,text", [(".obj", OBJ), (".ply", PLY)])
def test_malformed_mesh_file_loads_or_raises_a_clean_error(folder, suffix, text, data):
    path = folder / f"mesh{suffix}"
    path.write_text(data.draw(mutated_text(text)))
    load_or_refuse(ds.load_mesh, path)


@pytest.mark.parametrize("keep", range(1, 7))
def test_obj_cut_inside_its_last_face_is_refused(folder, keep):
    """Each cut of the last line, "f 4 1 5", that leaves fewer than 3 vertex references
    ("f", "f ", "f 4", ..., "f 4 1 ") is refused naming line 12, never dropped silently."""
    text = OBJ[: len(OBJ) - 8 + keep]
    path = folder / f"cut{keep}.obj"
    path.write_text(text)
    last = text.splitlines()[-1].strip()
    with pytest.raises(ValueError, match=re.escape(f"line 12: {last!r}")):
        ds.load_mesh(path)
    path.write_text(OBJ[:-1])  # only the newline cut: the whole face is still there
    assert len(ds.load_mesh(path).faces) == 6


# ---------------------------------------------------------------- scene-file meshes

json_scalar = st.one_of(st.none(), st.booleans(), st.integers(-10, 10),
                        st.floats(allow_nan=True, allow_infinity=True),
                        st.sampled_from(["1", "nan", "", "x"]))
json_value = st.recursive(json_scalar, lambda inner: st.lists(inner, max_size=4), max_leaves=8)
bad_number = st.sampled_from([float("nan"), float("inf"), float("-inf"), 1e39, -1e300, 1e30])
coordinate = st.one_of(st.floats(-2, 2), st.integers(-2, 2))
row = st.lists(coordinate, min_size=3, max_size=3)


@st.composite
def corrupt(draw, rows, bad_values):
    """rows (a list of lists) with up to 2 faults: a value replaced by one of bad_values,
    a row cut short or made longer, a row dropped."""
    rows = [list(r) for r in rows]
    for _ in range(draw(st.sampled_from([0, 0, 1, 2]))):
        i = draw(st.integers(0, max(len(rows) - 1, 0)))
        fault = draw(st.sampled_from(["value", "value", "short", "long", "drop"]))
        if not rows:
            break
        if fault == "value":
            rows[i][draw(st.integers(0, len(rows[i]) - 1))] = draw(bad_values)
        elif fault == "short" and rows[i]:
            rows[i].pop()
        elif fault == "long":
            rows[i].append(0)
        elif fault == "drop":
            del rows[i]
    return rows


@st.composite
def inline_mesh(draw):
    """(vertices, faces, normals or None): a valid inline mesh, faults drawn into each."""
    count = draw(st.integers(3, 6))
    vertices = draw(st.lists(row, min_size=count, max_size=count))
    faces = draw(st.lists(st.lists(st.integers(0, count - 1), min_size=3, max_size=3),
                          min_size=1, max_size=5))
    bad_index = st.one_of(st.integers(-3, count + 3), st.sampled_from([2**31, 10**20, 1.5]),
                          json_scalar)
    normals = draw(st.one_of(st.none(), st.just(vertices)))
    return (draw(corrupt(vertices, st.one_of(bad_number, json_scalar))),
            draw(corrupt(faces, bad_index)),
            None if normals is None else draw(corrupt(normals, st.one_of(bad_number,
                                                                           json_scalar))))


small_int = st.one_of(st.integers(-2, 40), st.sampled_from([10**9, 2**16 + 1]), json_scalar)
builtin = st.one_of(
    st.fixed_dictionaries({}, optional={"subdivisions": st.one_of(st.integers(-2, 2), st.just(9),
                                                                   json_scalar),
                                        "radius": st.one_of(coordinate, bad_number)}).map(
        lambda d: {"icosphere": d}),
    st.fixed_dictionaries({}, optional={"major_radius": st.one_of(coordinate, bad_number),
                                        "minor_radius": st.one_of(coordinate, json_scalar),
                                        "major_segments": small_int,
                                        "minor_segments": small_int}).map(lambda d: {"torus": d}),
    st.fixed_dictionaries({}, optional={"size": st.one_of(row, json_value)}).map(
        lambda d: {"box": d}),
    st.dictionaries(st.sampled_from(["icosphere", "cube", "box"]), json_value, max_size=2),
)
normal_options = st.fixed_dictionaries(
    {}, optional={"weighting": st.sampled_from(["angle", "area", "uniform", "cotan", 1]),
                  "crease_angle": st.one_of(st.floats(-10, 200), json_scalar)})
normals = st.one_of(normal_options, json_value)
path = st.one_of(st.sampled_from(["good.obj", "bad.obj", "nan.obj", "missing.obj", ".", "sub",
                                  ""]), json_scalar)
mesh_part = st.one_of(
    inline_mesh().map(lambda m: {"vertices": m[0], "faces": m[1], "normals": m[2] or {}}),
    st.fixed_dictionaries({"path": path}, optional={"normals": normals}),
    st.fixed_dictionaries({"builtin": st.one_of(builtin, json_value)},
                          optional={"normals": normals}),
    # anything: several sources, none, unknown keys, wrong types
    st.fixed_dictionaries({}, optional={"vertices": json_value, "faces": json_value,
                                        "normals": json_value, "path": path,
                                        "builtin": builtin, "colour": json_value}),
)


@pytest.fixture(scope="module")
def scene_folder(tmp_path_factory):
    root = tmp_path_factory.mktemp("scenes")
    (root / "good.obj").write_text(OBJ)
    (root / "bad.obj").write_text(OBJ + "f 1 2\n")
    (root / "nan.obj").write_text(OBJ.replace("v 1 1 0", "v 1 nan 0"))
    (root / "sub").mkdir()
    return root


@PROPERTY_SETTINGS
@given(mesh=mesh_part)
def test_malformed_scene_mesh_loads_or_raises_a_clean_error(scene_folder, mesh):
    load_or_refuse(lambda: ds.scene_from_dict({"mesh": mesh, "camera": CAMERA}, scene_folder)[0])


@PROPERTY_SETTINGS
@given(mesh=inline_mesh())
def test_inline_rows_load_or_raise_a_clean_error(mesh):
    """The common case drawn densely: rows of numbers with the odd bad value or index,
    through mesh_from_arrays directly and through a scene file."""
    vertices, faces, normals = mesh
    load_or_refuse(ds.mesh_from_arrays, vertices, faces, normals)
    part = {"vertices": vertices, "faces": faces, **({} if normals is None else
                                                     {"normals": normals})}
    load_or_refuse(lambda: ds.scene_from_dict({"mesh": part, "camera": CAMERA})[0])

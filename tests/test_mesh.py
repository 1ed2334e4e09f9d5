"""Tests for diffshade.scene.mesh against independent references: closed forms, hand-computed
weighted sums, numpy re-derivations and trimesh's own primitives and file formats."""

import math
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from jax.test_util import check_grads

from diffshade.scene.mesh import (
    Mesh,
    box,
    face_areas,
    face_normals,
    icosphere,
    load_mesh,
    mesh_from_arrays,
    mesh_from_trimesh,
    model_matrix,
    torus,
    transform_mesh,
    vertex_normals,
)
from diffshade.scene.transform import inverse_transpose


def np_face_normals(vertices, faces):
    tri = np.asarray(vertices, np.float64)[np.asarray(faces)]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return cross / np.linalg.norm(cross, axis=1, keepdims=True)


def directed_edges(faces):
    faces = np.asarray(faces)
    return [
        tuple(e) for e in np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    ]


def assert_watertight_and_consistent(faces):
    """Every edge has exactly two faces, traversing it in opposite directions."""
    edges = directed_edges(faces)
    unique = set(edges)
    assert len(unique) == len(edges)
    assert all((b, a) in unique for a, b in edges)


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


def angle_deg(a, b):
    a, b = unit(a), unit(b)
    return math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), np.dot(a, b)))


# --- primitives ---------------------------------------------------------------------------


@pytest.mark.parametrize("s", range(5))
def test_icosphere_topology_and_geometry(s):
    mesh = icosphere(s, radius=2.0)
    v, f, n = np.asarray(mesh.vertices), np.asarray(mesh.faces), np.asarray(mesh.normals)
    assert f.shape == (20 * 4**s, 3) and v.shape == (10 * 4**s + 2, 3)
    assert mesh.vertices.dtype == jnp.float32 and mesh.faces.dtype == jnp.int32
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 2.0, rtol=1e-6)
    num_edges = len(directed_edges(f)) // 2
    assert len(v) - num_edges + len(f) == 2
    assert_watertight_and_consistent(f)
    centroids = v[f].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", np_face_normals(v, f), centroids) > 0)
    np.testing.assert_allclose(n, v / 2.0, atol=1e-6)


def test_icosphere_face_count_at_level_5():
    assert icosphere(5).faces.shape == (20480, 3)


@pytest.mark.parametrize("bad", [-1, 9, 2.0, True, "3"])
def test_icosphere_rejects_bad_subdivisions(bad):
    with pytest.raises(ValueError, match="subdivisions"):
        icosphere(bad)


def test_torus_is_watertight_outward_with_analytic_normals():
    major, minor = 1.5, 0.5
    mesh = torus(major, minor, major_segments=12, minor_segments=8)
    v, f, n = np.asarray(mesh.vertices), np.asarray(mesh.faces), np.asarray(mesh.normals)
    assert v.shape == (96, 3) and f.shape == (192, 3)
    assert_watertight_and_consistent(f)
    assert len(v) - len(directed_edges(f)) // 2 + len(f) == 0  # genus 1
    ring = major * v * np.array([1.0, 0.0, 1.0]) / np.linalg.norm(v[:, [0, 2]], axis=1)[:, None]
    np.testing.assert_allclose(np.linalg.norm(v - ring, axis=1), minor, rtol=1e-5)
    np.testing.assert_allclose(n, (v - ring) / minor, atol=1e-5)
    outward = n[f].sum(axis=1)
    assert np.all(np.einsum("ij,ij->i", np_face_normals(v, f), outward) > 0)


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"minor_radius": 1.0}, "minor_radius"),
        ({"major_radius": -1.0}, "major_radius"),
        ({"major_segments": 2}, "major_segments"),
        ({"minor_segments": 3.5}, "minor_segments"),
    ],
)
def test_torus_rejects_bad_arguments(kwargs, name):
    with pytest.raises(ValueError, match=name):
        torus(**kwargs)


def test_box_has_flat_outward_sides():
    mesh = box((2.0, 4.0, 6.0))
    v, f, n = np.asarray(mesh.vertices), np.asarray(mesh.faces), np.asarray(mesh.normals)
    assert v.shape == (24, 3) and f.shape == (12, 3)
    np.testing.assert_allclose(np.abs(v), np.broadcast_to([1.0, 2.0, 3.0], v.shape))
    face_n = np_face_normals(v, f)
    np.testing.assert_allclose(n[f], np.repeat(face_n[:, None], 3, axis=1), atol=1e-6)
    assert np.all(np.einsum("ij,ij->i", face_n, v[f].mean(axis=1)) > 0)
    assert sorted(map(tuple, np.unique(n, axis=0))) == sorted(
        map(tuple, np.concatenate([np.eye(3), -np.eye(3)]))
    )
    with pytest.raises(ValueError, match="size"):
        box((1.0, 0.0, 1.0))


# --- normals ------------------------------------------------------------------------------


@pytest.mark.parametrize("weighting", ["angle", "area"])
def test_vertex_normals_on_sphere_are_radial(weighting):
    mesh = icosphere(3)
    normals = np.asarray(vertex_normals(mesh.vertices, mesh.faces, weighting))
    radial = np.asarray(mesh.vertices)
    cos = np.einsum("ij,ij->i", normals, radial)
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 2.0


# A tent: face A = (p0, p1, p2) in the z = 0 plane, face B = (p1, p0, p3) folded up along
# the shared edge p0-p1. nA = (0, 0, 1) with area 1; nB = (0, 1, 1)/sqrt 2 with area sqrt 2.
TENT_VERTICES = np.array([[0, 0, 0], [2, 0, 0], [0, 1, 0], [0, -1, 1], [5, 5, 5]], np.float32)
TENT_FACES = np.array([[0, 1, 2], [1, 0, 3]], np.int32)
N_A = np.array([0.0, 0.0, 1.0])
N_B = np.array([0.0, 1.0, 1.0]) / math.sqrt(2)
ANGLE_A_AT_P1 = math.atan(0.5)  # between (-2, 1, 0) and (-2, 0, 0)
ANGLE_B_AT_P1 = math.acos(2 / math.sqrt(6))  # between (-2, 0, 0) and (-2, -1, 1)
TENT_EXPECTED = {
    "angle": [unit(N_A + N_B), unit(ANGLE_A_AT_P1 * N_A + ANGLE_B_AT_P1 * N_B)],
    "area": [unit(N_A + math.sqrt(2) * N_B)] * 2,
    "uniform": [unit(N_A + N_B)] * 2,
}


@pytest.mark.parametrize("weighting", ["angle", "area", "uniform"])
def test_vertex_normals_on_tent_match_hand_weighted_sum(weighting):
    normals = np.asarray(vertex_normals(jnp.asarray(TENT_VERTICES), TENT_FACES, weighting))
    expected = TENT_EXPECTED[weighting] + [N_A, N_B, np.zeros(3)]  # p4 is used by no face
    np.testing.assert_allclose(normals, expected, atol=1e-6)
    jitted = jax.jit(vertex_normals, static_argnames="weighting")
    np.testing.assert_allclose(jitted(TENT_VERTICES, TENT_FACES, weighting), normals, atol=1e-6)


@pytest.mark.parametrize("weighting", ["angle", "area", "uniform"])
def test_vertex_normal_gradients_are_finite_for_unused_and_cancelling(weighting):
    # Faces 0 and 1 are the same triangle wound both ways, so their normals cancel.
    faces = np.array([[0, 1, 2], [0, 2, 1]], np.int32)
    verts = jnp.asarray(TENT_VERTICES)
    normals = vertex_normals(verts, faces, weighting)
    assert np.all(np.isfinite(normals)) and np.allclose(normals, 0.0, atol=1e-6)
    grad = jax.grad(lambda v: vertex_normals(v, faces, weighting).sum())(verts)
    assert np.all(np.isfinite(grad))
    grad = jax.grad(lambda v: vertex_normals(v, TENT_FACES, weighting).sum())(verts)
    assert np.all(np.isfinite(grad)) and np.all(grad[4] == 0)


@pytest.mark.parametrize("weighting", ["angle", "area", "uniform"])
def test_vertex_normal_gradients_match_finite_differences(weighting):
    with jax.enable_x64(True):
        verts = jnp.asarray(TENT_VERTICES[:4], jnp.float64)
        fn = lambda v: vertex_normals(v, TENT_FACES, weighting)  # noqa: E731
        check_grads(fn, (verts,), order=1, modes=["rev"], eps=1e-6, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize(
    "triangle",
    [[[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 0, 0], [0, 0, 0], [1, 1, 0]], [[1, 2, 3]] * 3],
    ids=["collinear", "repeated-vertex", "single-point"],
)
def test_degenerate_face_has_zero_normal_and_finite_gradient(triangle):
    verts, faces = jnp.asarray(triangle, jnp.float32), np.array([[0, 1, 2]])
    np.testing.assert_array_equal(face_normals(verts, faces), 0.0)
    np.testing.assert_array_equal(face_areas(verts, faces), 0.0)
    for fn in (face_normals, face_areas, vertex_normals):
        grad = jax.grad(lambda v, fn=fn: fn(v, faces).sum())(verts)
        assert np.all(np.isfinite(grad))


def test_face_normals_and_areas_of_tent():
    verts = jnp.asarray(TENT_VERTICES)
    np.testing.assert_allclose(face_normals(verts, TENT_FACES), [N_A, N_B], atol=1e-6)
    np.testing.assert_allclose(face_areas(verts, TENT_FACES), [1.0, math.sqrt(2)], rtol=1e-6)


# --- crease splitting ---------------------------------------------------------------------


def shared_corner_cube():
    cube = trimesh.creation.box()  # 8 shared corners of [-0.5, 0.5]^3, 12 faces
    assert len(cube.vertices) == 8
    return np.asarray(cube.vertices), np.asarray(cube.faces)


def test_crease_splits_cube_into_flat_sides():
    verts, faces = shared_corner_cube()
    mesh = mesh_from_arrays(verts, faces, crease_angle=30)
    v, f, n = np.asarray(mesh.vertices), np.asarray(mesh.faces), np.asarray(mesh.normals)
    assert v.shape == (24, 3) and f.shape == (12, 3)
    np.testing.assert_allclose(np.sort(np.abs(n), axis=1), [[0, 0, 1]] * 24, atol=1e-6)
    face_n = np_face_normals(v, f)
    np.testing.assert_allclose(n[f], np.repeat(face_n[:, None], 3, axis=1), atol=1e-6)
    np.testing.assert_allclose(v[f], verts[faces])  # split copies keep their positions


def test_crease_with_sparse_indices_drops_unused_vertices():
    verts, faces = shared_corner_cube()
    # Side diagonals 0-40 and 1-4: a hash of an edge by 36 (the corner count) would mix them.
    rows = np.array([0, 1, 41, 40, 4, 42, 43, 44])
    sparse = np.full((50, 3), 9.0)
    sparse[rows] = verts
    mesh = mesh_from_arrays(sparse, rows[faces], crease_angle=30)
    assert mesh.vertices.shape == (24, 3)
    np.testing.assert_allclose(np.sort(np.abs(mesh.normals), axis=1), [[0, 0, 1]] * 24, atol=1e-6)


def test_smooth_cube_corners_get_diagonal_normals():
    verts, faces = shared_corner_cube()
    mesh = mesh_from_arrays(verts, faces)
    assert mesh.vertices.shape == (8, 3)
    # Angle weighting sees 90 degrees of each side at every corner, however it is split.
    np.testing.assert_allclose(mesh.normals, np.sign(verts) / math.sqrt(3), atol=1e-6)


def test_crease_keeps_icosahedron_whole_below_its_edge_angle():
    smooth = mesh_from_arrays(icosphere(0).vertices, icosphere(0).faces, crease_angle=60)
    assert smooth.vertices.shape == (12, 3)
    np.testing.assert_allclose(smooth.normals, icosphere(0).normals, atol=1e-6)
    faceted = mesh_from_arrays(icosphere(0).vertices, icosphere(0).faces, crease_angle=30)
    v, f = np.asarray(faceted.vertices), np.asarray(faceted.faces)
    assert v.shape == (60, 3)
    np.testing.assert_allclose(
        np.asarray(faceted.normals)[f[:, 0]], np_face_normals(v, f), atol=1e-6
    )


def test_crease_zero_keeps_flat_regions_whole():
    grid = trimesh.creation.box().subdivide()  # coplanar triangles on each side
    mesh = mesh_from_trimesh(grid, crease_angle=0)
    expected = sum(len(np.unique(np.asarray(grid.faces)[side])) for side in _sides(grid))
    assert mesh.vertices.shape == (expected, 3)


def _sides(tm):
    normals = np.round(tm.face_normals).astype(int)
    return [np.all(normals == n, axis=1) for n in np.unique(normals, axis=0)]


# --- transforms ---------------------------------------------------------------------------


def test_transform_uses_inverse_transpose_for_normals():
    # The plane x + y = 0, spanned by tangents (1, -1, 0) and (0, 0, 1).
    tangents = np.array([[1.0, -1.0, 0.0], [0.0, 0.0, 1.0]])
    verts = np.array([[0, 0, 0], tangents[0], tangents[1]])
    normal = np.array([1.0, 1.0, 0.0]) / math.sqrt(2)
    mesh = mesh_from_arrays(verts, [[0, 1, 2]], normals=np.tile(normal, (3, 1)))
    scale = np.diag([2.0, 1.0, 1.0, 1.0])
    moved = transform_mesh(mesh, scale)
    np.testing.assert_allclose(moved.normals, np.tile(unit([0.5, 1.0, 0.0]), (3, 1)), atol=1e-6)
    np.testing.assert_allclose(moved.normals @ (tangents @ scale[:3, :3].T).T, 0.0, atol=1e-6)
    np.testing.assert_allclose(moved.vertices, verts @ scale[:3, :3].T, atol=1e-6)


def test_transform_matches_numpy_homogeneous_reference():
    mesh = torus(major_segments=8, minor_segments=6)
    matrix = model_matrix((1.0, -2.0, 0.5), (30.0, -45.0, 60.0), (1.0, 2.0, 0.5))
    moved = transform_mesh(mesh, matrix)
    homog = np.concatenate([np.asarray(mesh.vertices), np.ones((len(mesh.vertices), 1))], 1)
    np.testing.assert_allclose(moved.vertices, (homog @ matrix.T)[:, :3], atol=1e-5)
    inv_t = np.linalg.inv(matrix[:3, :3].astype(np.float64)).T
    expected = np.asarray(mesh.normals) @ inv_t.T
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    np.testing.assert_allclose(moved.normals, expected, atol=1e-5)


@pytest.mark.usefixtures("x64")
@pytest.mark.parametrize("seed", range(4))
def test_inverse_transpose_matches_numpy(seed):
    """The closed form (cofactors over the determinant) against LAPACK's inverse, float64,
    for a general matrix, a mirror (negative determinant) and a badly scaled one."""
    block = np.random.default_rng(seed).normal(size=(3, 3))
    for matrix in (block, block @ np.diag([-1.0, 1.0, 1.0]), block * [1e-3, 1.0, 1e3]):
        got = np.asarray(inverse_transpose(jnp.asarray(matrix)))
        np.testing.assert_allclose(got, np.linalg.inv(matrix).T, rtol=1e-12,
                                   atol=1e-12 * np.abs(np.linalg.inv(matrix)).max())


def test_transform_gradients_are_finite_even_for_singular_matrix():
    mesh = icosphere(1)
    loss = lambda m: jnp.sum(transform_mesh(mesh, m).normals * jnp.array([1.0, 2.0, 3.0]))  # noqa: E731
    for matrix in (model_matrix(rotate_deg=(10.0, 20.0, 30.0)), np.diag([1.0, 0.0, 1.0, 1.0])):
        assert np.all(np.isfinite(jax.grad(loss)(jnp.asarray(matrix, jnp.float32))))


def test_model_matrix_order_is_scale_rotate_x_y_z_translate():
    point = np.array([0.0, 1.0, 0.0, 1.0])
    # X by 90 sends y to z, then Y by 90 sends z to x; the other order would give z.
    np.testing.assert_allclose(
        model_matrix(rotate_deg=(90, 90, 0)) @ point, [1, 0, 0, 1], atol=1e-6
    )
    matrix = model_matrix(translate=(1, 2, 3), rotate_deg=(0, 0, 90), scale=(2, 3, 4))
    assert matrix.dtype == np.float32
    np.testing.assert_allclose(matrix @ [1.0, 1.0, 1.0, 1.0], [-2, 4, 7, 1], atol=1e-6)


# --- construction and files ---------------------------------------------------------------


def test_mesh_is_a_pytree_and_jits():
    mesh = box()
    leaves = jax.tree_util.tree_leaves(mesh)
    assert len(leaves) == 3
    doubled = jax.jit(lambda m: Mesh(m.vertices * 2, m.faces, m.normals))(mesh)
    np.testing.assert_allclose(doubled.vertices, 2 * np.asarray(mesh.vertices))


def test_mesh_from_arrays_converts_and_normalizes():
    mesh = mesh_from_arrays(TENT_VERTICES.astype(np.float64), TENT_FACES.astype(np.float64))
    assert mesh.vertices.dtype == jnp.float32 and mesh.faces.dtype == jnp.int32
    given = mesh_from_arrays(TENT_VERTICES, TENT_FACES, normals=np.tile([0.0, 0.0, 3.0], (5, 1)))
    np.testing.assert_allclose(given.normals, np.tile([0.0, 0.0, 1.0], (5, 1)))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"vertices": [[0, 0, 0], [1, np.nan, 0], [0, 1, 0]]}, "vertices: row 1"),
        ({"vertices": np.zeros((3, 2))}, "vertices: shape"),
        ({"faces": [[0, 1, 3]]}, "faces: index 3 out of range for 3 vertices"),
        ({"faces": [[0, -1, 2]]}, "faces: index -1"),
        ({"faces": [[0, 1.5, 2]]}, "faces: value 1.5"),
        ({"faces": np.zeros((0, 3), int)}, "faces: shape"),
        ({"faces": [[0, 1]]}, "faces: shape"),
        ({"normals": np.zeros((2, 3))}, "normals: shape"),
        ({"normals": [[0, 0, 1], [0, 0, 1], [0, 0, np.inf]]}, "normals: row 2"),
        ({"weighting": "cotan"}, "weighting: 'cotan'; expected one of"),
        ({"crease_angle": 200}, "crease_angle: 200"),
    ],
)
def test_mesh_from_arrays_names_bad_argument(kwargs, message):
    args = {"vertices": np.eye(3), "faces": [[0, 1, 2]]} | kwargs
    with pytest.raises(ValueError, match=re.escape(message)):
        mesh_from_arrays(**args)


@pytest.mark.parametrize("ext", ["obj", "ply", "stl", "glb"])
def test_load_mesh_roundtrip(tmp_path, ext):
    sphere = trimesh.creation.icosphere(subdivisions=2)
    path = tmp_path / f"sphere.{ext}"
    sphere.export(path)
    mesh = load_mesh(path)
    assert mesh.vertices.shape == (162, 3) and mesh.faces.shape == (320, 3)  # STL merged
    cos = np.einsum("ij,ij->i", np.asarray(mesh.normals), unit_rows(mesh.vertices))
    assert cos.min() > math.cos(math.radians(3.0))


def unit_rows(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def test_load_mesh_errors(tmp_path):
    missing = tmp_path / "nope.obj"
    with pytest.raises(FileNotFoundError, match="mesh file not found"):
        load_mesh(missing)
    for name, content in [
        ("garbage.obj", b"this is not a mesh\n"),
        ("garbage.stl", b"\x00\xff" * 7),
    ]:
        (tmp_path / name).write_bytes(content)
        with pytest.raises(ValueError, match=name):
            load_mesh(tmp_path / name)


def test_mesh_from_trimesh_scene_and_type_error():
    scene = trimesh.Scene([trimesh.creation.box(), trimesh.creation.icosphere(subdivisions=1)])
    assert mesh_from_trimesh(scene).faces.shape == (12 + 80, 3)
    with pytest.raises(TypeError, match="tm: ndarray"):
        mesh_from_trimesh(np.zeros((3, 3)))

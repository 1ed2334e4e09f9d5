"""Rasterization against the naive per-pixel reference rasterizer (tests/reference.py) and
closed forms: face ids, coverage, perspective-correct barycentrics and depth, near-plane
clipping, back-face culling, the pixel-centre convention and perspective-correct
interpolation (all in float64)."""

import jax
import numpy as np
import pytest
import reference
from reference import RefCamera

from diffshade import (
    RenderSettings,
    icosphere,
    interpolate,
    look_at,
    make_scene,
    model_matrix,
    project,
    rasterize_scene,
    render,
)

pytestmark = pytest.mark.usefixtures("x64")

EDGE_TOL = 1e-6  # pixels: face ids may differ only this close to an edge (or clip line)
HARD = RenderSettings()

# jitted once per scene structure: far cheaper than running the pipeline op by op
rasterize = jax.jit(rasterize_scene, static_argnames="settings")


@jax.jit
def fragment_points(scene):
    """World position of each pixel's nearest fragment: [H, W, 3], and face ids [H, W]."""
    frags = rasterize_scene(scene)
    points = interpolate(project(scene).world, scene.mesh.faces, frags)
    return points[..., 0, :], frags.face_ids[..., 0]


def naive(scene, cull_backfaces=False):
    world, _ = reference.world_geometry(scene)
    return reference.rasterize(RefCamera.of(scene.camera), world, np.asarray(scene.mesh.faces),
                               cull_backfaces)


def assert_matches_naive(scene, settings=HARD):
    """Compare rasterize_scene with the naive rasterizer; returns (ids [H, W], naive)."""
    frags = rasterize(scene, settings)
    ref = naive(scene, settings.cull_backfaces)
    ids = np.asarray(frags.face_ids[..., 0])
    clear = ref.edge_dist > EDGE_TOL
    assert clear.mean() > 0.9, "the scene should not put most pixel centres on edges"
    np.testing.assert_array_equal(ids[clear], ref.face_ids[clear])
    same = clear & (ref.face_ids >= 0)
    np.testing.assert_allclose(np.asarray(frags.bary[..., 0, :])[same], ref.bary[same],
                               atol=1e-9)
    np.testing.assert_allclose(np.asarray(frags.depth[..., 0])[same], ref.depth[same],
                               rtol=1e-9)
    np.testing.assert_array_equal(np.asarray(frags.front[..., 0])[same], ref.front[same])
    return ids, ref


def overlap_scene(mesh, size=24):
    """Four triangles: two interpenetrating, a small back-facing one in front of them and
    one running off the right of the image."""
    verts = [[-1.5, -1.2, -0.8], [1.4, -1.0, -0.2], [0.0, 1.5, -0.5],     # front, tilted
             [-1.0, 0.8, 0.3], [-0.2, -1.3, -1.2], [1.2, 0.6, 0.0],       # cuts through it
             [-0.3, -0.3, 1.0], [0.2, 0.5, 1.0], [0.5, -0.2, 1.0],        # clockwise, near
             [0.8, -0.5, 0.2], [3.0, 0.0, 0.2], [0.9, 0.7, 0.2]]          # off the right
    faces = [[0, 1, 2], [3, 4, 5], [6, 7, 8], [9, 10, 11]]
    cam = look_at((0.3, 0.2, 4.0), (0.0, 0.0, 0.0), width=size, height=size, fov_y=40.0)
    return make_scene(mesh(verts, faces, np.tile([0.0, 0.0, 1.0], (12, 1))), cam)


def sphere_scene(size=24):
    cam = look_at((0.4, 0.6, 3.5), (0.0, 0.0, 0.0), width=size, height=size - 4, fov_y=45.0)
    model = model_matrix((0.1, -0.1, 0.0), (20.0, 30.0, 10.0), (1.2, 0.8, 1.0))
    return make_scene(icosphere(1), cam, model=model)


def test_overlapping_triangles_match_the_naive_rasterizer(mesh):
    ids, ref = assert_matches_naive(overlap_scene(mesh))
    visible = set(np.unique(ids)) - {-1}
    assert visible == {0, 1, 2, 3}
    assert not ref.front[ids == 2].any() and ref.front[ids == 0].all()
    assert (ids == -1).sum() > 20


def test_culling_removes_back_faces_and_uncovers_what_they_hid(mesh):
    scene = overlap_scene(mesh)
    ids, _ = assert_matches_naive(scene, RenderSettings(cull_backfaces=True))
    kept, _ = assert_matches_naive(scene, RenderSettings(cull_backfaces=False))
    assert 2 not in ids
    hidden = kept == 2
    assert hidden.any() and np.all(np.isin(ids[hidden], [0, 1]))


def test_icosphere_matches_the_naive_rasterizer():
    ids, ref = assert_matches_naive(sphere_scene())
    assert len(np.unique(ids)) > 20 and ref.front[ids >= 0].all()


def test_culling_a_single_back_face(mesh):
    cam = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=16, height=16)
    verts = [[-1.0, -1.0, 0.0], [0.0, 1.0, 0.0], [1.0, -1.0, 0.0]]  # clockwise on screen
    scene = make_scene(mesh(verts, [[0, 1, 2]]), cam)
    culled = np.asarray(render(scene, RenderSettings(cull_backfaces=True)))[..., 3]
    kept = np.asarray(render(scene, RenderSettings(cull_backfaces=False)))[..., 3]
    assert culled.sum() == 0 and kept.sum() > 20


# ------------------------------------------------------------------------- near plane


def near_scene(mesh, verts):
    """Camera at the origin looking down -z with near = 1."""
    cam = look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), width=24, height=24, fov_y=60.0,
                  near=1.0, far=10.0)
    return make_scene(mesh(verts, [[0, 1, 2]]), cam)


def test_triangle_crossing_the_near_plane_keeps_its_visible_part(mesh):
    # one corner between the eye and the near plane: clipped per pixel at depth 1
    scene = near_scene(mesh, [[-0.2, -0.2, -0.5], [1.5, -1.0, -3.0], [0.0, 1.5, -2.5]])
    ids, ref = assert_matches_naive(scene)
    unclipped = naive(make_scene(scene.mesh, look_at(
        (0.0, 0.0, 0.0), (0.0, 0.0, -1.0), width=24, height=24, fov_y=60.0, near=0.01)))
    assert 20 < (ids == 0).sum() < (unclipped.face_ids == 0).sum() - 20


def test_triangle_with_a_corner_behind_the_eye_keeps_its_visible_part(mesh):
    scene = near_scene(mesh, [[-0.5, -0.8, 1.0], [1.5, -1.0, -3.0], [0.0, 1.5, -2.5]])
    ids, _ = assert_matches_naive(scene)
    assert 20 < (ids == 0).sum() < ids.size


def test_triangle_crossing_the_far_plane_is_clipped_there(mesh):
    verts = [[-1.5, -1.0, -2.0], [1.5, -1.0, -12.0], [0.0, 1.5, -6.0]]
    cam = look_at((0.0, 0.0, 0.0), (0.0, 0.0, -1.0), width=24, height=24, fov_y=60.0,
                  near=1.0, far=5.0)
    ids, _ = assert_matches_naive(make_scene(mesh(verts, [[0, 1, 2]]), cam))
    unclipped = naive(make_scene(mesh(verts, [[0, 1, 2]]), look_at(
        (0.0, 0.0, 0.0), (0.0, 0.0, -1.0), width=24, height=24, fov_y=60.0, far=100.0)))
    assert 20 < (ids == 0).sum() < (unclipped.face_ids == 0).sum() - 10


@pytest.mark.parametrize("z", [0.5, -0.5], ids=["behind_eye", "before_near"])
def test_triangle_entirely_behind_the_near_plane_renders_nothing(mesh, z):
    scene = near_scene(mesh, [[-1.0, -1.0, z], [1.0, -1.0, z], [0.0, 1.0, z]])
    np.testing.assert_array_equal(np.asarray(render(scene))[..., 3], 0.0)
    np.testing.assert_array_equal(naive(scene).face_ids, -1)


# ------------------------------------------------------------- pixel-centre convention


def half_plane_alpha(mesh, verts):
    cam = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=16, height=16)
    return np.asarray(render(make_scene(mesh(verts, [[0, 1, 2]]), cam)))[..., 3]


def test_edge_between_pixel_columns_splits_the_image_exactly(mesh):
    # the edge x = 0 projects to NDC x = 0, the boundary between columns 7 and 8
    alpha = half_plane_alpha(mesh, [[0.0, -10.0, 0.0], [0.0, 10.0, 0.0], [-10.0, 0.0, 0.0]])
    expected = np.zeros((16, 16))
    expected[:, :8] = 1.0
    np.testing.assert_array_equal(alpha, expected)


def test_row_zero_is_the_top_of_the_image(mesh):
    # a triangle covering y > 0 fills exactly the upper half of the rows
    alpha = half_plane_alpha(mesh, [[-10.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0]])
    expected = np.zeros((16, 16))
    expected[:8] = 1.0
    np.testing.assert_array_equal(alpha, expected)


# ---------------------------------------------------------- perspective-correct values


def screen_bary(cam, world_tri, row, col):
    """Affine (screen-space) barycentrics of the pixel centre in the projected triangle."""
    clip = np.concatenate([world_tri, np.ones((3, 1))], 1) @ (cam.proj @ cam.view).T
    ndc = clip[:, :2] / clip[:, 3:]
    x, y = cam.pixel_ndc(row, col)
    mat = np.stack([ndc[1] - ndc[0], ndc[2] - ndc[0]], 1)
    b1, b2 = np.linalg.solve(mat, np.array([x, y]) - ndc[0])
    return np.array([1.0 - b1 - b2, b1, b2])


def test_interpolation_is_perspective_correct_on_a_receding_floor(mesh):
    verts = [[-2.0, 0.0, -1.0], [2.0, 0.0, -1.0], [2.0, 0.0, -30.0], [-2.0, 0.0, -30.0]]
    cam = look_at((0.0, 1.0, 0.0), (0.0, 0.0, -4.0), width=24, height=24, fov_y=60.0)
    scene = make_scene(mesh(verts, [[0, 1, 2], [0, 2, 3]]), cam)
    points, ids = (np.asarray(a) for a in fragment_points(scene))
    ref_cam, faces, corners = RefCamera.of(scene.camera), np.asarray(scene.mesh.faces), \
        np.asarray(verts)
    exact, affine = [], []
    for row, col in zip(*np.nonzero(ids >= 0), strict=True):
        eye, ray = ref_cam.world_ray(row, col)
        exact.append(eye - eye[1] / ray[1] * ray)  # the ray meets y = 0
        tri = corners[faces[ids[row, col]]]
        affine.append(screen_bary(ref_cam, tri, row, col) @ tri)
    covered = points[ids >= 0]
    assert len(covered) > 100
    np.testing.assert_allclose(covered, np.array(exact), atol=1e-9)
    assert np.abs(np.array(affine) - np.array(exact)).max() > 1.0

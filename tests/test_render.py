"""Full renders against independent references: the naive rasterizer + OpenGL 1.x lighting
of tests/reference.py for every shading mode, and closed forms for normals under
non-uniform scale, Gouraud vs Phong on a plane, flat shading, Gouraud's per-vertex clamp
and the output format. float64 unless a test says float32."""

import jax
import numpy as np
import pytest
import reference

from diffshade import (
    RenderSettings,
    ambient_light,
    directional_light,
    icosphere,
    look_at,
    make_scene,
    material,
    model_matrix,
    point_light,
    render,
    render_parts,
    replace,
    spot_light,
)

pytestmark = pytest.mark.usefixtures("x64")

EDGE_TOL = 1e-6  # pixels: see test_raster.py
MODES = ("phong", "gouraud", "flat", "flat_last")


def image(scene, **settings):
    return np.asarray(render(scene, RenderSettings(**settings)))


def assert_matches_reference(scene, atol, shading="phong", **settings):
    """The render equals the reference render (pixels away from edges): returns the image,
    the reference image and the reference fragments."""
    ref, frags = reference.render(scene, shading, settings.get("specular", "blinn"),
                                  settings.get("clamp", True))
    img = image(scene, shading=shading, **settings)
    clear = frags.edge_dist > EDGE_TOL
    assert clear.mean() > 0.9
    np.testing.assert_allclose(img[clear], ref[clear], atol=atol, rtol=0)
    return img, ref, frags


def sphere_scene():
    """icosphere(1) under a rotation, translation and non-uniform scale, lit by lights of
    every type (two point lights), with a specular and emissive material, local viewer."""
    cam = look_at((0.4, 0.6, 3.5), (0.0, 0.0, 0.0), width=24, height=20, fov_y=45.0)
    lights = [ambient_light((0.05, 0.1, 0.05)),
              directional_light((1.0, -1.0, -1.0), (1.0, 0.8, 0.6), ambient=0.1),
              point_light((1.0, 1.0, 2.0), (0.5, 0.7, 0.9), attenuation=(1.0, 0.2, 0.1)),
              point_light((-2.0, 0.0, 1.0), (0.3, 0.2, 0.1), ambient=0.05),
              spot_light((0.0, 0.5, 3.0), (0.0, -0.1, -1.0), (0.6, 0.6, 0.3), cutoff=20.0,
                         exponent=4.0, attenuation=(1.0, 0.1, 0.05))]
    mat = material(ka=(0.2, 0.3, 0.1), kd=(0.7, 0.5, 0.3), ks=(0.5, 0.4, 0.3), shininess=20.0,
                   emission=(0.05, 0.0, 0.02))
    model = model_matrix((0.1, -0.1, 0.0), (20.0, 30.0, 10.0), (1.2, 0.8, 1.0))
    return make_scene(icosphere(1), cam, lights, mat, model=model, local_viewer=True,
                      global_ambient=(0.1, 0.15, 0.2), background=(0.2, 0.1, 0.0))


@pytest.mark.parametrize("shading", MODES)
def test_sphere_matches_reference(shading):
    img, _, _ = assert_matches_reference(sphere_scene(), 1e-4, shading)
    assert 0.2 < img[..., 3].mean() < 0.9


def test_sphere_phong_specular_model_matches_reference():
    assert_matches_reference(sphere_scene(), 1e-4, "phong", specular="phong")


def test_sphere_matches_reference_in_float32():
    with jax.enable_x64(False):
        scene = sphere_scene()
        img, _, _ = assert_matches_reference(scene, 2e-3, "phong")
    assert img.dtype == np.float32


def two_sided_scene(mesh, back=None):
    """Overlapping triangles, one of them clockwise on screen (a back face) in front."""
    verts = np.array([[-1.5, -1.2, -0.8], [1.4, -1.0, -0.2], [0.0, 1.5, -0.5],
                      [-1.0, 0.8, 0.3], [-0.2, -1.3, -1.2], [1.2, 0.6, 0.0],
                      [-0.6, -0.6, 1.0], [0.1, 0.6, 0.8], [0.6, -0.3, 1.2]])
    faces = np.arange(9).reshape(3, 3)
    tri = verts[faces]
    normals = np.repeat(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), 3, axis=0)
    normals = normals + np.tile([[0.2, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, 0.0, 0.0]], (3, 1))
    cam = look_at((0.3, 0.2, 4.0), (0.0, 0.0, 0.0), width=24, height=24, fov_y=40.0)
    lights = [directional_light((0.3, -0.2, -1.0), (0.9, 0.8, 0.7)),
              point_light((-1.0, 1.0, -2.0), (0.3, 0.5, 0.9), attenuation=(1.0, 0.0, 0.1))]
    front = material(ka=0.3, kd=(0.8, 0.5, 0.2), ks=0.4, shininess=10.0)
    back = back or material(ka=0.1, kd=(0.2, 0.4, 0.8), ks=0.9, shininess=40.0)
    return make_scene(mesh(verts, faces, normals), cam, lights, front, back_material=back,
                      two_sided=True, global_ambient=0.1)


@pytest.mark.parametrize("shading", MODES)
def test_two_sided_triangles_match_reference(mesh, shading):
    _, _, frags = assert_matches_reference(two_sided_scene(mesh), 1e-4, shading)
    assert (frags.face_ids == 2).sum() > 10 and not frags.front[frags.face_ids == 2].any()


@pytest.mark.parametrize("shading, plain_side", [("phong", "back"), ("gouraud", "back"),
                                                 ("phong", "front")])
def test_two_sided_materials_may_differ_in_having_specular_and_emission(mesh, shading,
                                                                        plain_side):
    # OpenGL's front and back materials each have their own specular and emission (zero
    # when not set); one side having ks and emission must not break the other side
    shiny = material(ka=0.3, kd=(0.8, 0.5, 0.2), ks=0.4, shininess=10.0, emission=0.1)
    plain = material(ka=0.1, kd=(0.2, 0.4, 0.8))
    front, back = (shiny, plain) if plain_side == "back" else (plain, shiny)
    scene = replace(two_sided_scene(mesh, back=back), material=front)
    assert_matches_reference(scene, 1e-4, shading)


# --------------------------------------------------------------------------- closed forms


def test_normals_under_non_uniform_scale_use_the_inverse_transpose(mesh):
    # model plane x + y = 0 (normal (1, 1, 0)/sqrt 2); under diag(3, 1, 1) the surface is
    # x/3 + y = 0 with normal (1, 3, 0)/sqrt 10, while M n would give (3, 1, 0)/sqrt 10
    verts = [[-1.0, 1.0, -1.0], [1.0, -1.0, -1.0], [1.0, -1.0, 1.0], [-1.0, 1.0, 1.0]]
    faces = [[0, 2, 1], [0, 3, 2]]
    cam = look_at((1.5, 4.0, 1.0), (0.0, 0.0, 0.0), width=20, height=20, fov_y=40.0)
    scene = make_scene(mesh(verts, faces), cam, [directional_light((0.0, -1.0, 0.0))],
                       material(ka=0.0, kd=0.5), model=np.diag([3.0, 1.0, 1.0, 1.0]))
    np.testing.assert_allclose(np.asarray(scene.mesh.normals[0]), [2**-0.5, 2**-0.5, 0.0])
    diffuse = np.asarray(render_parts(scene).diffuse)
    covered = image(scene)[..., 3] > 0
    assert covered.sum() > 50
    np.testing.assert_allclose(diffuse[covered], 0.5 * 3.0 / np.sqrt(10.0), atol=1e-12)
    assert np.abs(diffuse[covered] - 0.5 / np.sqrt(10.0)).min() > 0.3


def plane_scene(mesh, lights, mat, normals=None, size=16, **kw):
    """A square in z = 0 filling the view from (0, 0, 3)."""
    verts = [[-2.0, -2.0, 0.0], [2.0, -2.0, 0.0], [2.0, 2.0, 0.0], [-2.0, 2.0, 0.0]]
    cam = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=size, height=size, fov_y=30.0)
    return make_scene(mesh(verts, [[0, 1, 2], [0, 2, 3]], normals), cam, lights, mat, **kw)


def test_gouraud_equals_phong_on_a_plane_under_a_directional_light(mesh):
    to_light, shininess = reference.unit([1.0, 1.0, 2.0]), 16.0
    scene = plane_scene(mesh, [directional_light(-to_light, (0.9, 0.6, 0.3))],
                        material(ka=0.2, kd=(0.5, 0.6, 0.7), ks=0.4, shininess=shininess),
                        global_ambient=0.5)
    gouraud, phong = image(scene, shading="gouraud"), image(scene, shading="phong")
    half = reference.unit(to_light + np.array([0.0, 0.0, 1.0]))
    expected = (0.1 + np.array([0.5, 0.6, 0.7]) * np.array([0.9, 0.6, 0.3]) * to_light[2]
                + 0.4 * np.array([0.9, 0.6, 0.3]) * half[2] ** shininess)
    np.testing.assert_allclose(gouraud, phong, atol=1e-5)
    np.testing.assert_allclose(phong[..., :3], np.broadcast_to(expected, (16, 16, 3)),
                               atol=1e-12)
    np.testing.assert_array_equal(gouraud[..., 3], 1.0)


def tilted_triangle_scene(mesh):
    """One tilted triangle with deliberately different vertex normals, under a point light."""
    verts = np.array([[-1.0, -0.8, -0.5], [1.2, -0.6, 0.3], [0.1, 1.0, -0.2]])
    normals = [[-0.4, 0.0, 1.0], [0.5, -0.3, 1.0], [0.0, 0.6, 0.8]]
    cam = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=16, height=16, fov_y=45.0)
    light = point_light((0.5, 0.8, 1.5), (0.9, 0.8, 0.7), attenuation=(1.0, 0.1, 0.05))
    mat = material(ka=0.2, kd=(0.6, 0.5, 0.4), ks=0.5, shininess=8.0)
    return make_scene(mesh(verts, [[0, 1, 2]], normals), cam, [light], mat, local_viewer=True,
                      global_ambient=0.2)


def lit_colour(scene, point, normal):
    ref = reference.RefScene(scene)
    return np.clip(reference.total(ref.light(np.asarray(point), reference.unit(normal))), 0, 1)


def test_flat_uses_the_face_normal_at_the_centroid(mesh):
    scene = tilted_triangle_scene(mesh)
    verts = np.asarray(scene.mesh.vertices)
    face_normal = np.cross(verts[1] - verts[0], verts[2] - verts[0])
    expected = lit_colour(scene, verts.mean(0), face_normal)
    img = image(scene, shading="flat")
    covered = img[..., 3] > 0
    assert covered.sum() > 20
    np.testing.assert_allclose(img[covered][:, :3], np.broadcast_to(expected, (covered.sum(), 3)),
                               atol=1e-12)


def test_flat_last_uses_the_lit_colour_of_the_last_vertex(mesh):
    scene = tilted_triangle_scene(mesh)
    verts, normals = np.asarray(scene.mesh.vertices), np.asarray(scene.mesh.normals)
    expected = lit_colour(scene, verts[2], normals[2])
    assert np.abs(expected - lit_colour(scene, verts[0], normals[0])).max() > 0.05
    img = image(scene, shading="flat_last")
    covered = img[..., 3] > 0
    np.testing.assert_allclose(img[covered][:, :3], np.broadcast_to(expected, (covered.sum(), 3)),
                               atol=1e-12)


def saturated_triangle_scene(mesh):
    """Vertex 0 faces a strong light (colour 2.4 before clamping), vertices 1, 2 face away."""
    verts = [[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0]]
    normals = [[0.0, 0.0, 1.0], [0.0, 0.6, -0.8], [0.6, 0.0, -0.8]]
    cam = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=16, height=16, fov_y=45.0)
    light = directional_light((0.0, 0.0, -1.0), 3.0)
    return make_scene(mesh(verts, [[0, 1, 2]], normals), cam, [light],
                      material(ka=0.2, kd=0.8), global_ambient=0.2)


def test_gouraud_clamps_vertex_colours_before_interpolating(mesh):
    scene = saturated_triangle_scene(mesh)
    img, _, _ = assert_matches_reference(scene, 1e-9, "gouraud")
    unclamped, frags = reference.render(scene, "gouraud", clamp=False)
    covered = frags.face_ids >= 0
    # clamping after interpolation would give a brighter image
    assert (np.clip(unclamped[covered], 0, 1) - img[covered]).max() > 0.2


def test_gouraud_without_clamp_keeps_values_above_one(mesh):
    scene = saturated_triangle_scene(mesh)
    img, _, _ = assert_matches_reference(scene, 1e-9, "gouraud", clamp=False)
    assert img[..., :3].max() > 1.2


# ----------------------------------------------------------------------- image layout


def test_output_is_float32_rgba_with_alpha_coverage_over_background(mesh):
    with jax.enable_x64(False):
        verts = [[-1.0, -1.0, 0.0], [1.0, -0.5, 0.0], [0.0, 1.0, 0.0]]
        cam = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=20, height=12)
        scene = make_scene(mesh(verts, [[0, 1, 2]]), cam, [directional_light((0, 0, -1))],
                           background=(0.1, 0.2, 0.3))
        img = render(scene)
    assert img.shape == (12, 20, 4) and img.dtype == np.float32
    img = np.asarray(img)
    frags = reference.render(scene)[1]
    covered = frags.face_ids >= 0
    assert np.all(frags.edge_dist > 1e-3)  # far from edges even for float32
    np.testing.assert_array_equal(img[..., 3], covered.astype(np.float32))
    assert 10 < covered.sum() < covered.size
    background = np.broadcast_to(np.float32([0.1, 0.2, 0.3]), ((~covered).sum(), 3))
    np.testing.assert_array_equal(img[~covered][:, :3], background)


def test_emission_alone_is_the_image(mesh):
    scene = plane_scene(mesh, [], material(ka=0.0, kd=0.9, emission=(0.1, 0.5, 0.9)),
                        global_ambient=0.7)
    np.testing.assert_array_equal(image(scene), np.broadcast_to([0.1, 0.5, 0.9, 1.0],
                                                                (16, 16, 4)))


def test_light_above_lights_the_top_rows(mesh):
    # a point light at +y over a plane facing the camera: brightest near row 0 (the top)
    light = point_light((0.0, 1.5, 0.3), attenuation=(0.01, 0.0, 1.0))
    scene = plane_scene(mesh, [light], material(ka=0.0, kd=1.0), size=17, global_ambient=0.0)
    diffuse = np.asarray(render_parts(scene).diffuse)[:, 8, 0]
    assert np.argmax(diffuse) < 3 and diffuse[:8].min() > diffuse[9:].max()


def test_large_icosphere_renders_finite():
    # 20,480 faces at 512 x 512, hard rasterization with Phong shading
    with jax.enable_x64(False):
        cam = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=512, height=512)
        scene = make_scene(icosphere(5), cam, [directional_light((-1.0, -1.0, -1.0))],
                           material(ks=0.5, shininess=30.0))
        img = np.asarray(render(scene))
    assert img.shape == (512, 512, 4) and np.all(np.isfinite(img))
    assert 0.3 < img[..., 3].mean() < 0.7 and img[..., :3].max() > 0.5

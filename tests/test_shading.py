"""Closed forms for the lighting core, `diffshade.shading.lighting.shade`, and the same laws seen
through `render_parts` (OpenGL 1.x spec 2.14.1 semantics; all in float64).

Geometry used throughout: the surface normal N = +z at the origin, so that a light or a
viewer at angle theta from +z has N.L = cos(theta) exactly as written down.
"""

import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from reference import RefCamera

from diffshade import (
    RenderSettings,
    ambient_light,
    directional_light,
    look_at,
    make_scene,
    material,
    point_light,
    render_parts,
    replace,
    shade,
    sphere_light,
    spot_light,
)
from diffshade.numerics import float_dtype
from diffshade.scene.lights import group_lights
from diffshade.shading.lighting import reads_points
from diffshade.shading.shadows import shadow_maps

pytestmark = pytest.mark.usefixtures("x64")

PARTS = ("ambient", "diffuse", "specular", "emission")
BLINN, PHONG = RenderSettings(specular="blinn"), RenderSettings(specular="phong")

_shade = jax.jit(shade, static_argnames=("settings",))


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def at_angle(theta_deg, azimuth_deg=0.0):
    """Unit vector at angle theta from +z, in the plane at `azimuth` from +x."""
    t, a = math.radians(theta_deg), math.radians(azimuth_deg)
    return np.array([math.sin(t) * math.cos(a), math.sin(t) * math.sin(a), math.cos(t)])


def lit(mat, lights, *, points=(0.0, 0.0, 0.0), normals=(0.0, 0.0, 1.0),
        views=(0.0, 0.0, 1.0), global_ambient=0.0, settings=BLINN):
    """shade() on numpy inputs ([..., 3]); returns {part: numpy [..., 3]}."""
    dt = float_dtype()
    arr = partial(jnp.asarray, dtype=dt)
    ga = arr(np.broadcast_to(np.asarray(global_ambient, np.float64), (3,)))
    parts = _shade(mat, group_lights(lights), ga, arr(points), arr(unit(normals)),
                   arr(unit(views)), settings)
    return {name: np.asarray(getattr(parts, name)) for name in PARTS}


# ------------------------------------------------------------------ specular closed forms


@pytest.mark.parametrize("settings", [BLINN, PHONG], ids=["blinn", "phong"])
def test_specular_equals_light_specular_in_the_mirror_geometry(settings):
    # L and V at 45 degrees on either side of N: H = N (Blinn) and R = V (Phong), so the
    # specular term is exactly ks * Is whatever the shininess
    to_light, view = at_angle(45.0, 180.0), at_angle(45.0)
    ks, spec_colour, kd, diff_colour = (0.3, 0.5, 0.7), (1.0, 0.8, 0.6), (0.6, 0.4, 0.2), 0.9
    light = directional_light(-to_light, diffuse=diff_colour, specular=spec_colour)
    out = lit(material(ka=0.0, kd=kd, ks=ks, shininess=50.0), [light], views=view,
              settings=settings)
    np.testing.assert_allclose(out["specular"], np.multiply(ks, spec_colour), atol=1e-12)
    np.testing.assert_allclose(out["diffuse"], np.multiply(kd, diff_colour) * math.cos(
        math.pi / 4), atol=1e-12)


@pytest.mark.parametrize("settings, angle", [(BLINN, 22.5), (PHONG, 45.0)],
                         ids=["blinn", "phong"])
def test_specular_off_the_mirror_direction_is_cos_power(settings, angle):
    # L at 45 degrees, V = N: the angle between N and H is 22.5 degrees, between R and V 45
    shininess = 8.0
    light = directional_light(-at_angle(45.0, 180.0))
    out = lit(material(ka=0.0, kd=0.0, ks=0.7, shininess=shininess), [light], settings=settings)
    expected = 0.7 * math.cos(math.radians(angle)) ** shininess
    np.testing.assert_allclose(out["specular"], np.full(3, expected), atol=1e-12)


@pytest.mark.parametrize("settings", [BLINN, PHONG], ids=["blinn", "phong"])
@pytest.mark.parametrize("theta", [90.0, 100.0, 135.0])
def test_no_specular_where_the_light_is_behind_the_surface(settings, theta):
    # OpenGL's f_i: the specular term is 0 where N.L <= 0 even if N.H (or R.V) is > 0
    to_light = at_angle(theta)
    to_light[np.abs(to_light) < 1e-15] = 0.0  # N.L exactly 0 at 90 degrees
    view = unit(to_light + 2.2 * np.array([0.0, 0.0, 1.0]))
    if settings is PHONG:  # a view along R = 2 (N.L) N - L, so that R.V > 0
        view = unit(2.0 * to_light[2] * np.array([0.0, 0.0, 1.0]) - to_light + [0.0, 0.0, 0.1])
    half, reflect = unit(to_light + view), 2.0 * to_light[2] * np.array([0, 0, 1]) - to_light
    assert (half[2] if settings is BLINN else reflect @ view) > 0.0
    light = directional_light(-to_light)
    out = lit(material(ka=0.0, kd=0.5, ks=1.0, shininess=2.0), [light], views=view,
              settings=settings)
    np.testing.assert_array_equal(out["specular"], np.zeros(3))
    np.testing.assert_array_equal(out["diffuse"], np.zeros(3))


def test_without_ks_there_is_no_specular():
    light = directional_light(-at_angle(45.0, 180.0))
    with_ks = lit(material(ka=0.0, ks=0.5, shininess=10.0), [light], views=at_angle(45.0))
    without = lit(material(ka=0.0, ks=None), [light], views=at_angle(45.0))
    np.testing.assert_allclose(with_ks["specular"], np.full(3, 0.5), atol=1e-12)
    np.testing.assert_array_equal(without["specular"], np.zeros(3))
    np.testing.assert_allclose(without["diffuse"], with_ks["diffuse"], atol=0)


# ---------------------------------------------------------------- diffuse, per channel


def test_diffuse_is_kd_times_id_times_cos_theta():
    thetas = np.array([0.0, 30.0, 60.0, 85.0, 90.0, 120.0, 180.0])
    normals = np.stack([at_angle(t, 30.0) for t in thetas])  # N.L = cos(theta), L = +z
    kd, colour = np.array([0.9, 0.5, 0.25]), np.array([0.8, 1.0, 0.4])
    light = directional_light((0.0, 0.0, -1.0), colour)
    out = lit(material(ka=0.0, kd=kd), [light], normals=normals)
    cos = np.maximum(np.cos(np.radians(thetas)), 0.0)
    np.testing.assert_allclose(out["diffuse"], cos[:, None] * kd * colour, atol=1e-12)


def test_every_coefficient_acts_per_channel():
    ka, kd, ks, ke = (0.1, 0.2, 0.3), (0.9, 0.6, 0.3), (0.2, 0.5, 0.8), (0.01, 0.02, 0.03)
    ia, id_, is_ = (0.5, 0.25, 1.0), (0.3, 0.6, 0.9), (1.0, 0.5, 0.25)
    light = directional_light(-at_angle(45.0, 180.0), ambient=ia, diffuse=id_, specular=is_)
    out = lit(material(ka=ka, kd=kd, ks=ks, shininess=30.0, emission=ke), [light],
              views=at_angle(45.0), global_ambient=(0.2, 0.4, 0.6))
    m = np.multiply
    np.testing.assert_allclose(out["ambient"], m(ka, (0.2, 0.4, 0.6)) + m(ka, ia), atol=1e-12)
    np.testing.assert_allclose(out["diffuse"], m(kd, id_) * math.cos(math.pi / 4), atol=1e-12)
    np.testing.assert_allclose(out["specular"], m(ks, is_), atol=1e-12)
    np.testing.assert_allclose(out["emission"], ke, atol=0)


# ------------------------------------------------------------------ attenuation, spots


def test_attenuation_is_one_over_a_plus_bd_plus_cd2():
    coeffs, dists = (0.5, 0.3, 0.2), np.array([0.25, 1.0, 2.0, 5.0])
    points = np.stack([np.zeros_like(dists), np.zeros_like(dists), -dists], 1)
    light = point_light((0.0, 0.0, 0.0), (0.9, 0.6, 0.3), attenuation=coeffs)
    out = lit(material(ka=0.0, kd=0.5), [light], points=points)
    att = 1.0 / (coeffs[0] + coeffs[1] * dists + coeffs[2] * dists**2)
    np.testing.assert_allclose(out["diffuse"], att[:, None] * 0.5 * np.array([0.9, 0.6, 0.3]),
                               rtol=1e-12)


def test_pure_inverse_square_attenuation_is_one_over_d2_and_finite_at_the_light():
    dists = np.array([0.0, 1e-9, 0.5, 1.0, 3.0])
    points = np.stack([np.zeros_like(dists), np.zeros_like(dists), -dists], 1)
    light = point_light((0.0, 0.0, 0.0), (0.9, 0.6, 0.3), ambient=0.2,
                        attenuation=(0.0, 0.0, 1.0))
    out = lit(material(ka=0.5, kd=0.5), [light], points=points, global_ambient=0.0)
    far = dists >= 0.5
    np.testing.assert_allclose(out["diffuse"][far], 0.5 * np.array([0.9, 0.6, 0.3])
                               / dists[far, None] ** 2, rtol=1e-12)
    # at and next to the light the denominator is floored at tiny: large but finite
    assert np.all(np.isfinite(out["ambient"])) and np.all(out["ambient"][:2] > 1e12)


def test_attenuation_scales_the_light_ambient_but_not_emission_or_global_ambient():
    ka, light_ambient, global_ambient, ke = 0.5, (0.4, 0.2, 0.8), (0.1, 0.3, 0.2), (0.1, 0, 0.3)
    light = point_light((0.0, 0.0, 1.0), ambient=light_ambient, attenuation=(4.0, 0.0, 0.0))
    out = lit(material(ka=ka, kd=0.0, emission=ke), [light], global_ambient=global_ambient)
    expected = ka * np.asarray(global_ambient) + 0.25 * ka * np.asarray(light_ambient)
    np.testing.assert_allclose(out["ambient"], expected, atol=1e-12)
    np.testing.assert_allclose(out["emission"], ke, atol=0)


def spot_points(angles_deg, height=2.0):
    """Points on z = 0 seen from a spot at (0, 0, height) at the given angles off its axis."""
    xs = height * np.tan(np.radians(angles_deg))
    return np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], 1)


def spot_diffuse(angles_deg, exponent, cutoff):
    light = spot_light((0.0, 0.0, 2.0), (0.0, 0.0, -1.0), cutoff=cutoff, exponent=exponent)
    return lit(material(ka=0.0, kd=1.0), [light], points=spot_points(angles_deg))["diffuse"]


def test_spot_is_a_hard_cone():
    # N.L = cos(phi) for a point at angle phi off the axis; spot factor 1 inside, 0 outside
    eps = 1e-7
    angles = np.array([0.0, 20.0, 30.0 - math.degrees(eps), 30.0 + math.degrees(eps), 35.0])
    inside = np.array([1.0, 1.0, 1.0, 0.0, 0.0])
    expected = inside * np.cos(np.radians(angles))
    np.testing.assert_allclose(spot_diffuse(angles, 0.0, 30.0)[:, 0], expected, atol=1e-12)


def test_spot_exactly_at_the_cutoff_is_lit():
    # OpenGL lights points with -L.D >= cos(cutoff). cutoff 0 makes "exactly at the cutoff"
    # exact in floating point: the point straight below the spot has -L.D = 1 = cos(0)
    np.testing.assert_allclose(spot_diffuse(np.array([0.0, 1e-3]), 2.0, 0.0)[:, 0], [1.0, 0.0],
                               atol=1e-12)


def test_spot_exponent_falls_off_as_cos_power():
    angles, exponent = np.array([0.0, 10.0, 25.0, 40.0]), 8.0
    cos = np.cos(np.radians(angles))
    expected = np.where(angles <= 30.0, cos**exponent, 0.0) * cos
    np.testing.assert_allclose(spot_diffuse(angles, exponent, 30.0)[:, 0], expected, atol=1e-12)


def test_spot_with_cutoff_180_is_a_point_light():
    # the spot points away from the samples and has an exponent: both ignored at 180
    points = np.array([[0.0, 0.0, 0.0], [1.0, -0.5, 0.0], [-2.0, 3.0, -1.0]])
    normals = unit(np.array([[0.0, 0.0, 1.0], [0.3, 0.1, 1.0], [-0.5, 0.5, 0.2]]))
    views = unit(np.array([[0.0, 0.3, 1.0], [0.5, 0.0, 1.0], [0.0, 0.0, 1.0]]))
    kw = dict(ambient=0.3, diffuse=(0.9, 0.7, 0.5), specular=(0.4, 0.6, 0.8),
              attenuation=(1.0, 0.5, 0.25))
    spot = spot_light((0.5, 0.5, 2.0), (0.0, 0.0, 1.0), cutoff=180.0, exponent=10.0, **kw)
    mat = material(ka=0.5, kd=0.7, ks=0.6, shininess=12.0)
    as_spot = lit(mat, [spot], points=points, normals=normals, views=views)
    as_point = lit(mat, [point_light((0.5, 0.5, 2.0), **kw)], points=points, normals=normals,
                   views=views)
    to_light = np.array([0.5, 0.5, 2.0]) - points
    dist = np.linalg.norm(to_light, axis=1)
    att = 1.0 / (1.0 + 0.5 * dist + 0.25 * dist**2)
    n_dot_l = np.maximum(np.sum(normals * to_light, 1) / dist, 0.0)
    np.testing.assert_allclose(as_spot["diffuse"],
                               (att * n_dot_l)[:, None] * 0.7 * np.array([0.9, 0.7, 0.5]),
                               atol=1e-12)
    for name in PARTS:
        np.testing.assert_allclose(as_spot[name], as_point[name], atol=1e-12)


# ------------------------------------------------------------ emission, global ambient


def test_emission_alone():
    out = lit(material(ka=0.0, kd=0.7, ks=0.5, shininess=4.0, emission=(0.1, 0.2, 0.3)), [],
              global_ambient=0.6)
    np.testing.assert_allclose(sum(out.values()), [0.1, 0.2, 0.3], atol=0)


def test_global_ambient_alone():
    out = lit(material(ka=(0.5, 0.25, 1.0), kd=0.7), [], global_ambient=(0.2, 0.4, 0.6))
    np.testing.assert_allclose(sum(out.values()), [0.1, 0.1, 0.6], atol=1e-15)


def test_ambient_lights_add_ka_times_their_colour():
    lights = [ambient_light((0.1, 0.2, 0.3)), ambient_light(0.5)]
    out = lit(material(ka=(1.0, 0.5, 0.2), kd=0.7), lights, global_ambient=0.0)
    np.testing.assert_allclose(out["ambient"], [0.6, 0.35, 0.16], atol=1e-15)


# ------------------------------------------------- through render_parts: a facing plane


def plane_scene(mesh, lights, mat, *, eye_z=3.0, flip=False, **kw):
    """A 4x4 square in z = 0 (wound counter-clockwise seen from +z, or clockwise when
    `flip`) filling a 25x25 view from (0, 0, eye_z) (eye_z < 0 looks from below)."""
    verts = [[-2.0, -2.0, 0.0], [2.0, -2.0, 0.0], [2.0, 2.0, 0.0], [-2.0, 2.0, 0.0]]
    faces = [[0, 1, 2], [0, 2, 3]] if not flip else [[0, 2, 1], [0, 3, 2]]
    cam = look_at((0.0, 0.0, eye_z), (0.0, 0.0, 0.0), width=25, height=25, fov_y=30.0)
    return make_scene(mesh(verts, faces), cam, lights, mat, **kw)


def parts_image(scene, settings=BLINN):
    parts = render_parts(scene, settings)
    return {name: np.asarray(getattr(parts, name)) for name in PARTS}


def test_render_parts_emission_and_global_ambient_alone(mesh):
    scene = plane_scene(mesh, [], material(ka=(0.5, 0.25, 1.0), kd=0.7, emission=(0.1, 0, 0.3)),
                        global_ambient=(0.2, 0.4, 0.6))
    out = parts_image(scene)
    np.testing.assert_allclose(out["ambient"], np.broadcast_to([0.1, 0.1, 0.6], (25, 25, 3)),
                               atol=1e-15)
    np.testing.assert_allclose(out["emission"], np.broadcast_to([0.1, 0, 0.3], (25, 25, 3)),
                               atol=0)
    np.testing.assert_array_equal(out["diffuse"] + out["specular"], 0.0)


def test_render_parts_mirror_geometry_on_a_tilted_plane(mesh):
    # a plane whose normal is the half vector between L = +x and the infinite viewer +z
    cam = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=17, height=17, fov_y=30.0)
    verts = [[-2.0, -2.0, 2.0], [2.0, -2.0, -2.0], [2.0, 2.0, -2.0], [-2.0, 2.0, 2.0]]
    light = directional_light((-1.0, 0.0, 0.0), diffuse=0.5, specular=(1.0, 0.8, 0.6))
    mat = material(ka=0.0, kd=(0.2, 0.4, 0.6), ks=(0.3, 0.5, 0.7), shininess=64.0)
    out = parts_image(make_scene(mesh(verts, [[0, 1, 2], [0, 2, 3]]), cam, [light], mat))
    np.testing.assert_allclose(out["specular"], np.broadcast_to([0.3, 0.4, 0.42], (17, 17, 3)),
                               atol=1e-12)
    diffuse = 0.5 * np.array([0.2, 0.4, 0.6]) * math.cos(math.pi / 4)
    np.testing.assert_allclose(out["diffuse"], np.broadcast_to(diffuse, (17, 17, 3)),
                               atol=1e-12)


def test_local_viewer_differs_off_axis_and_agrees_on_axis(mesh):
    to_light, shininess = unit([1.0, 0.5, 2.0]), 20.0
    mat = material(ka=0.0, kd=0.0, ks=1.0, shininess=shininess)
    scene = plane_scene(mesh, [directional_light(-to_light)], mat)
    local = parts_image(replace(scene, local_viewer=True))["specular"][..., 0]
    infinite = parts_image(scene)["specular"][..., 0]
    cam = RefCamera.of(scene.camera)
    expected = np.zeros((25, 25, 2))
    for row in range(25):
        for col in range(25):
            eye, ray = cam.world_ray(row, col)
            point = eye - eye[2] / ray[2] * ray  # on z = 0
            for i, view in enumerate([unit(eye - point), np.array([0.0, 0.0, 1.0])]):
                expected[row, col, i] = unit(to_light + view)[2] ** shininess
    np.testing.assert_allclose(local, expected[..., 0], atol=1e-12)
    np.testing.assert_allclose(infinite, expected[..., 1], atol=1e-12)
    assert np.abs(local - infinite).max() > 0.05
    assert abs(local[12, 12] - infinite[12, 12]) < 1e-12  # the pixel on the view axis


def two_sided_scene(mesh, **kw):
    """The square's back faces the eye (clockwise on screen, so its normals are -z). Light
    A shines from the eye's side, light B from behind the square."""
    lights = [directional_light((0.0, 0.0, -1.0), (0.9, 0.6, 0.3)),   # A: L = +z
              directional_light((0.0, 0.0, 1.0), (0.2, 0.4, 0.8))]    # B: L = -z
    front = material(ka=(0.5, 0.5, 0.5), kd=(1.0, 0.8, 0.6))
    return plane_scene(mesh, lights, front, flip=True, global_ambient=0.2, **kw)


def test_two_sided_back_face_uses_flipped_normal_and_back_material(mesh):
    back = material(ka=(0.1, 0.2, 0.3), kd=(0.3, 0.2, 0.1))
    out = parts_image(two_sided_scene(mesh, two_sided=True, back_material=back))
    expected_diffuse = np.multiply((0.3, 0.2, 0.1), (0.9, 0.6, 0.3))  # back kd * light A
    np.testing.assert_allclose(out["diffuse"], np.broadcast_to(expected_diffuse, (25, 25, 3)),
                               atol=1e-12)
    np.testing.assert_allclose(out["ambient"], np.broadcast_to([0.02, 0.04, 0.06], (25, 25, 3)),
                               atol=1e-12)


def test_one_sided_back_face_uses_front_material_and_its_own_normal(mesh):
    back = material(ka=(0.1, 0.2, 0.3), kd=(0.3, 0.2, 0.1))
    out = parts_image(two_sided_scene(mesh, two_sided=False, back_material=back))
    expected_diffuse = np.multiply((1.0, 0.8, 0.6), (0.2, 0.4, 0.8))  # front kd * light B
    np.testing.assert_allclose(out["diffuse"], np.broadcast_to(expected_diffuse, (25, 25, 3)),
                               atol=1e-12)
    np.testing.assert_allclose(out["ambient"], np.full((25, 25, 3), 0.1), atol=1e-12)


def test_two_sided_front_face_keeps_front_material(mesh):
    # the same square seen from below is counter-clockwise on screen: a front face
    back = material(ka=(0.1, 0.2, 0.3), kd=(0.3, 0.2, 0.1))
    scene = two_sided_scene(mesh, two_sided=True, back_material=back)
    scene = replace(scene, camera=look_at((0.0, 0.0, -3.0), (0.0, 0.0, 0.0), width=25,
                                          height=25, fov_y=30.0))
    out = parts_image(scene)
    expected_diffuse = np.multiply((1.0, 0.8, 0.6), (0.2, 0.4, 0.8))  # front kd * light B
    np.testing.assert_allclose(out["diffuse"], np.broadcast_to(expected_diffuse, (25, 25, 3)),
                               atol=1e-12)


# ------------------------------------------------------------------ what shade reads


SUN = directional_light((0.3, -0.2, -1.0), (0.9, 0.8, 0.7))


@pytest.mark.parametrize("lights, reads", [
    ([], False), ([ambient_light(0.3)], False), ([SUN], False),
    ([SUN, ambient_light(0.3)], False), ([SUN, point_light((1.0, 2.0, 3.0))], True),
    ([spot_light((0.0, 0.0, 2.0), (0.0, 0.0, -1.0))], True),
    ([sphere_light((0.0, 1.0, 2.0), 0.3)], True)])
def test_shade_reads_points_only_for_positional_lights(lights, reads):
    # render interpolates no points where reads_points says shade reads none: with NaN
    # points, shade must then give the values it gives at the true points
    mat = material(ka=0.2, kd=(0.5, 0.4, 0.3), ks=0.4, shininess=12.0)
    groups = group_lights(lights)
    assert reads_points(groups) is reads
    points = jnp.array([[0.1, -0.3, 0.0], [0.5, 0.2, 0.1]])
    normals = jnp.asarray(unit([[0.0, 0.2, 1.0], [0.4, -0.1, 0.9]]))
    views = jnp.asarray(unit([0.1, 0.0, 1.0]))
    ga = jnp.full(3, 0.1)
    at_points = _shade(mat, groups, ga, points, normals, views, BLINN)
    at_nan = _shade(mat, groups, ga, jnp.full_like(points, jnp.nan), normals, views, BLINN)
    finite = all(np.isfinite(np.asarray(p)).all() for p in jax.tree.leaves(at_nan))
    assert finite is not reads
    if not reads:
        for got, want in zip(jax.tree.leaves(at_nan), jax.tree.leaves(at_points), strict=True):
            np.testing.assert_array_equal(got, want)


def test_a_shadow_map_makes_shade_read_the_points(mesh):
    scene = plane_scene(mesh, [directional_light((0.0, 0.0, -1.0), shadows=True)],
                        material(kd=0.5))
    maps = shadow_maps(scene, RenderSettings())
    assert not reads_points(scene.lights) and reads_points(scene.lights, maps)
    # visibilities computed before (fitting's cache) are no lookup
    assert not reads_points(scene.lights, {key: jnp.ones((4, 1)) for key in maps})

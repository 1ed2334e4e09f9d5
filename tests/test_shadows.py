"""Shadow maps (diffshade/shading/shadows.py) against the exact shadow of a sphere over a floor.

- One scene, three shadowed lights of different types, each lighting one colour channel
  only (a point light red, a spot green, a directional light blue): each channel of the
  hard and soft renders is compared per pixel with the closed form of its light: inside
  the exact shadow (diffshade.analytic.SphereOverPlane, NumPy ray/sphere tests) only the
  ambient terms ka * (global + light ambient), elsewhere those plus kd * Id * N.L (and
  the spot's cone), except within 2 pixels of an edge (shadow, cone, silhouette).
- Self-shadowing: a floor lit at 70-80 degrees from its normal (a directional and a point
  light, shadows on, nothing to cast a shadow) is lit everywhere: the slope-scaled bias.
- Structure: a light without shadows adds nothing to the program; each shadowed light
  adds one rasterization.
- Transforms, float64: check_grads (forward and reverse, order 1) with respect to the
  lights' positions, directions and radii, the vertices and kd in soft mode (a point,
  a directional, a disk and a sphere light in one program), and render_views against a
  loop of renders.
- The flag in the Python factories and in scene files, and its bad values.
- Area and sphere lights with shadows: the penumbrae of a rectangle, a disk and a sphere
  light against a ray-traced quadrature over each light (SphereOverPlane.floor_irradiance,
  NumPy ray/sphere tests); their soft penumbrae are in the check_grads above.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from test_structure import primitive_counts, scene_with

import diffshade as ds
from diffshade.analytic import SphereOverPlane, pixel_rays
from diffshade.io.scenefile import scene_from_dict, scene_to_dict

GEOMETRY = SphereOverPlane()
SIZE = 48
KA, KD, GLOBAL, LIGHT_AMBIENT = 0.3, 0.6, 0.2, 0.1
POINT = (-1.0, 1.8, -1.0)
SPOT = ((1.2, 1.8, -0.6), (-1.5, -2.8, 1.2), 40.0)  # position, direction, cutoff
SUN = (0.2, -1.0, 1.1)
CHANNELS = ("point", "spot", "directional")
SETTINGS = {"hard": ds.RenderSettings(shadow_map_size=128),
            "soft": ds.RenderSettings(raster="soft", sigma=0.05, gamma=1e-4,
                                      faces_per_pixel=4, shadow_map_size=128)}

# soft raster blends the floor's neighbouring faces in a pixel, each read at barycentrics
# clamped to its triangle: a few 1e-4 off the closed form with or without shadows
LIT_ATOL = {"hard": 2e-4, "soft": 1e-3}


def rgb(channel, value):
    return tuple(value if c == channel else 0.0 for c in range(3))


def three_light_scene(mesh, camera, shadows=True):
    """Point (red), spot (green) and directional (blue) lights, each with shadows."""
    lights = [ds.point_light(POINT, rgb(0, 1.0), ambient=rgb(0, LIGHT_AMBIENT), shadows=shadows),
              ds.spot_light(*SPOT[:2], rgb(1, 1.0), cutoff=SPOT[2], ambient=rgb(1, LIGHT_AMBIENT),
                            shadows=shadows),
              ds.directional_light(SUN, rgb(2, 1.0), ambient=rgb(2, LIGHT_AMBIENT),
                                   shadows=shadows)]
    return ds.make_scene(mesh, camera, lights, ds.material(ka=KA, kd=KD, ks=None),
                         global_ambient=GLOBAL)


def floor_points(camera):
    """Where each pixel's ray meets the floor's plane: [H, W, 3] float64."""
    origins, dirs = pixel_rays(camera)
    t = (GEOMETRY.plane_y - origins[..., 1]) / dirs[..., 1]
    return origins + t[..., None] * dirs


def closed_form(camera):
    """Per channel (light) on the floor, [H, W] each: the ambient-only colour (what a
    shadowed point keeps: OpenGL's spot cone scales its light's ambient too) and the lit
    colour."""
    points = floor_points(camera)
    to_point = np.asarray(POINT) - points
    n_dot_l = to_point[..., 1] / np.linalg.norm(to_point, axis=-1)
    to_spot = np.asarray(SPOT[0]) - points
    spot_l = to_spot / np.linalg.norm(to_spot, axis=-1, keepdims=True)
    axis = np.asarray(SPOT[1]) / np.linalg.norm(SPOT[1])
    cone = (-spot_l @ axis >= np.cos(np.deg2rad(SPOT[2]))).astype(float)
    sun_l = -np.asarray(SUN) / np.linalg.norm(SUN)
    scale = [np.ones_like(cone), cone, np.ones_like(cone)]
    cosines = [n_dot_l, spot_l[..., 1], np.full_like(cone, sun_l[1])]
    ambient = [KA * GLOBAL + s * KA * LIGHT_AMBIENT for s in scale]
    return ambient, [a + s * KD * np.maximum(c, 0.0)
                     for a, s, c in zip(ambient, scale, cosines, strict=True)], scale


def near_edge(*masks, width=2):
    """Pixels within `width` pixels (Chebyshev) of a change in any of the masks."""
    edge = np.zeros(masks[0].shape, bool)
    for mask in masks:
        m = np.pad(mask, 1, mode="edge")
        edge |= (m[1:-1, 1:-1] != m[:-2, 1:-1]) | (m[1:-1, 1:-1] != m[2:, 1:-1])
        edge |= (m[1:-1, 1:-1] != m[1:-1, :-2]) | (m[1:-1, 1:-1] != m[1:-1, 2:])
    grown = np.pad(edge, width)
    rows, cols = edge.shape
    return np.any([grown[width + dr:width + dr + rows, width + dc:width + dc + cols]
                   for dr in range(-width, width + 1) for dc in range(-width, width + 1)], 0)


@pytest.fixture(scope="module")
def camera():
    return ds.look_at((0.0, 4.5, 3.2), (0.0, -1.0, 0.5), width=SIZE, height=SIZE, fov_y=40.0)


@pytest.mark.parametrize("raster", SETTINGS)
def test_shadows_match_the_exact_shadow_of_a_sphere_over_a_floor(raster, camera):
    scene = three_light_scene(GEOMETRY.mesh(2, 4), camera)
    image = np.asarray(ds.render(scene, SETTINGS[raster]), np.float64)
    ambient, lit, cones = closed_form(camera)
    lights = {"point": ("point", POINT), "spot": ("point", SPOT[0]),
              "directional": ("directional", SUN)}
    for c, name in enumerate(CHANNELS):
        on_floor, shadow = GEOMETRY.shadow(camera, lights[name])
        away = on_floor & ~near_edge(on_floor, shadow, cones[c] > 0)
        inside, outside = away & shadow, away & ~shadow
        assert inside.sum() >= 20 and outside.sum() >= 200, (name, inside.sum(), outside.sum())
        np.testing.assert_allclose(image[inside, c], ambient[c][inside], atol=1e-5, err_msg=name)
        np.testing.assert_allclose(image[outside, c], lit[c][outside], atol=LIT_ATOL[raster],
                                   err_msg=name)
        # rendered shadow pixels lie in the exact shadow grown by 2 pixels (and 2 from the
        # sphere's silhouette, where the blend may show its shadowed underside)
        dark = on_floor & (np.abs(image[..., c] - ambient[c]) < 1e-5) & (cones[c] > 0)
        assert not np.any(dark & ~shadow & ~near_edge(shadow, on_floor)), name


GRAZING_SIZE = 32


def grazing_floor():
    """A 4 x 4 floor of 32 faces at y = 0 (normal +y) seen from above at 45 degrees, and
    the floor point [H, W, 3] under each pixel centre (None off the floor)."""
    xs = np.linspace(-2.0, 2.0, 5)
    verts = [[x, 0.0, z] for z in xs for x in xs]
    faces = []
    for j in range(4):
        for i in range(4):
            a, b, c, d = j * 5 + i, j * 5 + i + 1, (j + 1) * 5 + i + 1, (j + 1) * 5 + i
            faces += [[a, d, c], [a, c, b]]
    mesh = ds.mesh_from_arrays(np.array(verts), np.array(faces))
    camera = ds.look_at((0.0, 3.0, 3.0), (0.0, 0.0, 0.0), width=GRAZING_SIZE,
                        height=GRAZING_SIZE, fov_y=50.0)
    origins, dirs = pixel_rays(camera)
    points = origins + (-origins[..., 1] / dirs[..., 1])[..., None] * dirs
    return mesh, camera, points


@pytest.mark.parametrize("raster", SETTINGS)
@pytest.mark.parametrize("angle", [70.0, 75.0, 80.0])
def test_a_receiver_lit_at_a_grazing_angle_does_not_shadow_itself(raster, angle):
    """A directional light (blue) at `angle` degrees from the floor's normal and a point
    light (red) low over the floor, both with shadows and nothing to cast a shadow: every
    floor pixel is lit, ka * global + kd * cos(incidence) per channel. A depth bias that
    does not grow with the slope lets the floor shadow itself there (acne)."""
    mesh, camera, points = grazing_floor()
    theta = np.deg2rad(angle)
    to_sun = np.array([np.sin(theta), np.cos(theta), 0.0])
    bulb = np.array([-8.0, 8.0 / np.tan(theta), 0.5])
    lights = [ds.directional_light(-to_sun, rgb(2, 1.0), shadows=True),
              ds.point_light(bulb, rgb(0, 1.0), shadows=True)]
    scene = ds.make_scene(mesh, camera, lights, ds.material(ka=KA, kd=KD, ks=None),
                          global_ambient=GLOBAL)
    image = np.asarray(ds.render(scene, SETTINGS[raster]), np.float64)
    on_floor = (np.abs(points[..., 0]) < 2.0) & (np.abs(points[..., 2]) < 2.0)
    floor = on_floor & ~near_edge(on_floor)
    to_bulb = bulb - points
    cos_bulb = to_bulb[..., 1] / np.linalg.norm(to_bulb, axis=-1)
    # the point light's incidence over the floor: grazing too (60 to 85 degrees)
    incidence = np.rad2deg(np.arccos(cos_bulb[floor]))
    assert 60.0 < incidence.min() < angle < incidence.max() < 85.0
    assert floor.sum() >= 300
    for c, cos in ((2, np.cos(theta)), (0, cos_bulb)):
        want = KA * GLOBAL + KD * np.broadcast_to(cos, floor.shape)
        np.testing.assert_allclose(image[floor, c], want[floor], atol=LIT_ATOL[raster],
                                   err_msg=f"channel {c}")


def test_a_light_without_shadows_adds_no_shadow_pass():
    plain, bulb = ds.point_light((0.0, 1.0, 2.0)), ds.point_light((1.0, 0.5, 2.0), 0.5)
    shadowed = ds.point_light((0.0, 1.0, 2.0), shadows=True)
    counts = {name: primitive_counts(scene_with(lights)) for name, lights in {
        "plain": [plain], "plain+bulb": [plain, bulb], "shadowed": [shadowed],
        "shadowed+bulb": [shadowed, bulb], "flag_false": [ds.point_light((0.0, 1.0, 2.0),
                                                                          shadows=False)]}.items()}
    assert counts["flag_false"] == counts["plain"]
    # the shadow pass: one more rasterization (the cube's six faces in one batched op)
    assert counts["plain"]["fragment_geometry_op"] == 1
    assert counts["shadowed"]["fragment_geometry_op"] == 2
    assert counts["plain"]["argmax"] == 0 and counts["shadowed"]["argmax"] == 1
    # an unshadowed light costs the same next to a shadowed one as next to a plain one
    # (but for the indexing that takes a light out of a stack of one or of two)
    def added(a, b):
        return {k: v for k, v in (counts[a] - counts[b]).items() if k not in ("slice", "squeeze")}
    assert added("shadowed+bulb", "shadowed") == added("plain+bulb", "plain")
    assert counts["plain+bulb"]["fragment_geometry_op"] == 1


def tiny_scene(kinds=CHANNELS):
    """12 x 12 pixels, a 20-face sphere over a 2-face floor, shadowed lights of `kinds`."""
    camera = ds.look_at((0.0, 4.5, 3.2), (0.0, -1.0, 0.5), width=12, height=12, fov_y=40.0)
    scene = three_light_scene(GEOMETRY.mesh(0, 1), camera)
    return ds.replace(scene, lights=ds.replace(scene.lights, **{
        kind: None for kind in CHANNELS if kind not in kinds}))


TINY_SOFT = ds.RenderSettings(raster="soft", faces_per_pixel=22, sigma=2.0, gamma=1e-2,
                              soft_threshold=1e-10, shadow_map_size=16)


@pytest.mark.usefixtures("x64")
def test_render_views_with_shadows_equals_a_loop_of_renders():
    scene = tiny_scene(("point",))
    settings = ds.RenderSettings(shadow_map_size=16)
    cameras = [ds.look_at(eye, (0.0, -1.0, 0.5), width=12, height=12, fov_y=40.0)
               for eye in ((0.0, 4.5, 3.2), (2.0, 2.0, 2.5))]
    batch = np.asarray(ds.render_views(scene, cameras, settings))
    for cam, image in zip(cameras, batch, strict=True):
        np.testing.assert_allclose(image, ds.render(ds.replace(scene, camera=cam), settings),
                                   atol=1e-12)
    # the shadow is in the image: the floor has pixels at the ambient-only colour
    floor_ambient = KA * (GLOBAL + LIGHT_AMBIENT)
    assert np.any(np.abs(batch[..., 0] - floor_ambient) < 1e-9)


def test_scene_files_carry_the_flag_per_light():
    camera = ds.look_at((0.0, 2.6, 3.4), (0.0, -0.6, 0.0), width=8, height=8)
    lights = [ds.point_light(POINT, shadows=True), ds.point_light((1.0, 1.0, 1.0)),
              ds.directional_light(SUN, shadows=True), ds.spot_light(*SPOT[:2]),
              ds.area_light(DISK[0], normal=DISK[1], radius=DISK[2]),
              ds.area_light(DISK[0], normal=DISK[1], radius=DISK[2], shadows=True),
              ds.sphere_light(*BALL, shadows=True)]
    scene = ds.make_scene(ds.icosphere(0), camera, lights)
    assert scene.lights.point.shadows == (True, False)
    assert scene.lights.directional.shadows == (True,)
    assert scene.lights.spot.shadows == (False,)
    assert scene.lights.disk.shadows == (False, True)
    assert scene.lights.sphere.shadows == (True,)
    data = scene_to_dict(scene, ds.RenderSettings(shadow_map_size=64, shadow_bias=2.0))
    assert [light.get("shadows", False) for light in data["lights"]] == [
        True, True, False, False, False, True, True]
    again, settings = scene_from_dict(data)
    assert again.lights.point.shadows == (True, False)
    assert again.lights.disk.shadows == (False, True) and again.lights.sphere.shadows == (True,)
    assert settings.shadow_map_size == 64 and settings.shadow_bias == 2.0


@pytest.mark.parametrize("make,message", [
    (lambda: ds.point_light((0, 1, 0), shadows="yes"),
     "shadows: got 'yes'; expected True or False"),
    (lambda: ds.area_light((0, 1, 0), normal=(0, -1, 0), radius=1.0, shadows=1),
     "shadows: got 1; expected True or False"),
    (lambda: ds.sphere_light((0, 1, 0), 0.5, shadows=None),
     "shadows: got None; expected True or False"),
    (lambda: ds.spot_light((0, 1, 0), (0, -1, 0), cutoff=85.0, shadows=True),
     "cutoff: got 85.0; expected at most 80 degrees for a spot with shadows"),
    (lambda: ds.RenderSettings(shadow_map_size=0), "shadow_map_size: got 0; expected an integer"),
    (lambda: ds.RenderSettings(shadow_bias=-1.0), "shadow_bias: got -1.0; expected a finite"),
    (lambda: ds.RenderSettings(shadow_softness=0.0), "shadow_softness: got 0.0; expected"),
])
def test_bad_shadow_input_is_refused_with_a_clear_message(make, message):
    with pytest.raises(ValueError) as err:
        make()
    assert str(err.value).startswith(message)


def test_scene_file_rejects_a_non_boolean_flag():
    data = {"mesh": {"builtin": {"icosphere": {"subdivisions": 0}}},
            "camera": {"eye": [0, 0, 3], "target": [0, 0, 0], "width": 8, "height": 8},
            "lights": [{"type": "point", "position": [0, 1, 0], "shadows": 1}]}
    expected = r"^lights\[0\].shadows: got 1; expected true or false"
    with pytest.raises(ds.SceneFileError, match=expected):
        scene_from_dict(data)


# ------------------------------------------------- area and sphere lights: penumbrae

DISK = ((-0.5, 2.0, -1.0), (0.0, -1.0, 0.0), 0.5)  # centre, emitting normal, radius
BALL = ((0.5, 2.0, -1.0), 0.4)  # a sphere light: centre, radius
AREA_POWER, AREA_SIZE, AREA_MAP = 4.0, 40, 64
# the penumbra's error, per unit of the light's brightest unshadowed floor pixel: mean and
# max over the penumbra's pixels. Set by the samples (a visible fraction moves in steps of
# about 1/samples; a sphere's samples cover its whole surface, so about half face a point:
# it gets 32) and the 64^2 maps. Measured: disk 0.021 and 0.085, sphere 0.029 and 0.155.
PENUMBRA_TOL = {"disk": (0.04, 0.15), "sphere": (0.05, 0.25)}
#: a rectangle light 1.2 x 0.3 emitting down (centre, edge_u, edge_v: edge_u x edge_v is
#: -y), elongated so that the penumbra's width differs across and along the sphere's shadow
RECT = ((-0.5, 2.0, -1.0), (1.2, 0.0, 0.0), (0.0, 0.0, 0.3))
#: measured: 0.020 and 0.069; with the rectangle's shadow-map sample points turned by 90
#: degrees (edge_u and edge_v swapped) 0.023 and 0.112, scaled by 1/2 0.054 and 0.18
RECT_TOL = (0.03, 0.09)


def penumbra_scene(camera, samples=(16, 32)):
    """The sphere over the floor under a disk light (red) and a sphere light (green), both
    with shadows; samples: the disk's and the sphere's."""
    lights = [ds.area_light(DISK[0], normal=DISK[1], radius=DISK[2], color=rgb(0, AREA_POWER),
                            samples=samples[0], shadows=True),
              ds.sphere_light(*BALL, rgb(1, AREA_POWER), samples=samples[1], shadows=True)]
    return ds.make_scene(GEOMETRY.mesh(2, 4), camera, lights, ds.material(ka=KA, kd=KD, ks=None),
                         global_ambient=GLOBAL)


def penumbra_camera():
    return ds.look_at((0.0, 4.5, 3.2), (0.0, -1.0, 0.5), width=AREA_SIZE, height=AREA_SIZE,
                      fov_y=40.0)


def assert_penumbra_matches(image, camera, name, light, tolerances):
    """One channel of a render [H, W] under one light against the ray-traced quadrature
    over the light: the penumbra within tolerances (mean, max) of the brightest floor
    pixel, the umbra ambient only, the lit floor the unshadowed light; and the
    tolerances tell the penumbra from the hard shadow of the light's centre."""
    points = GEOMETRY.floor_points(camera)
    on_floor, _ = GEOMETRY.shadow(camera, ("point", light[1]))
    floor = on_floor & ~near_edge(on_floor, width=1)
    seen, unshadowed = GEOMETRY.floor_irradiance(points, light, nodes=32)
    want = KA * GLOBAL + KD * AREA_POWER * seen
    scale = KD * AREA_POWER * unshadowed[floor].max()
    fraction = seen / np.where(unshadowed > 0, unshadowed, 1.0)
    penumbra = floor & (fraction > 0.02) & (fraction < 0.98)
    # the umbra and the fully lit floor: a pixel away from the penumbra (the icosphere
    # is inscribed in the reference's sphere, and the maps have texels)
    umbra = floor & (fraction <= 1e-9) & ~near_edge(fraction <= 1e-9, width=1)
    lit = floor & (fraction >= 1.0 - 1e-9) & ~near_edge(fraction >= 1.0 - 1e-9, width=1)
    assert penumbra.sum() >= 120 and umbra.sum() >= 10 and lit.sum() >= 250, name
    error = np.abs(image - want)
    mean_tol, max_tol = tolerances
    assert error[penumbra].mean() < mean_tol * scale, (name, error[penumbra].mean() / scale)
    assert error[penumbra].max() < max_tol * scale, (name, error[penumbra].max() / scale)
    # the umbra keeps only the ambient term; lit points the unshadowed light (its
    # samples' estimate of the irradiance: 1% for a disk, exact for a sphere and for a
    # rectangle's closed form)
    np.testing.assert_allclose(image[umbra], KA * GLOBAL, atol=1e-6, err_msg=name)
    np.testing.assert_allclose(image[lit], want[lit], atol=0.01 * scale, err_msg=name)
    _, hard = GEOMETRY.shadow(camera, ("point", light[1]))
    hard_error = np.abs(KD * AREA_POWER * unshadowed * ~hard - KD * AREA_POWER * seen)
    assert hard_error[penumbra].mean() > 2 * mean_tol * scale, name


def test_area_and_sphere_light_penumbrae_match_a_ray_traced_reference():
    camera = penumbra_camera()
    settings = ds.RenderSettings(shadow_map_size=AREA_MAP, clamp=False)
    image = np.asarray(ds.render(penumbra_scene(camera), settings), np.float64)
    references = {"disk": ("disk", *DISK), "sphere": ("sphere", *BALL)}
    for c, (name, light) in enumerate(references.items()):
        assert_penumbra_matches(image[..., c], camera, name, light, PENUMBRA_TOL[name])


def test_rectangle_light_penumbra_matches_a_ray_traced_reference():
    """A rectangle light (16 samples, emitting down) against the quadrature over its area,
    each node's ray tested against the sphere (analytic.SphereOverPlane)."""
    camera = penumbra_camera()
    light = ds.area_light(RECT[0], *RECT[1:], color=AREA_POWER, samples=16, shadows=True)
    scene = ds.make_scene(GEOMETRY.mesh(2, 4), camera, [light],
                          ds.material(ka=KA, kd=KD, ks=None), global_ambient=GLOBAL)
    settings = ds.RenderSettings(shadow_map_size=AREA_MAP, clamp=False)
    image = np.asarray(ds.render(scene, settings), np.float64)
    assert_penumbra_matches(image[..., 0], camera, "rect", ("rect", *RECT), RECT_TOL)


# cost: 66 s of CPU with -n 0 on the loaded 2-core machine, where the two tests it
# replaces (marked 78 and 90) took 36 and 38 s: scaled as they were
@pytest.mark.cost(150)
@pytest.mark.usefixtures("x64")
def test_soft_shadows_and_penumbrae_pass_check_grads_wrt_lights_and_geometry():
    """One program for every kind of shadow map: a cube map (point light), an orthographic
    map (directional; the spot's perspective map is a cube face's kind) and the penumbrae
    of a disk and a sphere light (two samples each), with respect to the lights' positions,
    directions and radii, the vertices and kd."""
    scene = tiny_scene(("point", "directional"))
    area = penumbra_scene(scene.camera, samples=(2, 2)).lights
    lights = ds.replace(scene.lights, disk=area.disk, sphere=area.sphere)
    weights = jnp.asarray(np.random.default_rng(0).uniform(0.5, 1.5, (12, 12, 4)))
    params = {"point": lights.point.position, "sun": lights.directional.direction,
              "disk": lights.disk.center, "radius": lights.disk.radius,
              "ball": lights.sphere.position, "ball_radius": lights.sphere.radius,
              "vertices": scene.mesh.vertices, "kd": scene.material.kd}

    def loss(p):
        groups = ds.replace(lights, point=ds.replace(lights.point, position=p["point"]),
                            directional=ds.replace(lights.directional, direction=p["sun"]),
                            disk=ds.replace(lights.disk, center=p["disk"], radius=p["radius"]),
                            sphere=ds.replace(lights.sphere, position=p["ball"],
                                              radius=p["ball_radius"]))
        s = ds.replace(scene, lights=groups, mesh=ds.replace(scene.mesh, vertices=p["vertices"]),
                       material=ds.replace(scene.material, kd=p["kd"]))
        return jnp.sum(weights * ds.render(s, TINY_SOFT))

    check_grads(jax.jit(loss), (params,), order=1, modes=("fwd", "rev"), eps=1e-6, atol=1e-5,
                rtol=1e-5)

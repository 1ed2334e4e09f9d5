"""Area and sphere lights against independent references, in float64.

- The rectangle's closed form (Lambert's formula with horizon clipping) against a dense
  midpoint quadrature over the rectangle in NumPy, at points that see it whole, partly
  below their horizon, edge-on and from behind.
- The sampled terms (disk, sphere, specular) against dense NumPy quadratures of the same
  integrals (over the disk in polar coordinates, over the sphere's surface).
- The radiometric convention: a tiny rectangle or disk renders as a spot light of
  exponent 1 and cutoff 90 along its normal with 1/d^2 attenuation, a sphere of any
  radius above the horizon as a point light with 1/d^2 attenuation.
- Gradients with respect to the light's centre and kd equal central differences.
"""

import re

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import make_mesh
from jax.test_util import check_grads
from test_structure import primitive_counts

from diffshade import (
    RenderSettings,
    area_light,
    look_at,
    make_scene,
    material,
    point_light,
    render,
    replace,
    scene_from_dict,
    sphere_light,
    spot_light,
)
from diffshade.io.scenefile import SceneFileError, scene_to_dict
from diffshade.shading.area import orthonormal_frame, rect_irradiance, sample_incidence, terms
from diffshade.shading.lighting import _light_terms

pytestmark = pytest.mark.usefixtures("x64")

RNG = np.random.default_rng(7)


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# Points and normals seeing a rectangle centred at the origin, emitting towards +z
# (edge_u x edge_v = +z), from every side: above, partly below their horizon, behind.
CENTRE, EDGE_U, EDGE_V = np.array([0.1, -0.2, 0.0]), np.array([1.2, 0.3, 0.0]), \
    np.array([-0.2, 0.8, 0.0])


def probe_points():
    points = np.array([[0.0, 0.0, 1.0], [0.5, 0.3, 0.7], [2.0, 0.0, 0.3], [-1.0, 1.0, 0.5],
                       [0.2, 0.1, 0.4], [0.3, 0.0, -1.0], [0.0, 0.0, 3.0], [1.5, -1.0, 0.8]])
    normals = unit(np.array([[0.0, 0.0, -1.0], [0.3, -0.2, -1.0], [-1.0, 0.0, 0.0],
                             [0.6, -0.7, 0.2], [1.0, 0.2, -0.3], [0.0, 0.0, 1.0],
                             [0.1, 0.2, -1.0], [-0.5, 0.6, -0.4]]))
    return points, normals


def planar_quadrature(corner_at, area, emit_normal, points, normals, weight, grid=600):
    """(1 / A) integral over the light of max(n.w, 0) max(-n_L.w, 0) / r^2 dA; corner_at
    maps [G, G] grid coordinates to light points [G, G, 3] with Jacobian weight / (G^2)."""
    s = (np.arange(grid) + 0.5) / grid
    q, jac = corner_at(*np.meshgrid(s, s, indexing="ij"))
    out = []
    for p, n in zip(points, normals, strict=True):
        to = q - p
        r2 = np.sum(to * to, -1)
        w = to / np.sqrt(r2)[..., None]
        f = np.maximum(w @ n, 0) * np.maximum(-(w @ emit_normal), 0) / r2
        out.append(np.sum(f * jac) / area)
    return np.array(out)


def rect_quadrature(points, normals):
    def at(s, t):
        q = CENTRE + (s - 0.5)[..., None] * EDGE_U + (t - 0.5)[..., None] * EDGE_V
        return q, np.full(s.shape, 1.0 / s.size)
    return planar_quadrature(at, 1.0, unit(np.cross(EDGE_U, EDGE_V)), points, normals, 1.0)


def test_rect_closed_form_matches_quadrature_with_horizon_clipping():
    points, normals = probe_points()
    light = area_light(CENTRE, EDGE_U, EDGE_V)
    got = np.asarray(rect_irradiance(light, points, normals))[:, 0]
    want = rect_quadrature(points, normals)
    assert want[5] == 0 and np.sum(want > 0) >= 6  # one point behind, the rest lit
    np.testing.assert_allclose(got, want, rtol=2e-3, atol=1e-6)


def sampled_estimates(light, kind, points, normals):
    """E estimated by the light's own sample pattern: sum_j w_j max(N.L_j, 0)."""
    pattern, at = sample_incidence(kind, light, points)
    total = 0.0
    for sample in pattern:
        light_dir, weight = at(sample)
        total = total + np.asarray(weight)[:, 0] * np.maximum(
            np.sum(np.asarray(light_dir) * normals, -1), 0)
    return total


def test_sampled_disk_matches_polar_quadrature():
    radius, normal = 0.7, unit(np.array([0.2, -0.1, 1.0]))
    light = area_light(CENTRE, normal=normal, radius=radius, samples=256)
    t1, t2 = (np.asarray(t) for t in orthonormal_frame(np.asarray(light.normal)))

    def at(s, t):
        r, phi = radius * s, 2 * np.pi * t
        q = CENTRE + (r * np.cos(phi))[..., None] * t1 + (r * np.sin(phi))[..., None] * t2
        return q, r * radius * 2 * np.pi / s.size
    points, normals = probe_points()
    want = planar_quadrature(at, np.pi * radius**2, normal, points, normals, 1.0)
    got = sampled_estimates(light, "disk", points, normals)
    np.testing.assert_allclose(got, want, rtol=3e-2, atol=2e-3 * want.max())


def sphere_quadrature(position, radius, points, normals, grid=800):
    """(1 / (pi R^2)) integral over the sphere's surface of max(n.w, 0) max(n_s.(-w), 0)
    / r^2 dA: only the surface facing the point counts, which is what it sees."""
    theta = (np.arange(grid) + 0.5) / grid * np.pi
    phi = (np.arange(2 * grid) + 0.5) / (2 * grid) * 2 * np.pi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    ns = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    da = radius**2 * np.sin(th) * (np.pi / grid) * (np.pi / grid)
    out = []
    for p, n in zip(points, normals, strict=True):
        to = position + radius * ns - p
        r2 = np.sum(to * to, -1)
        w = to / np.sqrt(r2)[..., None]
        f = np.maximum(w @ n, 0) * np.maximum(-np.sum(ns * w, -1), 0) / r2
        out.append(np.sum(f * da) / (np.pi * radius**2))
    return np.array(out)


def test_sampled_sphere_matches_surface_quadrature():
    position, radius = np.array([0.0, 0.2, 0.5]), 0.4
    points, normals = probe_points()
    points = points + np.array([0.0, 0.0, 0.6])  # every point outside the sphere
    light = sphere_light(position, radius, samples=256)
    want = sphere_quadrature(position, radius, points, normals)
    got = sampled_estimates(light, "sphere", points, normals)
    np.testing.assert_allclose(got, want, rtol=3e-2, atol=2e-3 * want.max())


def test_sampled_specular_matches_quadrature():
    """ks Is times the integral of [N.L > 0] max(N.H, 0)^n max(-n_L.w, 0) / r^2 / A."""
    light = area_light(CENTRE, EDGE_U, EDGE_V, samples=1024)
    points, normals = probe_points()
    keep = [0, 1, 3, 6]
    points, normals = points[keep], normals[keep]
    # viewers near the mirror direction of the light's centre: the highlight is on it
    to_centre = unit(CENTRE - points)
    mirror = 2 * np.sum(normals * to_centre, -1, keepdims=True) * normals - to_centre
    views = unit(mirror + np.array([0.1, -0.05, 0.0]))
    mat = material(ka=0.0, kd=0.0, ks=1.0, shininess=8.0)
    _, _, got = terms("rect", light, mat, points, normals, views, RenderSettings(),
                      _light_terms)
    grid = 500
    s = (np.arange(grid) + 0.5) / grid
    ss, tt = np.meshgrid(s, s, indexing="ij")
    q = CENTRE + (ss - 0.5)[..., None] * EDGE_U + (tt - 0.5)[..., None] * EDGE_V
    emit = unit(np.cross(EDGE_U, EDGE_V))
    for p, n, v, g in zip(points, normals, views, np.asarray(got), strict=True):
        to = q - p
        r2 = np.sum(to * to, -1)
        w = to / np.sqrt(r2)[..., None]
        lobe = np.maximum(unit(w + v) @ n, 0) ** 8.0 * (w @ n > 0)
        want = np.mean(lobe * np.maximum(-(w @ emit), 0) / r2)
        np.testing.assert_allclose(g, want, rtol=3e-2, atol=1e-3 * want)


# ------------------------------------------------------------------ renders and limits

SIZE = 12


def scene_with(light, mat=None):
    quad = make_mesh([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], [[0, 1, 2], [0, 2, 3]])
    cam = look_at((0.2, 0.1, 3.0), (0.0, 0.0, 0.0), width=SIZE, height=SIZE, fov_y=45.0)
    mat = mat or material(ka=0.1, kd=(0.8, 0.6, 0.4), ks=0.5, shininess=12.0)
    return make_scene(quad, cam, [light], mat, global_ambient=0.0)


AT = (0.3, -0.2, 1.5)
DOWN = (0.2, 0.1, -1.0)


def test_tiny_planar_lights_render_as_a_cosine_spot_with_inverse_square_falloff():
    spot = spot_light(AT, DOWN, 2.0, exponent=1.0, cutoff=90.0, attenuation=(0, 0, 1))
    want = np.asarray(render(scene_with(spot)))
    d = np.array(DOWN) / np.linalg.norm(DOWN)
    tangent = np.cross(d, [1.0, 0.0, 0.0])
    # the error is O(size^2 / d^2) for the closed form (at 1e-3: Lambert's formula; at
    # 1e-8: its point limit), O(size / d) for a jittered sample pattern
    for light, atol in ((area_light(AT, 1e-3 * tangent, 1e-3 * np.cross(d, tangent),
                                    color=2.0), 1e-5),
                        (area_light(AT, 1e-8 * tangent, 1e-8 * np.cross(d, tangent),
                                    color=2.0), 1e-12),
                        (area_light(AT, normal=DOWN, radius=1e-8, color=2.0, samples=4), 1e-7)):
        np.testing.assert_allclose(render(scene_with(light)), want, atol=atol)


def test_a_sphere_above_the_horizon_renders_as_a_point_light_with_inverse_square_falloff():
    bulb = point_light(AT, 2.0, attenuation=(0, 0, 1))
    want = np.asarray(render(scene_with(bulb, material(ka=0.1, kd=(0.8, 0.6, 0.4)))))
    for radius in (0.0, 1e-6):
        got = render(scene_with(sphere_light(AT, radius, 2.0, samples=4),
                                material(ka=0.1, kd=(0.8, 0.6, 0.4))))
        np.testing.assert_allclose(got, want, atol=1e-6 if radius else 1e-12)
    # a large sphere too, to the stratified estimate's accuracy (the diffuse integral of
    # the cone is exactly cos / d^2 while it is above the horizon)
    big = render(scene_with(sphere_light(AT, 0.5, 2.0, samples=64),
                            material(ka=0.1, kd=(0.8, 0.6, 0.4))))
    np.testing.assert_allclose(big, want, atol=5e-3)


LIGHTS = {  # builders: the lights must be made inside the test, in float64
    "rect": lambda: area_light((0.3, -0.2, 1.2), (0.6, 0.1, 0.0), (0.0, 0.5, 0.1), samples=4),
    "disk": lambda: area_light((0.3, -0.2, 1.2), normal=DOWN, radius=0.4, samples=4),
    "sphere": lambda: sphere_light((0.3, -0.2, 1.2), 0.3, samples=4),
}


@pytest.mark.parametrize("kind", LIGHTS)
def test_gradients_wrt_light_centre_and_kd_equal_central_differences(kind):
    light = LIGHTS[kind]()
    scene = scene_with(light)
    settings = RenderSettings(clamp=False)
    weights = np.random.default_rng(3).uniform(0.5, 1.5, (SIZE, SIZE, 4))
    field = "position" if hasattr(light, "position") else "center"

    def loss(centre, kd):
        lights = replace(scene.lights, **{
            name: replace(group, **{field: centre[None]})
            for name in ("rect", "disk", "sphere")
            if (group := getattr(scene.lights, name)) is not None})
        s = replace(scene, lights=lights, material=replace(scene.material, kd=kd))
        return jnp.sum(weights * render(s, settings))

    check_grads(loss, (getattr(light, field), scene.material.kd), order=1, modes=["rev"],
                eps=1e-6, atol=1e-6, rtol=1e-6)


def test_bad_area_lights_are_rejected_with_the_argument_named():
    cases = {
        "edge_u, normal: got both": dict(edge_u=(1, 0, 0), edge_v=(0, 1, 0), normal=(0, 0, 1),
                                         radius=1.0),
        "edge_u, normal: got neither": {},
        "radius: got -1": dict(normal=(0, 0, 1), radius=-1),
        "radius: missing": dict(normal=(0, 0, 1)),
        "normal: got": dict(normal=(0, 0, 0), radius=1.0),
        "samples: got 0": dict(normal=(0, 0, 1), radius=1.0, samples=0),
        "edge_v: got": dict(edge_u=(1, 0, 0), edge_v=(1, 0)),
    }
    for message, kwargs in cases.items():
        with pytest.raises(ValueError, match=message):
            area_light((0, 0, 1), **kwargs)
    with pytest.raises(ValueError, match="radius: got"):
        sphere_light((0, 0, 1), float("inf"))
    base = scene_with(sphere_light((0, 0, 1), 0.1, samples=4))
    two = [sphere_light((0, 0, 1), 0.1, samples=4), sphere_light((0, 0, 2), 0.1, samples=8)]
    with pytest.raises(ValueError, match=r"lights\[1\].samples: got 8; expected 4"):
        make_scene(base.mesh, base.camera, two)


def test_scene_files_read_and_write_area_lights_and_kt():
    data = {
        "mesh": {"builtin": {"box": {"size": [1, 1, 1]}}},
        "camera": {"eye": [0, 0, 3], "target": [0, 0, 0], "width": 8, "height": 8},
        "lights": [
            {"type": "area", "center": [0, 0, 2], "edge_u": [1, 0, 0], "edge_v": [0, -1, 0],
             "color": 2, "samples": 8},
            {"type": "area", "center": [1, 0, 2], "normal": [0, 0, -1], "radius": 0.5},
            {"type": "sphere", "position": [0, 1, 2], "radius": 0.2, "ambient": 0.1},
        ],
        "material": {"kd": 0.5, "kt": [0.1, 0.2, 0.3]},
    }
    scene, settings = scene_from_dict(data)
    assert scene.lights.rect.samples == 8 and scene.lights.disk.samples == 16
    np.testing.assert_allclose(scene.lights.rect.diffuse[0], 2.0)
    np.testing.assert_allclose(scene.lights.sphere.radius[0], 0.2)
    np.testing.assert_allclose(scene.material.kt, [0.1, 0.2, 0.3])
    back, _ = scene_from_dict(scene_to_dict(scene, settings))
    np.testing.assert_allclose(render(back), render(scene), atol=1e-12)
    for light, message in (
            ({"type": "area", "center": [0, 0, 2]},
             "lights[0].edge_u, lights[0].normal: got neither"),
            ({"type": "sphere", "position": [0, 0, 2], "radius": -1}, "lights[0].radius: got -1"),
            ({"type": "area", "center": [0, 0, 2], "normal": [0, 0, 1], "radius": 1,
              "samples": 0}, "lights[0].samples: got 0; expected a positive integer")):
        with pytest.raises(SceneFileError, match=re.escape(message)):
            scene_from_dict({**data, "lights": [light]})
    with pytest.raises(SceneFileError, match=re.escape("material.kt: got 2")):
        scene_from_dict({**data, "material": {"kt": 2}})


def test_only_scenes_with_extended_lights_compile_their_code():
    plain = primitive_counts(scene_with(point_light(AT, 1.0), material(kd=0.5)))
    rect = primitive_counts(scene_with(LIGHTS["rect"](), material(kd=0.5)))
    rect_glossy = primitive_counts(scene_with(LIGHTS["rect"]()))
    disk = primitive_counts(scene_with(LIGHTS["disk"](), material(kd=0.5)))
    assert plain["atan2"] == plain["scan"] == 0
    assert rect["atan2"] >= 1 and rect["scan"] == 0  # the closed form: no samples
    assert rect_glossy["scan"] == 1  # the specular term is sampled
    assert disk["scan"] == 1 and disk["atan2"] == 0

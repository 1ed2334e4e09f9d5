"""The mesh pipeline against an exact, ray-traced sphere (diffshade.analytic).

An icosphere rendered with Phong shading must converge to the exact sphere as it is
subdivided; this checks projection, rasterization, perspective-correct interpolation and
shading end to end against geometry that is not a mesh.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import diffshade as ds
from diffshade.analytic import camera_rays, intersect_sphere, render_analytic_sphere


def sphere_scene(subdivisions, size=64, local_viewer=False):
    return ds.make_scene(
        ds.icosphere(subdivisions),
        ds.look_at((0.3, 0.2, 3.0), (0.0, 0.0, 0.0), width=size, height=size, fov_y=40.0),
        [ds.directional_light((-1.0, -1.0, -1.0)), ds.point_light((2.0, 2.0, 2.0), 0.5)],
        ds.material(ka=0.2, kd=(0.7, 0.3, 0.2), ks=0.5, shininess=30.0),
        local_viewer=local_viewer)


def test_fine_icosphere_matches_exact_sphere():
    scene = sphere_scene(6, local_viewer=True)
    settings = ds.RenderSettings(shading="phong")
    mesh_img = np.asarray(ds.render(scene, settings))
    exact = np.asarray(render_analytic_sphere(scene, settings))
    both = (mesh_img[..., 3] == 1) & (exact[..., 3] == 1)
    assert both.sum() > 0.3 * both.size
    assert np.abs(mesh_img[..., :3] - exact[..., :3])[both].max() < 1.0 / 255


def test_error_decreases_with_subdivision():
    settings = ds.RenderSettings(shading="phong")
    exact = np.asarray(render_analytic_sphere(sphere_scene(1), settings))
    errors = []
    for level in (1, 3, 5):
        img = np.asarray(ds.render(sphere_scene(level), settings))
        errors.append(np.sqrt(np.mean((img[..., :3] - exact[..., :3]) ** 2)))
    assert all(a > b for a, b in zip(errors, errors[1:], strict=False))


def test_ray_hits_match_closed_form():
    cam = ds.look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), width=8, height=8, fov_y=30.0)
    origins, dirs = camera_rays(cam, jnp.zeros((1, 2)))
    t, hit = intersect_sphere(origins, dirs, jnp.zeros(3), 1.5)
    assert bool(hit[0]) and float(t[0]) == pytest.approx(3.5, abs=1e-5)
    origins, dirs = camera_rays(cam, jnp.array([[1.0, 1.0]]))
    half = np.tan(np.radians(15.0))
    expected = np.array([half, half, -1.0]) / np.linalg.norm([half, half, -1.0])
    np.testing.assert_allclose(np.asarray(dirs[0]), expected, atol=1e-6)

"""The conversions of docs/light-units.md: a light given in physical units (radiant
intensity, power, irradiance, radiance) and converted as the page says lights a diffuse
plane of albedo rho, fitted as kd = rho, with the radiance a physically based renderer
computes, rho / pi * (irradiance), written here from the physics and not from diffshade.

The scene: a plane z = 0 seen from (0, 0, 3) by a 17 x 17 camera, whose centre pixel (8, 8)
samples the view axis, so it shows the plane point (0, 0, 0) with normal +z.
"""

import math

import numpy as np
import pytest

import diffshade as ds

ALBEDO = 0.6
PLANE = ds.mesh_from_arrays([[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]],
                            [[0, 1, 2], [0, 2, 3]])
CAMERA = ds.look_at((0, 0, 3), (0, 0, 0), width=17, height=17)


def centre_pixel(lights, global_ambient=0.0, ka=0.0):
    scene = ds.make_scene(PLANE, CAMERA, lights, ds.material(ka=ka, kd=ALBEDO),
                          global_ambient=global_ambient)
    return float(np.asarray(ds.render(scene, ds.RenderSettings(clamp=False)))[8, 8, 0])


def lambert(irradiance):
    """Radiance leaving a Lambertian surface of albedo ALBEDO: rho / pi * E."""
    return ALBEDO / math.pi * irradiance


def geometry(position):
    """(d^2, cos theta) from the plane point (0, 0, 0), normal +z, to `position`."""
    d2 = float(np.dot(position, position))
    return d2, position[2] / math.sqrt(d2)


@pytest.mark.parametrize("position", [(0.0, 0.0, 2.0), (1.0, 0.0, 1.5), (-0.3, 0.7, 0.4)])
def test_radiant_intensity_over_pi_with_inverse_square(position):
    intensity = 10.0  # W/sr
    d2, cos = geometry(position)
    light = ds.point_light(position, intensity / math.pi, attenuation=(0, 0, 1))
    assert centre_pixel([light]) == pytest.approx(lambert(intensity * cos / d2), rel=1e-5)


def test_power_of_an_isotropic_bulb_over_four_pi_squared():
    power, position = 100.0, (1.0, 0.0, 1.5)  # W; intensity power / (4 pi) W/sr
    d2, cos = geometry(position)
    light = ds.point_light(position, power / (4 * math.pi**2), attenuation=(0, 0, 1))
    want = lambert(power / (4 * math.pi) * cos / d2)
    assert centre_pixel([light]) == pytest.approx(want, rel=1e-5)
    assert want == pytest.approx(0.38910, abs=1e-5)  # docs/light-units.md's worked example


def test_irradiance_of_a_distant_light_over_pi():
    irradiance, travel = 3.0, np.array([0.6, 0.0, -0.8])  # W/m^2 on a surface facing it
    light = ds.directional_light(travel, irradiance / math.pi)
    assert centre_pixel([light]) == pytest.approx(lambert(irradiance * 0.8), rel=1e-5)


def test_sphere_emitter_radiance_times_radius_squared():
    # a uniform sphere of radiance L above the horizon: E = pi L R^2 cos / d^2 (small, so
    # that the sampled cone's error stays below the tolerance)
    radiance, radius, position = 5e4, 0.003, (0.5, 0.2, 1.5)
    d2, cos = geometry(position)
    light = ds.sphere_light(position, radius, radiance * radius**2, samples=4)
    want = lambert(math.pi * radiance * radius**2 * cos / d2)
    assert centre_pixel([light]) == pytest.approx(want, rel=1e-3)


def test_small_rectangle_radiance_times_area_over_pi():
    # a small Lambertian emitter of radiance L facing the point: E ~ L A cos cos' / d^2
    radiance, side, height = 20.0, 0.01, 2.0
    light = ds.area_light((0, 0, height), (side, 0, 0), (0, -side, 0),
                          color=radiance * side**2 / math.pi, samples=4)
    want = lambert(radiance * side**2 / height**2)
    assert centre_pixel([light]) == pytest.approx(want, rel=1e-4)


def test_uniform_environment_radiance_is_the_ambient_colour():
    # uniform radiance L from the hemisphere: E = pi L, so the surface reflects rho L
    radiance = 0.7
    assert centre_pixel([], global_ambient=radiance, ka=ALBEDO) == pytest.approx(
        lambert(math.pi * radiance), rel=1e-6)

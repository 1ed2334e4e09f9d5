"""A light's default colours when only some are given (OpenGL's glLightfv defaults, as
docs/scene-format.md states them): ambient 0, and diffuse and specular `color`, default
white. So a light given only `diffuse` keeps a white specular colour; it does not copy its
diffuse colour. Checked by the API and by the scene file, for every light type, against the
values written out by hand, and in a render against the closed form of a plane lit and
seen along its normal (N.L = N.H = 1).
"""

import numpy as np
import pytest

import diffshade as ds
from diffshade.io.scenefile import scene_from_dict

DIFFUSE = (0.2, 0.4, 0.6)
#: each light type given only a diffuse colour: (API factory call, scene-file object, the
#: LightGroups field it lands in)
ONLY_DIFFUSE = {
    "directional": (lambda: ds.directional_light((0, 0, -1), diffuse=DIFFUSE),
                    {"direction": [0, 0, -1]}, "directional"),
    "point": (lambda: ds.point_light((0, 0, 2), diffuse=DIFFUSE), {"position": [0, 0, 2]},
              "point"),
    "spot": (lambda: ds.spot_light((0, 0, 2), (0, 0, -1), diffuse=DIFFUSE),
             {"position": [0, 0, 2], "direction": [0, 0, -1]}, "spot"),
    "area": (lambda: ds.area_light((0, 0, 2), (1, 0, 0), (0, 1, 0), diffuse=DIFFUSE),
             {"center": [0, 0, 2], "edge_u": [1, 0, 0], "edge_v": [0, 1, 0]}, "rect"),
    "sphere": (lambda: ds.sphere_light((0, 0, 2), 0.1, diffuse=DIFFUSE),
               {"position": [0, 0, 2], "radius": 0.1}, "sphere"),
}


def scene_file(lights, material=None):
    """A scene-file dict: a plane-like quad at z = 0 seen from +z (orthographic)."""
    return {"version": 1,
            "mesh": {"vertices": [[-2, -2, 0], [2, -2, 0], [2, 2, 0], [-2, 2, 0]],
                     "faces": [[0, 1, 2], [0, 2, 3]]},
            "camera": {"eye": [0, 0, 3], "target": [0, 0, 0], "width": 4, "height": 4,
                       "projection": "orthographic", "ortho_height": 2},
            "lights": lights, "material": material or {}}


def assert_colours(light):
    np.testing.assert_allclose(np.reshape(light.ambient, -1), [0.0, 0.0, 0.0])
    np.testing.assert_allclose(np.reshape(light.diffuse, -1), DIFFUSE, rtol=1e-6)
    np.testing.assert_allclose(np.reshape(light.specular, -1), [1.0, 1.0, 1.0])


@pytest.mark.parametrize("kind", ONLY_DIFFUSE)
def test_a_light_given_only_diffuse_has_a_white_specular_colour_by_api(kind):
    assert_colours(ONLY_DIFFUSE[kind][0]())


@pytest.mark.parametrize("kind", ONLY_DIFFUSE)
def test_a_light_given_only_diffuse_has_a_white_specular_colour_by_scene_file(kind):
    _, fields, group = ONLY_DIFFUSE[kind]
    light = {"type": kind, **fields, "diffuse": list(DIFFUSE)}
    scene, _ = scene_from_dict(scene_file([light]))
    assert_colours(getattr(scene.lights, group))


def test_the_specular_highlight_takes_the_white_default_not_the_diffuse_colour():
    """ka 0, kd 0.5, ks 0.7 lit along the normal and seen along it (directional light,
    infinite viewer): diffuse part kd * DIFFUSE, specular part ks * (1, 1, 1) at every
    pixel, by the API and by the scene file."""
    material = {"ka": 0.0, "kd": 0.5, "ks": 0.7, "shininess": 5.0}
    light = {"type": "directional", "direction": [0, 0, -1], "diffuse": list(DIFFUSE)}
    from_file, _ = scene_from_dict(scene_file([light], material))
    by_api = ds.make_scene(from_file.mesh, from_file.camera,
                           [ds.directional_light((0, 0, -1), diffuse=DIFFUSE)],
                           ds.material(**material))
    for scene in (from_file, by_api):
        parts = ds.render_parts(scene)
        np.testing.assert_allclose(parts.diffuse, np.broadcast_to(0.5 * np.array(DIFFUSE),
                                                                  (4, 4, 3)), rtol=1e-6)
        np.testing.assert_allclose(parts.specular, np.full((4, 4, 3), 0.7), rtol=1e-6)

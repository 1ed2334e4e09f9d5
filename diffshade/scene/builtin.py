"""Built-in demo scenes, by name: `builtin_scene(name, width, height) -> Scene`.

Each is one lit object at the origin seen by a perspective camera, built through the
public API; `BUILTIN_SCENES` lists the names. examples/sphere.json is the "sphere" scene
written as a scene file. Render them with `RenderSettings()` or
`diffshade render --builtin NAME -o OUT.png`.
"""

from diffshade.scene.camera import look_at
from diffshade.scene.lights import ambient_light, directional_light, point_light, spot_light
from diffshade.scene.materials import material
from diffshade.scene.mesh import box, icosphere, model_matrix, torus
from diffshade.scene.scene import Scene, make_scene

__all__ = ["BUILTIN_SCENES", "builtin_scene"]


def _sphere(width, height) -> Scene:
    """A red glossy sphere: a white key light from the upper left, a warm point light."""
    camera = look_at((0.0, 0.0, 3.5), (0.0, 0.0, 0.0), width=width, height=height)
    lights = [
        directional_light((1.0, -1.0, -1.0), 0.8),
        point_light((2.0, 1.5, 2.5), (0.5, 0.45, 0.4), attenuation=(1.0, 0.0, 0.05)),
    ]
    red = material(ka=(0.6, 0.12, 0.1), kd=(0.7, 0.15, 0.1), ks=0.6, shininess=40.0)
    return make_scene(icosphere(4, 1.0), camera, lights, red, background=(0.05, 0.05, 0.08))


def _torus(width, height) -> Scene:
    """A blue torus seen from above, lit by a spot light and a dim ambient light."""
    camera = look_at((0.0, 2.5, 3.0), (0.0, 0.0, 0.0), width=width, height=height)
    lights = [
        spot_light((0.0, 3.0, 1.5), (0.0, -3.0, -1.5), 0.9, cutoff=18.0, exponent=4.0),
        ambient_light(0.15),
    ]
    blue = material(ka=(0.1, 0.2, 0.5), kd=(0.15, 0.3, 0.75), ks=0.5, shininess=60.0)
    return make_scene(torus(1.0, 0.35, 48, 24), camera, lights, blue, global_ambient=0.1)


def _box(width, height) -> Scene:
    """A yellow unit cube turned to show three sides (flat side normals)."""
    camera = look_at((0.0, 0.0, 3.5), (0.0, 0.0, 0.0), width=width, height=height)
    lights = [
        directional_light((-0.4, -1.0, -0.6), 0.8),
        point_light((-1.5, 0.5, 3.0), 0.5),
    ]
    yellow = material(ka=(0.5, 0.45, 0.1), kd=(0.8, 0.7, 0.2), ks=0.3, shininess=20.0)
    model = model_matrix(rotate_deg=(25.0, 35.0, 0.0))
    return make_scene(box((1.0, 1.0, 1.0)), camera, lights, yellow, model=model)


_BUILDERS = {"sphere": _sphere, "torus": _torus, "box": _box}
BUILTIN_SCENES = tuple(_BUILDERS)


def builtin_scene(name, width=256, height=256) -> Scene:
    """The built-in scene `name` (one of BUILTIN_SCENES) rendered at width x height pixels."""
    if name not in _BUILDERS:
        raise ValueError(f"name: got {name!r}; expected one of {BUILTIN_SCENES}")
    return _BUILDERS[name](width, height)

"""The scene's structure decides what is compiled, and only the structure.

Markers, counted over the render's jaxpr and all its sub-jaxprs:
- the spot path is the only user of `cos` (the cone's cutoff angle);
- `exp`/`log` come only from safe_pow, used by the specular power and the spot exponent,
  so a directional-only scene without `ks` has none;
- attenuation and the spot cone add equations: the equation count grows when a point or
  spot light is added to a directional-only scene.
Recompilation is observed with the jitted `render`'s own cache size.
"""

import collections

import jax
import numpy as np
from jax.extend import core as jex_core

from diffshade import (
    RenderSettings,
    directional_light,
    icosphere,
    look_at,
    make_scene,
    material,
    point_light,
    render,
    replace,
    spot_light,
)

SETTINGS = RenderSettings()


def primitive_counts(scene, settings=SETTINGS):
    """Counter of primitive names in the jaxpr of render(scene), sub-jaxprs included."""
    counts = collections.Counter()

    def walk(jaxpr):
        for eqn in jaxpr.eqns:
            counts[eqn.primitive.name] += 1
            for param in eqn.params.values():
                for sub in param if isinstance(param, (list, tuple)) else [param]:
                    if isinstance(sub, jex_core.ClosedJaxpr):
                        walk(sub.jaxpr)
                    elif isinstance(sub, jex_core.Jaxpr):
                        walk(sub)

    walk(jax.make_jaxpr(lambda s: render(s, settings))(scene).jaxpr)
    return counts


def scene_with(lights, mat=None, size=8):
    cam = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=size, height=size)
    return make_scene(icosphere(0), cam, lights, mat or material())


SUN = directional_light((0.0, -1.0, -1.0))
BULB = point_light((0.0, 1.0, 2.0), attenuation=(1.0, 0.1, 0.01))
SPOT = spot_light((0.0, 0.0, 2.0), (0.0, 0.0, -1.0), cutoff=30.0, exponent=2.0)


def test_directional_only_scene_compiles_no_spot_or_attenuation_code():
    sun = primitive_counts(scene_with([SUN]))
    with_bulb = primitive_counts(scene_with([SUN, BULB]))
    with_spot = primitive_counts(scene_with([SUN, SPOT]))
    assert sun["cos"] == 0 and sun["exp"] == 0 and sun["log"] == 0
    assert with_spot["cos"] >= 1 and with_spot["exp"] >= 1
    assert sum(with_bulb.values()) > sum(sun.values())
    assert sum(with_spot.values()) > sum(with_bulb.values())


def test_material_without_ks_compiles_no_specular_code():
    plain = primitive_counts(scene_with([SUN], material(ks=None)))
    shiny = primitive_counts(scene_with([SUN], material(ks=0.5, shininess=10.0)))
    assert plain["exp"] == 0 and plain["log"] == 0
    assert shiny["exp"] >= 1 and shiny["log"] >= 1
    assert sum(shiny.values()) > sum(plain.values())


def test_new_values_with_the_same_structure_do_not_recompile():
    # an image size no other test uses, so that the first render is a fresh compile
    scene = scene_with([SUN, BULB], material(ka=0.1, kd=0.5, ks=0.3, shininess=5.0), size=11)
    first = np.asarray(render(scene))
    size = render._cache_size()
    changed = replace(
        scene, material=material(ka=0.3, kd=0.2, ks=0.9, shininess=60.0),
        lights=replace(scene.lights, point=replace(scene.lights.point,
                                                   position=scene.lights.point.position + 0.5)),
        global_ambient=scene.global_ambient * 2.0, background=scene.background + 0.25)
    second = np.asarray(render(changed))
    assert render._cache_size() == size
    assert np.abs(second - first).max() > 0.05  # the new values did take effect


def test_a_new_structure_does_recompile():
    # the control for the test above: dropping ks changes the pytree, so render retraces
    scene = scene_with([SUN], material(ks=0.5, shininess=10.0), size=13)
    render(scene)
    size = render._cache_size()
    render(replace(scene, material=material(ks=None)))
    assert render._cache_size() == size + 1


def test_a_jitted_render_traces_once_for_new_material_values():
    traces = []

    @jax.jit
    def brightness(scene):
        traces.append(1)  # runs only while tracing
        return render(scene, SETTINGS)[..., :3].sum()

    scene = scene_with([SUN], material(ka=0.1, kd=0.5, ks=0.3, shininess=5.0), size=9)
    first = brightness(scene)
    second = brightness(replace(scene, material=material(ka=0.3, kd=0.2, ks=0.6,
                                                         shininess=9.0)))
    assert len(traces) == 1 and first != second

"""The scene's structure decides what is compiled, and only the structure.

Markers, counted over the render's jaxpr and all its sub-jaxprs:
- the spot path is the only user of `cos` (the cone's cutoff angle);
- `exp`/`log` come only from safe_pow, used by the specular power and the spot exponent,
  so a directional-only scene without `ks` has none;
- attenuation and the spot cone add equations: the equation count grows when a point or
  spot light is added to a directional-only scene.
- a scene of one object (make_scene(objects=[one])) compiles exactly the program of the
  same scene built from a mesh; a scene of several gathers each stacked material field
  per sample (a gather whose table has a leading object axis), and only such a scene.
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
    model_matrix,
    point_light,
    render,
    replace,
    scene_object,
    spot_light,
)

SETTINGS = RenderSettings()


def equations(scene, settings=SETTINGS):
    """Every equation of the jaxpr of render(scene), sub-jaxprs included."""
    found = []

    def walk(jaxpr):
        for eqn in jaxpr.eqns:
            found.append(eqn)
            for param in eqn.params.values():
                for sub in param if isinstance(param, (list, tuple)) else [param]:
                    if isinstance(sub, jex_core.ClosedJaxpr):
                        walk(sub.jaxpr)
                    elif isinstance(sub, jex_core.Jaxpr):
                        walk(sub)

    walk(jax.make_jaxpr(lambda s: render(s, settings))(scene).jaxpr)
    return found


def primitive_counts(scene, settings=SETTINGS):
    """Counter of primitive names in the jaxpr of render(scene), sub-jaxprs included."""
    return collections.Counter(eqn.primitive.name for eqn in equations(scene, settings))


def gather_tables(scene, settings=SETTINGS):
    """Counter of the shapes of the tables (first operands) that gathers read from."""
    return collections.Counter(eqn.invars[0].aval.shape for eqn in equations(scene, settings)
                               if eqn.primitive.name == "gather")


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


# ------------------------------------------------------------------- several objects

SOFT = RenderSettings(raster="soft")
RED, BLUE = material(kd=(0.8, 0.1, 0.1)), material(kd=(0.1, 0.1, 0.8), ks=0.5, shininess=9.0)


def objects_scene(count, two_sided=False, size=8):
    """`count` icospheres in a row, the second with a back material, via `objects`."""
    cam = look_at((0.0, 0.0, 4.0), (0.0, 0.0, 0.0), width=size, height=size)
    objects = [scene_object(icosphere(0), (RED, BLUE)[i % 2],
                            transform=model_matrix((1.2 * i - 0.6 * (count - 1), 0.0, 0.0)),
                            back_material=material(kd=0.3) if i % 2 else None)
               for i in range(count)]
    return make_scene(objects=objects, camera=cam, lights=[SUN, BULB], two_sided=two_sided)


def test_one_object_compiles_the_program_of_a_scene_built_from_a_mesh():
    for two_sided in (False, True):
        one = objects_scene(1, two_sided)
        plain = make_scene(icosphere(0), one.camera, [SUN, BULB], RED, model=one.model,
                           two_sided=two_sided)
        for settings in (SETTINGS, SOFT):
            program = str(jax.make_jaxpr(lambda s, st=settings: render(s, st))(one))
            assert program == str(jax.make_jaxpr(lambda s, st=settings: render(s, st))(plain))
            # no per-object gather leaked in: no table with a leading axis of one object
            assert not [t for t in gather_tables(one, settings) if t[:1] == (1,)]


def test_several_objects_gather_each_material_field_per_sample():
    for two_sided in (False, True):
        scene = objects_scene(2, two_sided)
        stacked = [scene.material] + ([scene.back_material] if two_sided else [])
        want = collections.Counter(leaf.shape for m in stacked for leaf in jax.tree.leaves(m))
        # soft Phong shading is traced twice: in both branches of on_active's lax.cond
        for settings, traced in ((SETTINGS, 1), (SOFT, 2)):
            tables = gather_tables(scene, settings)
            got = collections.Counter({t: n for t, n in tables.items() if t[:1] == (2,)})
            assert got == collections.Counter({t: traced * n for t, n in want.items()}), (
                two_sided, settings.raster, got, want)

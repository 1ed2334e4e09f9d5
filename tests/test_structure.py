"""The scene's structure decides what is compiled, and only the structure.

Markers, counted over the render's jaxpr and all its sub-jaxprs, in hard and soft raster:
- the spot path is the only user of `cos` (the cone's cutoff angle);
- `log` comes only from safe_pow, used by the specular power and the spot exponent, so a
  directional-only scene without `ks` has as many as a scene without lights (none in
  hard raster; soft raster's weights have their own);
- `log1p` (log-sigmoid) only from soft raster's coverage: hard raster has none;
- each light's incidence passes one `optimization_barrier`: a directional light's carries
  only its direction (no attenuation array of ones), a point light's also its attenuation;
- two-sided lighting without a back material selects only the normal's side, never
  between materials; a back material adds one select per material field;
- emission adds no per-fragment work when the material has none.
- a scene of one object (make_scene(objects=[one])) compiles exactly the program of the
  same scene built from a mesh; a scene of several gathers each stacked material field
  per sample (a gather whose table has a leading object axis), and only such a scene.
The plain scene's lowered program is compared, op for op, with the one the revision
before the effects of issue 14 (BASELINE) lowers, run from `git archive` in a subprocess.
Recompilation is counted with JAX's compile events (tests/compiles.py).
"""

import collections
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from compiles import compiles
from jax.extend import core as jex_core

from diffshade import (
    RenderSettings,
    area_light,
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
    sphere_light,
    spot_light,
)

SETTINGS = RenderSettings()
SOFT = RenderSettings(raster="soft")
RASTERS = pytest.mark.parametrize("settings", [SETTINGS, SOFT], ids=["hard", "soft"])
#: the revision before the effects of issue 14 (shadows, transparency, area lights, objects)
BASELINE = "4ab48df"
ROOT = Path(__file__).resolve().parents[1]


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


@RASTERS
def test_directional_only_scene_compiles_no_spot_or_attenuation_code(settings):
    sun = primitive_counts(scene_with([SUN]), settings)
    with_bulb = primitive_counts(scene_with([SUN, BULB]), settings)
    with_spot = primitive_counts(scene_with([SUN, SPOT]), settings)
    dark = primitive_counts(scene_with([]), settings)  # the soft weights' own logs only
    assert sun["cos"] == 0 and sun["log"] == dark["log"]
    assert with_spot["cos"] >= 1 and with_spot["log"] > dark["log"]
    assert sum(with_bulb.values()) > sum(sun.values())
    assert sum(with_spot.values()) > sum(with_bulb.values())


@RASTERS
def test_material_without_ks_compiles_no_specular_code(settings):
    plain = primitive_counts(scene_with([SUN], material(ks=None)), settings)
    shiny = primitive_counts(scene_with([SUN], material(ks=0.5, shininess=10.0)), settings)
    dark = primitive_counts(scene_with([]), settings)
    assert plain["log"] == dark["log"]
    assert shiny["log"] > dark["log"]
    assert sum(shiny.values()) > sum(plain.values())


def test_only_soft_raster_compiles_the_sigmoid_coverage():
    hard = primitive_counts(scene_with([SUN]), SETTINGS)
    soft = primitive_counts(scene_with([SUN]), SOFT)
    assert hard["log1p"] == 0 and soft["log1p"] >= 1


@RASTERS
def test_an_area_light_without_shadows_lowers_without_shadow_maps(settings):
    disk = {"normal": (0.0, 0.0, -1.0), "radius": 0.3, "samples": 4}
    lights = {"disk": [area_light((0.0, 1.0, 2.0), **disk)],
              "disk_flag_false": [area_light((0.0, 1.0, 2.0), **disk, shadows=False)],
              "disk_shadowed": [area_light((0.0, 1.0, 2.0), **disk, shadows=True)],
              "ball": [sphere_light((0.0, 1.0, 2.0), 0.3, samples=4)],
              "ball_shadowed": [sphere_light((0.0, 1.0, 2.0), 0.3, samples=4, shadows=True)]}
    counts = {name: primitive_counts(scene_with(group), settings)
              for name, group in lights.items()}
    assert counts["disk_flag_false"] == counts["disk"]
    for name in ("disk", "ball"):
        # no rasterization but the camera's
        assert counts[name]["fragment_geometry_op"] == 1, name
        # shadows: one more rasterization (every sample's cube map, in a loop), map
        # lookups (a cube-face argmax) and one more rematerialized loop body (over the
        # samples' visibilities)
        added = counts[f"{name}_shadowed"] - counts[name]
        assert added["fragment_geometry_op"] == 1 and added["argmax"] >= 1, name
        assert added["remat2"] >= 1, name


def barrier_operands(scene, settings=SETTINGS):
    """Operand counts of the optimization barriers that render(scene) has beyond those of
    the same scene without lights."""
    def operands(s):
        return collections.Counter(len(e.invars) for e in equations(s, settings)
                                   if e.primitive.name == "optimization_barrier")
    extra = operands(scene) - operands(replace(scene, lights=scene_with([]).lights))
    return sorted(extra.elements())


@RASTERS
def test_a_directional_light_carries_no_attenuation_array(settings):
    plain = material(ks=None)
    # a barrier per light (per traced copy of the shading: soft raster's compaction traces
    # it in both branches of a cond): the direction alone, or with the attenuation
    sun = barrier_operands(scene_with([SUN], plain), settings)
    bulb = barrier_operands(scene_with([BULB], plain), settings)
    assert set(sun) == {1} and set(bulb) == {2}
    assert barrier_operands(scene_with([SUN, BULB], plain), settings) == sorted(sun + bulb)


def _selects(scene, settings):
    return primitive_counts(scene, settings)["select_n"]


@RASTERS
def test_two_sided_lighting_selects_materials_only_with_a_back_material(settings):
    mat = material(ka=0.1, kd=0.5, ks=0.3, shininess=5.0)
    one = scene_with([SUN], mat)
    two = replace(one, two_sided=True)
    back = replace(two, back_material=material(ka=0.2, kd=0.1, ks=0.6, shininess=9.0))
    fields = 4  # ka, kd, ks, shininess
    copies = len(barrier_operands(scene_with([SUN], material(ks=None)), settings))  # shadings
    # without a back material only the normals' side is chosen (a select per sample)
    assert 1 <= _selects(two, settings) - _selects(one, settings) <= 2 * copies
    assert _selects(back, settings) - _selects(two, settings) == fields * copies


def compiled_adds(scene, settings):
    """How many `add` instructions XLA's optimized program for render(scene) has."""
    text = jax.jit(lambda s: render(s, settings)).lower(scene).compile().as_text()
    return len(re.findall(r"\badd\(", text))


def test_emission_compiles_only_when_the_material_has_it():
    # without emission the renderer adds an image of zeros, which XLA folds away
    plain = compiled_adds(scene_with([SUN], material(ks=None)), SETTINGS)
    glowing = compiled_adds(scene_with([SUN], material(ks=None, emission=0.3)), SETTINGS)
    assert glowing > plain


PLAIN_PROGRAM = r"""
import collections, json, re, sys
import jax
import diffshade as ds
cam = ds.look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=8, height=8)
lights = [ds.directional_light((0.0, -1.0, -1.0)),
          ds.point_light((0.0, 1.0, 2.0), attenuation=(1.0, 0.1, 0.01))]
out = {}
for raster in ("hard", "soft"):
    scene = ds.make_scene(ds.icosphere(0), cam, lights, ds.material(ks=0.3, shininess=5.0))
    text = jax.jit(lambda s: ds.render(s, ds.RenderSettings(raster=raster))).lower(scene).as_text()
    out[raster] = collections.Counter(re.findall(r"= (?:\"?)([a-z_]+\.[a-z_0-9.]+)", text))
print(json.dumps(out))
"""


def lowered_plain_program(cwd):
    proc = subprocess.run([sys.executable, "-c", PLAIN_PROGRAM], cwd=cwd, capture_output=True,
                          text=True, env={**os.environ, "PYTHONPATH": str(cwd)})
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_a_plain_scene_lowers_to_the_program_of_the_baseline_revision(tmp_path):
    try:
        archive = subprocess.run(["git", "archive", BASELINE], cwd=ROOT, capture_output=True,
                                 check=True).stdout
    except (OSError, subprocess.CalledProcessError) as err:
        pytest.fail(f"the baseline revision {BASELINE} is not in this clone's history: {err}")
    subprocess.run(["tar", "-x", "-C", str(tmp_path)], input=archive, check=True)
    before = lowered_plain_program(tmp_path)
    now = lowered_plain_program(ROOT)
    assert sum(now["hard"].values()) > 100  # the count did see the program
    assert now["hard"] == before["hard"]
    # Soft raster has since been made faster (fewer operations of most kinds); it must
    # not have gained any, except those SOFT_GROWTH lists.
    grown = {op: (before["soft"].get(op, 0), n) for op, n in now["soft"].items()
             if n > before["soft"].get(op, 0) + SOFT_GROWTH.get(op, 0)}
    assert not grown, f"operations the plain soft program gained (before, now): {grown}"


#: What the plain soft program may have gained since BASELINE, and why: the host call that
#: finds the active slots (compact.active_indices, which replaced a jnp.nonzero); the
#: Phong samples' interpolation and renormalization, now inside both branches of
#: on_active's cond (render._shade_active: one more host call, gather, sqrt, divide and
#: the reshapes and slices around them); the log-sigmoids written out, so that one jit
#: shares their exp and log1p between the weights and the alpha (blend.log_coverages:
#: exp, log1p, minimum, abs, subtract, multiply), and the background's weight kept apart
#: in the softmax (one concatenate).
SOFT_GROWTH = {"stablehlo.custom_call": 2, "stablehlo.gather": 1, "stablehlo.sqrt": 1,
               "stablehlo.divide": 1, "stablehlo.reshape": 8, "stablehlo.slice": 8,
               "stablehlo.exponential": 2, "stablehlo.log_plus_one": 1,
               "stablehlo.minimum": 2, "stablehlo.abs": 1, "stablehlo.subtract": 1,
               "stablehlo.multiply": 4, "stablehlo.concatenate": 1}


def test_new_values_with_the_same_structure_do_not_recompile():
    scene = scene_with([SUN, BULB], material(ka=0.1, kd=0.5, ks=0.3, shininess=5.0), size=11)
    first = np.asarray(render(scene))
    changed = replace(
        scene, material=material(ka=0.3, kd=0.2, ks=0.9, shininess=60.0),
        lights=replace(scene.lights, point=replace(scene.lights.point,
                                                   position=scene.lights.point.position + 0.5)),
        global_ambient=scene.global_ambient * 2.0, background=scene.background + 0.25)
    with compiles() as counted:
        second = np.asarray(render(changed))
    assert counted.of(render) == 0
    assert np.abs(second - first).max() > 0.05  # the new values did take effect


def test_a_new_structure_does_recompile():
    # the control for the test above: dropping ks changes the pytree, so render retraces
    scene = scene_with([SUN], material(ks=0.5, shininess=10.0), size=13)
    render(scene)
    with compiles() as counted:
        render(replace(scene, material=material(ks=None)))
    assert counted.of(render) == 1


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

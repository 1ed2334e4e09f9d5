"""The scene's structure decides what is compiled, and only the structure.

Markers, counted over the render's jaxpr and all its sub-jaxprs, in hard and soft raster:
- `cos` comes only from the spot cone's cutoff angle and a sphere light's samples;
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
- the plain scene (a directional and a point light, specular, opaque, one object, no
  shadows) compiles none of the effects' markers (cos and sin, rasterizations beyond the
  camera's, shadow-map lookups, loops over light samples, depth sorts, hard raster's
  layers): it has those of a scene without lights. Each effect added to it (a spot
  light, shadows of a directional or a point light, a disk or sphere light, kt, a kd
  texture on a mesh with UVs: texel reads, operations on a table of its 5 x 7 texel
  cells) raises
  its own markers and no other, and adds operations without removing any of the plain
  program's (but soft kt, which composites the layers in place of the soft blend);
- values never change the program (a term of zero strength is compiled all the same),
  nor does a field the structure leaves unused (a back material without two-sided
  lighting): the programs are equal equation for equation.
Recompilation is counted with JAX's compile events (tests/compiles.py).
"""

import collections
import re

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
    rasterize_scene,
    render,
    replace,
    scene_object,
    sphere_light,
    spot_light,
    texture,
)
from diffshade.pipeline.rendering import ACTIVE_SLOTS_PER_PIXEL

SETTINGS = RenderSettings()
SOFT = RenderSettings(raster="soft")
RASTERS = pytest.mark.parametrize("settings", [SETTINGS, SOFT], ids=["hard", "soft"])


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
    # the coverage's log-sigmoid, log(1 + exp(-|x|)) (composite.blend.log_coverages)
    assert hard["log"] == 0 and soft["log"] >= 1


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


# ------------------------------------------------- the plain scene and each effect

#: the plain scene: a directional and a point light on a specular, opaque material, one
#: object, one-sided lighting and no shadows
PLAIN_LIGHTS = [SUN, BULB]
PLAIN_MATERIAL = material(ks=0.3, shininess=5.0)
DISK = area_light((0.0, 1.0, 2.0), normal=(0.0, 0.0, -1.0), radius=0.3, samples=4)
BALL = sphere_light((0.0, 1.0, 2.0), 0.3, samples=4)


def plain_scene(lights=PLAIN_LIGHTS, mat=PLAIN_MATERIAL):
    return scene_with(lights, mat)


SHADOWS = {"rasterizations", "map lookups"}
#: the texture effect's size: 35 texels, no other table of the program has 35 rows
TEXELS = (5, 7)
SAMPLED = {"sample loops"}
#: each effect added to the plain scene (a builder), and the markers it raises in hard and
#: in soft raster
EFFECTS = {
    "spot light": (lambda: plain_scene(PLAIN_LIGHTS + [SPOT]), {"cos"}, {"cos"}),
    "directional shadows": (lambda: plain_scene([replace(SUN, shadows=True), BULB]),
                            SHADOWS, SHADOWS),
    "point shadows": (lambda: plain_scene([SUN, replace(BULB, shadows=True)]),
                      SHADOWS, SHADOWS),
    "disk light": (lambda: plain_scene(PLAIN_LIGHTS + [DISK]), SAMPLED, SAMPLED),
    "sphere light": (lambda: plain_scene(PLAIN_LIGHTS + [BALL]),
                     SAMPLED | {"sin", "cos"}, SAMPLED | {"sin", "cos"}),
    # hard raster keeps K layers instead of a z-buffer's one; soft raster keeps K anyway
    # and sorts them by depth to composite them
    "transparency": (lambda: plain_scene(mat=material(ks=0.3, shininess=5.0, kt=0.4)),
                     {"layers"}, {"depth sorts"}),
    "kd texture": (lambda: make_scene(icosphere(0, uv=True), plain_scene().camera, PLAIN_LIGHTS,
                                      material(kd=texture(np.ones(TEXELS + (3,))), ks=0.3,
                                               shininess=5.0)),
                   {"texel reads"}, {"texel reads"}),
}


def layers(scene, settings):
    """Fragment layers per pixel that render(scene) rasterizes (K of its Fragments)."""
    return jax.eval_shape(lambda s: rasterize_scene(s, settings), scene).face_ids.shape[-1]


def markers(scene, settings):
    """Code that only the effects compile, in render(scene)'s program: cos (a spot's cone,
    a sphere light's samples), sin (a sphere light's samples), rasterizations (the
    camera's, plus one per shadowed light), shadow-map lookups (the argmax that picks a
    map), loops over a light's samples (scan), depth sorts, the fragment layers, and
    texel reads (operations whose first table operand has a row per texel of the
    effect's TEXELS: the texture lookup's)."""
    ops = primitive_counts(scene, settings)
    return {"cos": ops["cos"], "sin": ops["sin"],
            "rasterizations": ops["fragment_geometry_op"], "map lookups": ops["argmax"],
            "sample loops": ops["scan"], "depth sorts": ops["sort"],
            "layers": layers(scene, settings),
            "texel reads": texel_reads(scene, settings)}


def texel_reads(scene, settings):
    """Equations of render(scene) reading a table of TEXELS[0] * TEXELS[1] rows: a texture
    lookup's texels (the texture op's, its last operand, or a gather's table off the CPU
    backend); the plain program has no table of that many rows."""
    rows = TEXELS[0] * TEXELS[1]

    def reads(eqn):
        table = {"gather": 0, "sample_texture_op": -1}.get(eqn.primitive.name)
        return table is not None and eqn.invars[table].aval.shape[:1] == (rows,)
    return sum(map(reads, equations(scene, settings)))


@RASTERS
def test_a_plain_scene_compiles_none_of_the_effects(settings):
    plain, dark = markers(plain_scene(), settings), markers(scene_with([]), settings)
    assert sum(primitive_counts(plain_scene(), settings).values()) > 100  # it saw the program
    # the plain scene's lights and specular term compile no effect's code
    assert plain == dark
    assert plain["rasterizations"] == 1 and plain["layers"] == (settings.faces_per_pixel
                                                               if settings.raster == "soft"
                                                               else 1)
    for name, (build, *raised) in EFFECTS.items():
        got = markers(build(), settings)
        want = raised[settings.raster == "soft"]
        assert {m for m in got if got[m] != plain[m]} == want, (name, plain, got)
        assert all(got[m] > plain[m] for m in want), (name, plain, got)


@RASTERS
def test_an_effect_adds_its_code_to_the_plain_program_and_removes_none(settings):
    plain = primitive_counts(plain_scene(), settings)
    for name, (build, *_) in EFFECTS.items():
        if name == "transparency" and settings.raster == "soft":
            continue  # composites every layer, in place of the soft blend of lit fragments
        added = primitive_counts(build(), settings)
        assert not plain - added, (name, plain - added)
        assert sum(added.values()) > sum(plain.values()), name


def operations(scene, settings):
    """Every equation of render(scene)'s jaxpr in order, as its primitive and output types
    (the arguments aside: a field the program never reads is still one)."""
    return [(e.primitive.name, [str(v.aval) for v in e.outvars])
            for e in equations(scene, settings)]


@RASTERS
def test_values_and_unused_fields_leave_the_program_as_it_is(settings):
    dark_sun = directional_light((1.0, 0.0, -1.0), 0.0)
    dim_bulb = point_light((0.0, -1.0, 2.0), 0.0, attenuation=(1.0, 0.0, 0.0))
    same = {
        # other values, several of them zero: a term of zero strength is still compiled
        "values": (plain_scene(), plain_scene([dark_sun, dim_bulb],
                                              material(ka=0.0, kd=0.0, ks=0.0))),
        # a back material is used only with two-sided lighting, its kt with it
        "unused back material": (plain_scene(), replace(plain_scene(),
                                                        back_material=material(kt=0.5))),
        "zero-strength spot": (EFFECTS["spot light"][0](), plain_scene(PLAIN_LIGHTS + [
            spot_light((0.0, 0.0, 2.0), (0.0, 0.0, -1.0), 0.0, cutoff=180.0)])),
        "opaque layers": (EFFECTS["transparency"][0](),
                          plain_scene(mat=material(ks=0.3, shininess=5.0, kt=0.0))),
    }
    for name, (one, other) in same.items():
        assert operations(one, settings) == operations(other, settings), name
    # the control: another structure is another program
    spot = EFFECTS["spot light"][0]()
    assert operations(plain_scene(), settings) != operations(spot, settings)


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
        # soft Phong shading is traced once per branch of on_active's lax.switch: per tier
        # of ACTIVE_SLOTS_PER_PIXEL (K = 8 is above them all), and everywhere
        soft_traced = len(ACTIVE_SLOTS_PER_PIXEL) + 1
        for settings, traced in ((SETTINGS, 1), (SOFT, soft_traced)):
            tables = gather_tables(scene, settings)
            got = collections.Counter({t: n for t, n in tables.items() if t[:1] == (2,)})
            assert got == collections.Counter({t: traced * n for t, n in want.items()}), (
                two_sided, settings.raster, got, want)


@RASTERS
def test_uvs_without_a_texture_compile_the_program_of_a_mesh_without_them(settings):
    with_uv = make_scene(icosphere(0, uv=True), plain_scene().camera, PLAIN_LIGHTS,
                         PLAIN_MATERIAL)
    assert primitive_counts(with_uv, settings) == primitive_counts(plain_scene(), settings)

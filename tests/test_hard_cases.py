"""The catalogue of numerically hard cases (issue 5): finite values and finite gradients
everywhere, in float32 and float64, and gradients equal to central finite differences
(float64) wherever the rendered function is smooth at the case.

Every case is a scene of one shared structure: a 15x15 image (odd, so that pixel column
and row 7 sample the view axis exactly), V_PAD vertices, F_PAD faces, one light of each
type and a material with specular and emission. Cases differ in values only, so they are
stacked and rendered in one `vmap`, and the whole PLAN of (scene variant, settings) pairs
compiles once per float dtype. Meshes are padded to the shared shape with unused vertices
and fully degenerate faces (one vertex three times): both are hard cases themselves and
invisible by construction.

The loss is sum(weights * RGBA) with fixed random weights; its gradient is taken with
respect to every float leaf of the scene: vertices, vertex normals, the model matrix, the
whole camera, every field of every light, the front and back materials, the global ambient
and the background. The finite differences of float64 are evaluated in the same batch
(each smooth case also appears moved by +-EPS along a random direction).

docs/stability.md lists each case with the technique that keeps it finite.
"""

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffshade import (
    Mesh,
    RenderSettings,
    ambient_light,
    area_light,
    box,
    directional_light,
    icosphere,
    look_at,
    make_scene,
    material,
    mesh_from_arrays,
    model_matrix,
    point_light,
    render,
    replace,
    scene_object,
    sphere_light,
    spot_light,
)
from diffshade.numerics import float_dtype
from diffshade.scene.mesh import vertex_normals

SIZE = 15
V_PAD, F_PAD = 10, 6
EPS = 1e-6  # central-difference step, relative to each leaf's magnitude

# the apex is off the view axis, so that no pixel centre sits on a vertex or an edge
TENT = ([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.2], [1.0, 1.0, 0.0], [-1.0, 1.0, -0.2],
         [0.1, 0.05, 0.5]], [[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
QUAD = ([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]],
        [[0, 1, 2], [0, 2, 3]])
CLOCKWISE_QUAD = (QUAD[0], [[0, 2, 1], [0, 3, 2]])
# a triangle whose centroid is exactly the origin (flat shading is evaluated there)
CENTRED = ([[-1.0, -1.0, 0.0], [2.0, -1.0, 0.0], [-1.0, 2.0, 0.0]], [[0, 1, 2]])


# ------------------------------------------------------------------------ the cases


def padded_mesh(vertices, faces):
    """Mesh in the default float dtype, padded to [V_PAD, 3] vertices (unused, at the
    origin) and [F_PAD, 3] faces (vertex 0 three times); normals from vertex_normals."""
    verts = np.zeros((V_PAD, 3))
    verts[: len(vertices)] = vertices
    tris = np.zeros((F_PAD, 3), np.int32)
    tris[: len(faces)] = faces
    verts, tris = jnp.asarray(verts, float_dtype()), jnp.asarray(tris)
    return Mesh(verts, tris, vertex_normals(verts, tris))


def case_scene(geometry=TENT, *, eye=(0.3, 0.4, 3.0), target=(0.0, 0.0, 0.0),
               up=(0.0, 1.0, 0.0), near=0.5, far=10.0,
               sun=(0.2, -0.3, -1.0), bulb=(0.5, 0.5, 2.0), attenuation=(1.0, 0.1, 0.05),
               spot=((0.0, 0.0, 3.0), (0.0, 0.0, -1.0)), cutoff=30.0, exponent=2.0,
               shininess=20.0, model=None):
    """A scene of the shared structure; keywords override the generic defaults."""
    cam = look_at(eye, target, up, width=SIZE, height=SIZE, fov_y=50.0, near=near, far=far)
    lights = [ambient_light(0.1),
              directional_light(sun, (0.5, 0.45, 0.4), ambient=0.05),
              point_light(bulb, (0.7, 0.6, 0.8), ambient=0.05, attenuation=attenuation),
              spot_light(*spot, (0.6, 0.7, 0.5), cutoff=cutoff, exponent=exponent,
                         ambient=0.05, attenuation=attenuation)]
    mat = material(ka=0.2, kd=(0.7, 0.5, 0.3), ks=(0.5, 0.4, 0.6), shininess=shininess,
                   emission=0.05)
    return make_scene(padded_mesh(*geometry), cam, lights, mat, model=model,
                      global_ambient=(0.1, 0.15, 0.2), background=(0.2, 0.1, 0.3))


def plus(vertices, faces, geometry=TENT):
    """geometry with extra vertices and faces (face indices local to the extra vertices)."""
    base_v, base_f = geometry
    return (list(base_v) + list(vertices),
            list(base_f) + [[i + len(base_v) for i in face] for face in faces])


def scaled(s):
    """The generic scene with every length times s and attenuation (a, b/s, c/s^2): the
    same attenuation at the same relative distance, so the same image."""
    return case_scene((np.asarray(TENT[0]) * s, TENT[1]), eye=(0.3 * s, 0.4 * s, 3.0 * s),
                      near=0.5 * s, far=10.0 * s,
                      bulb=(0.5 * s, 0.5 * s, 2.0 * s), attenuation=(1.0, 0.1 / s, 0.05 / s**2),
                      spot=((0.0, 0.0, 3.0 * s), (0.0, 0.0, -1.0)))


ON_AXIS = {"eye": (0.0, 0.0, 3.0)}
# lights in the plane z = 0 of QUAD: the sun travels along +x, the bulb and spot lie in it
IN_PLANE = {"sun": (1.0, 0.0, 0.0), "bulb": (0.5, 3.0, 0.0),
            "spot": ((-3.0, 0.2, 0.0), (1.0, 0.0, 0.0)), "cutoff": 60.0}
BEHIND = {"sun": (0.0, 0.0, 1.0), "bulb": (0.0, 0.0, -2.0),
          "spot": ((0.0, 0.0, -2.0), (0.0, 0.0, 1.0))}


@dataclasses.dataclass(frozen=True)
class Case:
    """build() -> Scene; what: the hard part, for the failure messages.

    smooth: the raster modes in which the render is differentiable at the case with
    respect to every leaf but `fixed` (key paths): there central differences must agree.
    length: the scene's unit of length (the step for leaves that are all zero).
    """

    build: object
    what: str
    smooth: tuple = ("hard", "soft")
    fixed: tuple = ()
    length: float = 1.0


SMOOTH, HARD_ONLY, NOT_SMOOTH = ("hard", "soft"), ("hard",), ()
SPOT_CUTOFF = "['lights'].spot.cutoff"


def case(smooth, what, geometry=TENT, fixed=(), **kw):
    return Case(functools.partial(case_scene, geometry, **kw), what, smooth, fixed)


CASES = {
    "generic": case(SMOOTH, "a generic scene, pixels covered by no face included"),
    **{f"shininess_{s:g}": case(SMOOTH, f"shininess {s:g}", shininess=s)
       for s in (0.0, 0.01, 1.0, 1000.0, 10000.0)},
    "n_dot_l_zero": case(NOT_SMOOTH, "N.L exactly 0 for the sun, the bulb and the spot", QUAD,
                         **ON_AXIS, **IN_PLANE),
    "l_minus_v": case(NOT_SMOOTH, "L = -V with N.L = 1 (a back face lit from behind): H = 0/0",
                      CLOCKWISE_QUAD, **ON_AXIS, **BEHIND),
    "normals_cancel": case(NOT_SMOOTH, "a face and its reverse: zero vertex normals",
                           plus([[-0.5, -0.5, 0.8], [0.5, -0.4, 0.8], [0.0, 0.5, 0.8]],
                                [[0, 1, 2], [0, 2, 1]])),
    "unused_vertex_at_eye": case(SMOOTH, "a vertex used by no face (zero normal), at the eye",
                                 plus([[0.3, 0.4, 3.0]], [])),
    # soft: a zero-area face is skipped, but a slightly larger one has a footprint
    "zero_area": case(HARD_ONLY, "three distinct vertices at one point",
                      plus([[0.1, 0.1, 0.8]] * 3, [[0, 1, 2]])),
    "collinear": case(NOT_SMOOTH, "three collinear vertices on a row of pixel centres",
                      plus([[-0.8, 0.0, 0.8], [0.1, 0.0, 0.8], [0.9, 0.0, 0.8]], [[0, 1, 2]]),
                      **ON_AXIS),
    "repeated_vertex": case(SMOOTH, "faces naming one vertex twice",
                            plus([[-0.5, 0.2, 0.8], [0.6, -0.3, 0.8]], [[0, 0, 1], [1, 0, 1]])),
    "edge_on": case(NOT_SMOOTH, "a face in a plane through the eye, on a column of pixel centres",
                    plus([[0.0, -0.8, -0.5], [0.0, 0.9, 0.0], [0.0, 0.0, 1.5]], [[0, 1, 2]]),
                    **ON_AXIS),
    "tiny_triangle": case(SMOOTH, "a face smaller than a pixel, between pixel centres",
                          plus([[0.02, 0.02, 0.8], [0.05, 0.02, 0.8], [0.03, 0.05, 0.8]],
                               [[0, 1, 2]]), **ON_AXIS),
    "huge_triangle": case(SMOOTH, "a face reaching 1000 units beyond the image",
                          ([[-1e3, -1e3, -1.0], [1e3, -1e3, -1.0], [0.0, 1e3, -1.0]],
                           [[0, 1, 2]])),
    "near_plane": case(SMOOTH, "faces crossing the near plane and the eye plane (clip w < 0)",
                       plus([[-0.5, -0.5, 2.8], [0.8, -0.2, 0.0], [0.0, 0.7, 3.6],
                             [-0.6, 0.3, 1.0]], [[0, 1, 3], [3, 1, 2]]), **ON_AXIS),
    # soft: a face is culled as soon as one vertex is nearer than the near plane
    "vertex_on_near_plane": case(HARD_ONLY, "a vertex exactly on the near plane",
                                 plus([[0.2, 0.1, 2.5], [0.9, -0.6, 0.6], [-0.7, -0.2, 0.7]],
                                      [[0, 2, 1]]), **ON_AXIS),
    "vertex_in_eye_plane": case(NOT_SMOOTH, "a vertex at clip w = 0 and one at the eye itself",
                                plus([[0.5, 0.2, 3.0], [0.0, 0.0, 3.0], [-0.5, -0.5, 1.0]],
                                     [[0, 2, 1]]), **ON_AXIS),
    "behind_camera": case(SMOOTH, "a face entirely behind the camera",
                          plus([[-1.0, -1.0, 4.0], [1.0, -1.0, 4.5], [0.0, 1.0, 5.0]],
                               [[0, 1, 2]]), **ON_AXIS),
    "far_plane": case(SMOOTH, "a face crossing the far plane",
                      plus([[-1.0, -1.0, -12.0], [1.0, -0.5, 1.0], [0.0, 1.0, -3.0]],
                           [[0, 1, 2]])),
    "nothing_covered": case(SMOOTH, "the camera looks away: no pixel is covered",
                            eye=(0.0, 0.0, 3.0), target=(0.0, 0.0, 6.0)),
    "one_depth": case(NOT_SMOOTH, "overlapping coplanar faces: every depth ties",
                      ([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [0.0, 1.0, 0.0],
                        [-1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, -1.0, 0.0]],
                       [[0, 1, 2], [5, 4, 3], [0, 4, 3]]), **ON_AXIS),
    "light_at_surface": case(NOT_SMOOTH, "the bulb at the centroid, the spot at a vertex",
                             CENTRED, **ON_AXIS, bulb=(0.0, 0.0, 0.0),
                             spot=((-1.0, -1.0, 0.0), (0.0, 0.0, -1.0))),
    "inverse_square": case(SMOOTH, "pure inverse-square attenuation (0, 0, 1)",
                           attenuation=(0.0, 0.0, 1.0)),
    "inverse_square_at_surface": case(NOT_SMOOTH, "attenuation (0, 0, 1) and d = 0: the bulb "
                                      "at the centroid, the spot at a vertex", CENTRED,
                                      **ON_AXIS, bulb=(0.0, 0.0, 0.0),
                                      spot=((-1.0, -1.0, 0.0), (0.0, 0.0, -1.0)),
                                      attenuation=(0.0, 0.0, 1.0)),
    "inverse_square_near": case(NOT_SMOOTH, "attenuation (0, 0, 1), the bulb 1e-6 above the "
                                "centroid", CENTRED, **ON_AXIS, bulb=(0.0, 0.0, 1e-6),
                                attenuation=(0.0, 0.0, 1.0)),
    "light_at_eye": case(SMOOTH, "the bulb at the eye (L = V for a local viewer)",
                         bulb=(0.3, 0.4, 3.0)),
    "scale_1e-4": Case(lambda: scaled(1e-4), "every length times 1e-4", length=1e-4),
    "scale_1e4": Case(lambda: scaled(1e4), "every length times 1e4", length=1e4),
    "spot_e0_c0": case(NOT_SMOOTH, "spot exponent 0, cutoff 0 (a cone of one ray)",
                       **ON_AXIS, exponent=0.0, cutoff=0.0),
    "spot_e128_c0": case(NOT_SMOOTH, "spot exponent 128, cutoff 0", **ON_AXIS, exponent=128.0,
                         cutoff=0.0),
    "spot_e0_c90": case(SMOOTH, "spot exponent 0, cutoff 90 (a half-space)", exponent=0.0,
                        cutoff=90.0),
    "spot_e128_c90": case(SMOOTH, "spot exponent 128, cutoff 90", exponent=128.0,
                          cutoff=90.0),
    "spot_no_cone": case(SMOOTH, "cutoff 180 (no cone), exponent 128, spot behind the surface",
                         exponent=128.0, cutoff=180.0, fixed=(SPOT_CUTOFF,),
                         spot=((0.0, 0.0, -3.0), (0.0, 0.0, 1.0))),
    "model_transform": case(SMOOTH, "rotation, translation and non-uniform scale",
                            model=model_matrix((0.1, -0.2, 0.3), (20.0, -35.0, 10.0),
                                               (1.3, 0.7, 1.1))),
    "grazing_view": case(SMOOTH, "a surface seen 1 degree from edge-on", QUAD,
                         eye=(0.13, -3.0, 0.05), target=(0.05, 0.1, 0.0), up=(0.0, 0.0, 1.0)),
    "saturated": case(SMOOTH, "lights 10^4 times too bright: every channel saturates",
                      attenuation=(1e-4, 0.0, 0.0)),
}


# --------------------------------------------------------- the plan: variants x settings


def _plain(scene, back):
    return scene


def _local_two_sided(scene, back):
    return replace(scene, local_viewer=True, two_sided=True, back_material=back)


VARIANTS = {"plain": _plain, "local_two_sided": _local_two_sided}

# Every shading mode in soft raster, Phong and Gouraud in hard raster too, clamping off,
# the smooth spot edge, the Phong specular model, back-face culling, sigma and gamma of
# 1e-8 and 1e2, and a local viewer with two-sided lighting. Each entry compiles a program
# of its own (4-12 s of CPU each), so no two entries run the same code on the cases: flat
# and flat_last light one sample per face (per vertex) whichever raster reads it
# (diffshade.shading.samples), so they run in soft raster alone, which reads and clamps those
# samples as hard raster does; hard raster's own code runs under Phong and Gouraud.
PLAN = (
    ("plain", RenderSettings()),
    ("plain", RenderSettings(raster="soft")),
    ("plain", RenderSettings(shading="gouraud")),
    ("plain", RenderSettings(shading="gouraud", raster="soft", clamp=False,
                             spot_edge="smooth", sigma=1e-8, gamma=1e-8)),
    ("plain", RenderSettings(shading="flat", raster="soft", specular="phong", sigma=1e2,
                             gamma=1e2)),
    ("plain", RenderSettings(shading="flat_last", raster="soft", cull_backfaces=True,
                             sigma=1e2, gamma=1e-8)),
    ("local_two_sided", RenderSettings(clamp=False, spot_edge="smooth")),
)


# ---------------------------------------- the effects catalogue: transparency, area lights
# Its own shared structure (a transparent material over two layers, a rectangle, a disk and
# a sphere light), so that the main catalogue keeps compiling what it compiled before.

BEHIND_QUAD = [[-1.5, -1.5, -0.6], [1.5, -1.5, -0.6], [1.5, 1.5, -0.6], [-1.5, 1.5, -0.6]]
ZERO_RECT = ("['lights'].rect.edge_u", "['lights'].rect.edge_v")


EXTENDED_AT = ((0.4, 0.3, 2.0), (-0.5, 0.2, 1.5), (0.2, -0.6, 1.8))


def effects_scene(kt=(0.3, 0.6, 0.9), size=1.0, at=EXTENDED_AT):
    """The tent with a quad behind it; a rectangle, a disk and a sphere light centred at
    `at`, `size` times their generic size (0: zero-size lights)."""
    cam = look_at((0.3, 0.4, 3.0), (0.0, 0.0, 0.0), width=SIZE, height=SIZE, fov_y=50.0,
                  near=0.5, far=10.0)
    lights = [ambient_light(0.1),
              area_light(at[0], (0.8 * size, 0.1 * size, 0.0), (0.0, -0.6 * size, 0.1 * size),
                         color=(0.7, 0.6, 0.8), ambient=0.05, samples=4),
              area_light(at[1], normal=(0.3, -0.1, -1.0), radius=0.5 * size,
                         color=(0.6, 0.7, 0.5), samples=4),
              sphere_light(at[2], 0.3 * size, (0.5, 0.45, 0.4), samples=4)]
    mat = material(ka=0.2, kd=(0.7, 0.5, 0.3), ks=(0.5, 0.4, 0.6), shininess=20.0,
                   emission=0.05, kt=kt)
    return make_scene(padded_mesh(*plus(BEHIND_QUAD, [[0, 1, 2], [0, 2, 3]])), cam, lights,
                      mat, global_ambient=(0.1, 0.15, 0.2), background=(0.2, 0.1, 0.3))


EFFECT_CASES = {
    "effects_generic": Case(effects_scene, "transparency and extended lights, generic"),
    "kt_0": Case(lambda: effects_scene(kt=0.0), "kt exactly 0 (opaque layers composited)"),
    "kt_1": Case(lambda: effects_scene(kt=1.0), "kt exactly 1 (invisible surfaces)"),
    "kt_0_and_1": Case(lambda: effects_scene(kt=(0.0, 1.0, 0.0)), "kt 0, 1, 0 per channel"),
    # a zero rectangle has no normal and emits nothing, the smallest one a point light's
    # worth: its edges are not moved by the central differences
    "zero_size_lights": Case(lambda: effects_scene(size=0.0),
                             "a zero-size rectangle, disk and sphere light", fixed=ZERO_RECT),
    "extended_lights_at_apex": Case(lambda: effects_scene(at=[TENT[0][4]] * 3),
                                    "extended lights centred on the tent's apex",
                                    smooth=NOT_SMOOTH),
    "zero_size_lights_at_apex": Case(lambda: effects_scene(size=0.0, at=[TENT[0][4]] * 3),
                                     "zero-size lights at the tent's apex", smooth=NOT_SMOOTH),
}
EFFECT_PLAN = (("plain", RenderSettings(faces_per_pixel=2)),
               ("plain", RenderSettings(raster="soft", faces_per_pixel=2)))


def label(variant, settings):
    default = RenderSettings()
    changed = [f"{f.name}={getattr(settings, f.name)}" for f in dataclasses.fields(settings)
               if getattr(settings, f.name) != getattr(default, f.name)]
    return "-".join([variant] + changed)


def fd_applies(case, settings):
    """Central differences resolve the soft blend only where sigma and gamma are not tiny
    (a step of 1e-6 of a coordinate moves a logit x / 1e-8 by ~100)."""
    soft_ok = settings.sigma >= 1.0 and settings.gamma >= 1e-4
    return settings.raster in case.smooth and (settings.raster == "hard" or soft_ok)


CATALOGUES = {"catalogue": (CASES, PLAN), "effects": (EFFECT_CASES, EFFECT_PLAN)}
ALL_CASES = {**CASES, **EFFECT_CASES}


# --------------------------------------------------------------- loss and gradients


def params_of(scene):
    """Every float leaf of the scene (all but the faces, an int array); the back material
    is used by the two-sided variant only."""
    back = material(ka=0.1, kd=(0.2, 0.4, 0.8), ks=0.9, shininess=40.0, emission=0.02)
    return {"vertices": scene.mesh.vertices, "normals": scene.mesh.normals,
            "model": scene.model, "camera": scene.camera, "lights": scene.lights,
            "material": scene.material, "back_material": back,
            "global_ambient": scene.global_ambient, "background": scene.background}


def assemble(params, faces, like, variant):
    mesh = Mesh(params["vertices"], faces, params["normals"])
    scene = replace(like, mesh=mesh, model=params["model"], camera=params["camera"],
                    lights=params["lights"], material=params["material"],
                    global_ambient=params["global_ambient"], background=params["background"])
    return VARIANTS[variant](scene, params["back_material"])


# LLVM's backend optimizations only schedule IEEE operations (no fast-math), so they change
# no value beyond rounding; without them the plan compiles about twice as fast.
FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}


@functools.partial(jax.jit, static_argnames=("plan",), compiler_options=FAST_COMPILE)
def losses_and_grads(params, faces, like, weights, plan):
    """Per plan entry, over the batch (params stacked, faces [N, F, 3]): ((loss [N],
    image [N, H, W, 4]), grads like params)."""

    def run(variant, settings):
        def loss(p, f):
            image = render(assemble(p, f, like, variant), settings)
            return jnp.sum(weights * image), image

        return jax.vmap(jax.value_and_grad(loss, has_aux=True))(params, faces)

    return [run(*entry) for entry in plan]


# leaves that are not lengths: a zero one moves on its own unit's scale (a principal point
# shift in pixels, lens coefficients), not on the scene's
NOT_LENGTHS = ("['camera'].shift", "['camera'].dist")


def random_direction(params, seed, length, fixed):
    """A random direction in parameter space: each entry scaled by its own magnitude,
    zeros by the smaller of the leaf's smallest non-zero magnitude and `length` (a zero
    translation must move by a fraction of the scene; 1 for NOT_LENGTHS); `fixed` leaves
    do not move."""

    def entry_scale(x, unit):
        nonzero = np.abs(x[x != 0])
        floor = min(nonzero.min(), unit) if nonzero.size else unit
        return np.where(x != 0, np.abs(x), floor)

    def entry(path, x):
        key = jax.tree_util.keystr(path)
        if key in fixed:
            return np.zeros_like(x)
        scale = entry_scale(x, 1.0 if key in NOT_LENGTHS else length)
        return (rng.normal(size=np.shape(x)) * scale).astype(x.dtype)

    rng = np.random.default_rng(seed)
    return jax.tree_util.tree_map_with_path(entry, params)


def moved(params, direction, step):
    return jax.tree.map(lambda x, d: x + step * d, params, direction)


def dot(grads, direction):
    """(sum of g * d, sum of |g * d|) over every leaf."""
    terms = [np.asarray(g, np.float64) * d for g, d in
             zip(jax.tree.leaves(grads), jax.tree.leaves(direction), strict=True)]
    return sum(t.sum() for t in terms), sum(np.abs(t).sum() for t in terms)


@dataclasses.dataclass
class Row:
    """One case under one plan entry: loss [], image [H, W, 4], grads like params and, in
    float64 for smooth cases, fd = (gradient . direction, sum of |terms|, central
    difference along the direction)."""

    variant: str
    settings: RenderSettings
    loss: np.ndarray
    image: np.ndarray
    grads: dict
    fd: tuple | None = None


def stack(trees):
    return jax.tree.map(lambda *xs: np.stack(xs), *trees)


def catalogue_batch(x64, cases=CASES):
    """(params stacked, faces [N, F, 3], a scene of the shared structure, directions):
    every case in `cases` order, then, in float64, each smooth case moved by +EPS and -EPS
    along its random direction (directions: {case: direction}, in that order)."""
    scenes = {name: c.build() for name, c in cases.items()}
    params = {name: jax.tree.map(np.asarray, params_of(s)) for name, s in scenes.items()}
    directions = {name: random_direction(params[name], i, c.length, c.fixed)
                  for i, (name, c) in enumerate(cases.items()) if x64 and c.smooth}
    members = [(name, params[name]) for name in cases] + [
        (name, moved(params[name], d, sign * EPS)) for name, d in directions.items()
        for sign in (1.0, -1.0)]
    faces = np.stack([np.asarray(scenes[name].mesh.faces) for name, _ in members])
    return stack([p for _, p in members]), faces, scenes[next(iter(cases))], directions


def make_row(entry, out, i, direction=None, j=None):
    """Row of batch member i; with a direction, the central difference from members j
    (moved by +EPS) and j + 1 (by -EPS)."""
    (loss, image), grads = out
    row = Row(*entry, loss[i], image[i], jax.tree.map(lambda g: g[i], grads))
    if direction is not None:
        slope, scale = dot(row.grads, direction)
        row.fd = (slope, scale, (loss[j] - loss[j + 1]) / (2 * EPS))
    return row


@functools.cache
def results(x64, catalogue="catalogue"):
    """{case: [Row per plan entry]}: the whole catalogue (or the effects catalogue) in one
    compiled call per dtype."""
    cases, plan = CATALOGUES[catalogue]
    with jax.enable_x64(x64):
        params, faces, like, directions = catalogue_batch(x64, cases)
        weights = np.random.default_rng(5).uniform(0.5, 1.5, (SIZE, SIZE, 4))
        out = losses_and_grads(params, jnp.asarray(faces), like,
                               jnp.asarray(weights, float_dtype()), plan)
        out = jax.tree.map(np.asarray, out)
    moved_at = {name: len(cases) + 2 * k for k, name in enumerate(directions)}
    return {name: [make_row(entry, o, i, directions.get(name), moved_at.get(name))
                   for entry, o in zip(plan, out, strict=True)]
            for i, name in enumerate(cases)}


# ----------------------------------------------------------------------------- checks
# Each check maps one dtype's table of results to failure messages, and one test per dtype
# runs them all: the catalogue compiles once per dtype, and a test per check could land on
# another pytest-xdist worker and compile it all again there.

DTYPES = {"float32": False, "float64": True}
BACKGROUND = np.array([0.2, 0.1, 0.3])


def where(name, row):
    return f"{name} ({ALL_CASES[name].what}), {label(row.variant, row.settings)}"


def nonfinite_leaves(tree):
    """Key paths of the leaves holding NaN or inf."""
    return [jax.tree_util.keystr(path) for path, leaf in
            jax.tree_util.tree_flatten_with_path(tree)[0] if not np.all(np.isfinite(leaf))]


def problems(row):
    """What is wrong with one render, as messages (empty when all is well)."""
    found = []
    if not (np.isfinite(row.loss) and np.all(np.isfinite(row.image))):
        found.append("non-finite image")
    bad = nonfinite_leaves(row.grads)
    if bad:
        found.append(f"non-finite gradient in {bad}")
    # a blend of colours in [0, 1] may round a few ulps above 1
    top = 1.0 + 4 * np.finfo(row.image.dtype).eps
    alpha, rgb = row.image[..., 3], row.image[..., :3]
    if not (alpha.min() >= 0 and alpha.max() <= top):
        found.append(f"alpha outside [0, 1]: {alpha.min()}..{alpha.max()}")
    if row.settings.clamp and not (rgb.min() >= 0 and rgb.max() <= top):
        found.append(f"clamped colour outside [0, 1]: {rgb.min()}..{rgb.max()}")
    return found


def check_finite(table, dtype):
    return [f"{where(name, row)}: {msg}" for name, rows in table.items() for row in rows
            for msg in problems(row)]


def check_central_differences(table, dtype):
    found = []
    for name, rows in table.items():
        for row in rows:
            if row.fd is None or not fd_applies(ALL_CASES[name], row.settings):
                continue
            slope, scale, fd = row.fd
            if abs(slope - fd) > 1e-6 * scale + 1e-9:
                found.append(f"{where(name, row)}: gradient . d = {slope!r}, central "
                             f"difference {fd!r} (scale {scale:.3g})")
    return found


def differ(got, want, atol):
    """A message when got and want differ by more than atol anywhere, else None."""
    err = np.abs(np.asarray(got, np.float64) - np.asarray(want, np.float64))
    return f"differs by {err.max():.3g} > {atol:.3g}" if np.any(err > atol) else None


def check_render_agrees(table, dtype):
    """The catalogue's compiled call (vmap, grad, its compiler options) renders what
    `render` renders, to rounding."""
    found = []
    with jax.enable_x64(DTYPES[dtype]):
        for name in ("generic", "l_minus_v", "near_plane", "light_at_surface"):
            want = np.asarray(render(CASES[name].build(), PLAN[0][1]))
            msg = differ(table[name][0].image, want, 100 * np.finfo(want.dtype).eps)
            found += [f"{where(name, table[name][0])}: catalogue and render() {msg}"] if msg else []
    return found


def check_scale_invariance(table, dtype):
    """Scaled scenes render as the generic one (except with sigma 1e-8, where coverage
    turns on rounding)."""
    atol = {"float32": 2e-4, "float64": 1e-9}[dtype]
    found = []
    for name in ("scale_1e-4", "scale_1e4"):
        for row, generic in zip(table[name], table["generic"], strict=True):
            msg = differ(row.image, generic.image, atol) if row.settings.sigma >= 1.0 else None
            found += [f"{where(name, row)}: image and the generic one {msg}"] if msg else []
    return found


def check_uncovered(table, dtype):
    """No pixel covered: background, alpha 0, no gradient for geometry or material. The
    generic scene: uncovered pixels show the background."""
    found = []
    for row in table["nothing_covered"]:
        leaves = {k: jax.tree.leaves(row.grads[k]) for k in ("vertices", "normals", "model",
                                                                "material")}
        moved = [k for k, v in leaves.items() if any(np.any(g) for g in v)]
        msg = differ(row.image, np.append(BACKGROUND, 0.0) + np.zeros_like(row.image), 1e-6)
        found += [f"{where('nothing_covered', row)}: {m}" for m in
                  ([msg] if msg else []) + ([f"gradient for {moved}"] if moved else [])]
    for row in table["generic"]:
        uncovered = row.image[..., 3] == 0
        msg = differ(row.image[uncovered, :3], BACKGROUND + np.zeros((uncovered.sum(), 3)), 1e-6)
        if row.settings.raster == "hard" and not 0 < uncovered.sum() < SIZE * SIZE:
            msg = f"{uncovered.sum()} uncovered pixels; expected some, not all"
        found += [f"{where('generic', row)}: background {msg}"] if msg else []
    return found


def check_saturation(table, dtype):
    """Every covered pixel saturates: clamped, the colour is 1 and the material gradient
    is exactly 0 (clip passes no gradient outside [0, 1]); unclamped, it flows."""
    found = []
    for row in table["saturated"]:
        flows = any(np.any(g) for g in jax.tree.leaves(row.grads["material"]))
        covered = row.image[..., 3] == 1
        if row.settings.clamp and row.settings.raster == "hard":
            msg = differ(row.image[covered, :3], 1.0, 1e-6)
            found += [f"{where('saturated', row)}: clamped colour {msg}"] if msg else []
        if flows == row.settings.clamp:
            found.append(f"{where('saturated', row)}: material gradient "
                         f"{'flows' if flows else 'is zero'} with clamp={row.settings.clamp}")
    return found


CHECKS = (check_finite, check_central_differences, check_render_agrees,
          check_scale_invariance, check_uncovered, check_saturation)


@pytest.mark.cost(150)  # 170 before the plan lost two entries: -12% of CPU measured
@pytest.mark.parametrize("dtype", DTYPES)
def test_catalogue(dtype):
    """Every case under every plan entry: finite values and gradients, colours in range,
    gradients equal to central differences (float64, smooth cases), and the values the
    hard cases must have."""
    table = results(DTYPES[dtype])
    found = [msg for check in CHECKS for msg in check(table, dtype)]
    assert not found, f"{len(found)} failures ({dtype}):\n" + "\n".join(found)


@pytest.mark.cost(75)
@pytest.mark.parametrize("dtype", DTYPES)
def test_effects_catalogue(dtype):
    """Transparency (kt 0, 1, mixed) and zero-size area and sphere lights, in hard and
    soft raster: finite values and gradients, colours in range, and gradients equal to
    central differences (float64)."""
    table = results(DTYPES[dtype], "effects")
    found = [msg for check in (check_finite, check_central_differences)
             for msg in check(table, dtype)]
    assert not found, f"{len(found)} failures ({dtype}):\n" + "\n".join(found)


@pytest.mark.parametrize("dtype", DTYPES)
def test_clamped_soft_blend_stays_within_one(dtype):
    # colours clamped to [0, 1] and a background in [0, 1]: their convex combination must
    # be too, but the soft weights sum to 1 only up to rounding (the catalogue's checks
    # allow 4 ulps so that they report only what is worse)
    with jax.enable_x64(DTYPES[dtype]):
        image = np.asarray(render(CASES["generic"].build(), RenderSettings(raster="soft")))
    assert image[..., :3].max() <= 1.0 and image[..., 3].max() <= 1.0


# ------------------------------------------------------------- two objects touching
# A scene of several objects has its own structure (stacked materials, object ids), so it
# is its own small batch: a cube resting on a floor, its bottom face coplanar with the
# floor (every depth ties there, between two objects with different materials) and its
# bottom edges on it.

TOUCHING_PLAN = (
    ("local_two_sided", RenderSettings(clamp=False)),
    ("plain", RenderSettings(shading="gouraud", raster="soft", clamp=False, sigma=1e-8,
                             gamma=1e-8)),
    ("plain", RenderSettings(shading="flat_last", raster="soft", sigma=1e2, gamma=1e2)),
)


def touching_scene():
    like = case_scene()
    floor = mesh_from_arrays(np.asarray(QUAD[0]) * 1.5, QUAD[1])
    objects = [
        scene_object(floor, material(ka=0.3, kd=(0.5, 0.5, 0.4))),
        scene_object(box((0.8, 0.8, 0.8)), material(ka=0.2, kd=(0.7, 0.2, 0.1), ks=0.5,
                                                    shininess=20.0, emission=0.05),
                     transform=model_matrix((0.1, 0.05, 0.4), (0.0, 0.0, 20.0)),
                     back_material=material(kd=(0.1, 0.6, 0.2), ks=0.2, shininess=5.0))]
    return make_scene(objects=objects, camera=like.camera, lights=like.lights,
                      global_ambient=like.global_ambient, background=like.background)


@functools.partial(jax.jit, static_argnames=("plan",), compiler_options=FAST_COMPILE)
def touching_losses_and_grads(params, like, weights, plan):
    """Per plan entry: ((loss, image), grads) of the touching scene."""

    def run(variant, settings):
        def loss(p):
            scene = replace(like, mesh=Mesh(p["vertices"], like.mesh.faces, p["normals"]),
                            material=p["material"], back_material=p["back_material"])
            if variant == "local_two_sided":
                scene = replace(scene, local_viewer=True, two_sided=True)
            image = render(scene, settings)
            return jnp.sum(weights * image), image

        return jax.value_and_grad(loss, has_aux=True)(params)

    return [run(*entry) for entry in plan]


@pytest.mark.parametrize("dtype", DTYPES)
def test_two_objects_touching(dtype):
    """Finite values and gradients (vertices, normals, every object's front and back
    material), colours in range, under shading and raster modes and two-sided lighting."""
    with jax.enable_x64(DTYPES[dtype]):
        scene = touching_scene()
        params = {"vertices": scene.mesh.vertices, "normals": scene.mesh.normals,
                  "material": scene.material, "back_material": scene.back_material}
        weights = np.random.default_rng(5).uniform(0.5, 1.5, (SIZE, SIZE, 4))
        out = touching_losses_and_grads(params, scene, jnp.asarray(weights, float_dtype()),
                                        TOUCHING_PLAN)
        out = jax.tree.map(np.asarray, out)
    rows = [Row(*entry, loss, image, grads)
            for entry, ((loss, image), grads) in zip(TOUCHING_PLAN, out, strict=True)]
    found = [f"{label(r.variant, r.settings)}: {m}" for r in rows for m in problems(r)]
    covered = [(r.image[..., 3] > 0).mean() for r in rows]
    assert not found, f"{len(found)} failures ({dtype}):\n" + "\n".join(found)
    assert min(covered) > 0.3  # the case is the one meant: both objects in view
    # both materials move the image: the second (the cube) in every render
    assert all(np.any(r.grads["material"].kd[1]) and np.any(r.grads["material"].kd[0])
               for r in rows)


# ----------------------------------------------------------------- a 2048 x 2048 render


def disk_fraction(radius, distance, fov_y):
    """Fraction of a square perspective image covered by a sphere's silhouette (centred)."""
    half_angle = math.asin(radius / distance)
    r_ndc = math.tan(half_angle) / math.tan(math.radians(fov_y) / 2)
    return math.pi * r_ndc**2 / 4


def test_2048_square_hard_render_fits_in_memory_and_covers_the_sphere():
    mesh = icosphere(3)
    cam = look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=2048, height=2048, fov_y=45.0)
    scene = make_scene(mesh, cam, [point_light((2.0, 2.0, 4.0), 0.8)],
                       material(ks=0.5, shininess=50.0))
    image = np.asarray(render(scene))
    assert image.shape == (2048, 2048, 4) and np.all(np.isfinite(image))
    # the mesh lies between its inscribed sphere (radius: the nearest face plane) and the
    # unit sphere; the pixel grid blurs the outline by about its perimeter in pixels
    verts, faces = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces)
    tri = verts[faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    inner = np.min(np.abs(np.sum(normals * tri[:, 0], 1)) / np.linalg.norm(normals, axis=1))
    slack = 2 * math.pi * 2048 / 2048**2
    coverage = image[..., 3].mean()
    assert disk_fraction(inner, 3.0, 45.0) - slack < coverage < disk_fraction(1.0, 3.0, 45.0)


# ---------------------------------------------------------------------- shadow maps
# A second, smaller catalogue of one shared structure: a 20-face sphere over a 2-face
# floor, lit by a point light, a spot, a directional light, a disk and a sphere light, all
# with shadows (diffshade/shading/shadows.py; the disk and the sphere two samples each, so two cube
# maps each: penumbrae), in both raster modes. Cases differ in values only and render in
# one vmap per raster mode; values and gradients with respect to every float leaf of the
# mesh, the lights and the material must be finite.

SHADOW_SIZE = 10
# soft raster differentiates through the depth comparisons; hard raster's step passes no
# gradient to the maps, so float32 covers it alone
SHADOW_SETTINGS = {"float32": (RenderSettings(shadow_map_size=8),
                               RenderSettings(raster="soft", spot_edge="smooth",
                                              shadow_map_size=8)),
                   "float64": (RenderSettings(raster="soft", spot_edge="smooth",
                                              shadow_map_size=8),)}
SPHERE_RADIUS = 0.5


def shadow_scene(center=(0.0, 0.0, 0.0), floor_y=-1.0, bulb=(-1.0, 1.8, -1.0),
                 spot=((1.2, 1.8, -0.6), (-1.5, -2.8, 1.2)), sun=(0.2, -1.0, 1.1),
                 disk=((-0.8, 2.0, 0.6), (0.2, -1.0, 0.1), 0.5), ball=((0.7, 1.9, 0.4), 0.3)):
    """floor_y None: the floor touches the sphere's lowest vertex. disk: a disk light's
    centre, normal and radius; ball: a sphere light's centre and radius."""
    sphere = icosphere(0, SPHERE_RADIUS)
    floor_y = np.asarray(sphere.vertices)[:, 1].min() + center[1] if floor_y is None else floor_y
    floor = np.array([[-2.0, floor_y, -2.0], [2.0, floor_y, -2.0], [2.0, floor_y, 2.0],
                      [-2.0, floor_y, 2.0]])
    verts = np.concatenate([np.asarray(sphere.vertices, np.float64) + center, floor])
    faces = np.concatenate([np.asarray(sphere.faces), np.array([[12, 15, 14], [12, 14, 13]])])
    normals = np.concatenate([np.asarray(sphere.normals, np.float64), [[0.0, 1.0, 0.0]] * 4])
    mesh = Mesh(jnp.asarray(verts, float_dtype()), jnp.asarray(faces, jnp.int32),
                jnp.asarray(normals, float_dtype()))
    cam = look_at((0.0, 4.5, 3.2), (0.0, -1.0, 0.5), width=SHADOW_SIZE, height=SHADOW_SIZE,
                  fov_y=40.0)
    lights = [point_light(bulb, 0.8, ambient=0.05, shadows=True),
              spot_light(*spot, 0.7, cutoff=40.0, ambient=0.05, shadows=True),
              directional_light(sun, 0.6, ambient=0.05, shadows=True),
              area_light(disk[0], normal=disk[1], radius=disk[2], color=2.0, samples=2,
                         shadows=True),
              sphere_light(*ball, 2.0, samples=2, shadows=True)]
    return make_scene(mesh, cam, lights, material(ka=0.2, kd=0.6, ks=0.3, shininess=20.0),
                      global_ambient=0.1)


SHADOW_CASES = {
    "shadow_generic": dict(),
    "light_inside_object": dict(bulb=(0.0, 0.0, 0.0), spot=((0.05, 0.1, 0.0), (0.0, -1.0, 0.0)),
                                disk=((0.0, 0.1, 0.0), (0.0, -1.0, 0.1), 0.2),
                                ball=((0.05, 0.0, 0.05), 0.2)),
    "caster_touching_receiver": dict(floor_y=None),
    # the area lights' samples straddle the floor's plane, on the sphere's shadow edge
    "grazing_light_on_shadow_edge": dict(bulb=(-3.0, -0.99, 0.1), sun=(1.0, -1e-3, 0.2),
                                         spot=((-3.0, -0.98, 0.0), (1.0, 0.0, 0.05)),
                                         disk=((-3.0, -0.99, 0.1), (1.0, 1e-3, 0.0), 0.3),
                                         ball=((-3.0, -0.98, 0.0), 0.1)),
    "object_behind_light": dict(bulb=(0.0, 0.0, 3.0), sun=(0.0, 1.0, 0.0),
                                spot=((0.0, 0.0, 2.0), (0.0, 0.3, 1.0)),
                                disk=((0.0, 0.0, 3.0), (0.0, 0.0, 1.0), 0.5),
                                ball=((0.0, 0.0, 2.5), 0.3)),
    "zero_size_area_lights": dict(disk=((-0.8, 2.0, 0.6), (0.2, -1.0, 0.1), 0.0),
                                  ball=((0.7, 1.9, 0.4), 0.0)),
}


def shadow_params(scene):
    return {"vertices": scene.mesh.vertices, "normals": scene.mesh.normals,
            "lights": scene.lights, "material": scene.material}


@functools.partial(jax.jit, static_argnames=("settings",), compiler_options=FAST_COMPILE)
def shadow_losses_and_grads(params, like, weights, settings):
    def loss(p):
        scene = replace(like, mesh=Mesh(p["vertices"], like.mesh.faces, p["normals"]),
                        lights=p["lights"], material=p["material"])
        image = render(scene, settings)
        return jnp.sum(weights * image), image
    return jax.vmap(jax.value_and_grad(loss, has_aux=True))(params)


@pytest.mark.cost(100)
@pytest.mark.parametrize("dtype", DTYPES)
def test_shadow_cases_have_finite_values_and_gradients(dtype):
    found = []
    with jax.enable_x64(DTYPES[dtype]):
        scenes = {name: shadow_scene(**kw) for name, kw in SHADOW_CASES.items()}
        params = stack([jax.tree.map(np.asarray, shadow_params(s)) for s in scenes.values()])
        weights = jnp.asarray(np.random.default_rng(6).uniform(0.5, 1.5, (SHADOW_SIZE,) * 2
                                                                + (4,)), float_dtype())
        for settings in SHADOW_SETTINGS[dtype]:
            (_, images), grads = shadow_losses_and_grads(params, scenes["shadow_generic"],
                                                         weights, settings)
            for i, name in enumerate(SHADOW_CASES):
                row = f"{name}, raster={settings.raster}"
                if not np.all(np.isfinite(np.asarray(images[i]))):
                    found.append(f"{row}: non-finite image")
                bad = nonfinite_leaves(jax.tree.map(lambda g, i=i: np.asarray(g[i]), grads))
                found += [f"{row}: non-finite gradient in {bad}"] if bad else []
    assert not found, "\n".join(found)

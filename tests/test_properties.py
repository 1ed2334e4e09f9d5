"""Property tests (hypothesis): random valid scenes give a finite image, colours in [0, 1]
when clamped, alpha in [0, 1], and finite gradients with respect to every float leaf.

One structure throughout, so each settings object compiles once: a 16x16 image of an
icosphere(1) with randomly moved vertices (normals recomputed from them inside the loss,
so their gradient flows through `vertex_normals`), one light of each type, a material
with specular and emission. Everything else is drawn: the vertices' displacement, the
model transform (rotation, translation, scale 0.5-2 per axis), the camera (eye around the
mesh, target, up, fov, near/far), every light field (a positional light may sit exactly
on a vertex), and the material, with shininess from 0 to 10^4.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from diffshade import (
    Mesh,
    RenderSettings,
    ambient_light,
    directional_light,
    icosphere,
    look_at,
    make_scene,
    material,
    model_matrix,
    point_light,
    render,
    replace,
    spot_light,
)
from diffshade.scene.mesh import vertex_normals

SIZE = 16
SPHERE = icosphere(1)
RENDERS = (
    RenderSettings(),
    RenderSettings(shading="gouraud", raster="soft", specular="phong", spot_edge="smooth",
                   clamp=False, sigma=0.5, gamma=1e-3),
    RenderSettings(shading="flat_last", raster="soft", cull_backfaces=True, sigma=2.0),
)
PROPERTY_SETTINGS = settings(max_examples=30, deadline=None, derandomize=True, database=None,
                             suppress_health_check=[HealthCheck.too_slow])

# ---------------------------------------------------------------------- strategies

unit = st.floats(0.0, 1.0)
colour = st.tuples(unit, unit, unit)
coord = st.floats(-4.0, 4.0)
point = st.tuples(coord, coord, coord)
direction = point.filter(lambda v: np.linalg.norm(v) > 1e-3)
shininess = st.one_of(st.sampled_from([0.0, 0.01, 1.0, 1000.0, 10000.0]),
                      st.floats(-2.0, 4.0).map(lambda e: 10.0**e))
attenuation = st.tuples(st.floats(0.05, 2.0), st.floats(0.0, 1.0), st.floats(0.0, 1.0))


@st.composite
def vertices(draw):
    """icosphere(1) vertices [42, 3], each moved by up to 0.3 per axis."""
    amount = draw(st.floats(0.0, 0.3))
    seed = draw(st.integers(0, 2**31 - 1))
    noise = np.random.default_rng(seed).uniform(-1.0, 1.0, (len(SPHERE.vertices), 3))
    return np.asarray(SPHERE.vertices, np.float64) + amount * noise


@st.composite
def light_position(draw, verts):
    """Anywhere around the mesh, or exactly on one of its vertices."""
    on_vertex = draw(st.booleans())
    if on_vertex:
        return tuple(verts[draw(st.integers(0, len(verts) - 1))])
    return draw(point)


@st.composite
def cameras(draw):
    forward = np.asarray(draw(direction))
    eye = forward / np.linalg.norm(forward) * draw(st.floats(2.0, 8.0))
    target = draw(st.tuples(*[st.floats(-0.5, 0.5)] * 3))
    up = np.asarray(draw(direction))
    view = np.asarray(target) - eye
    assume(np.linalg.norm(np.cross(view, up)) > 1e-3 * np.linalg.norm(view) * np.linalg.norm(up))
    near = draw(st.floats(0.01, 1.0))
    return look_at(tuple(eye), target, tuple(up), width=SIZE, height=SIZE,
                   fov_y=draw(st.floats(10.0, 120.0)), near=near,
                   far=near + draw(st.floats(1.0, 100.0)))


@st.composite
def scenes(draw):
    verts = draw(vertices())
    lights = [ambient_light(draw(colour)),
              directional_light(draw(direction), draw(colour), ambient=draw(colour)),
              point_light(draw(light_position(verts)), draw(colour), ambient=draw(colour),
                          attenuation=draw(attenuation)),
              spot_light(draw(light_position(verts)), draw(direction), draw(colour),
                         ambient=draw(colour), attenuation=draw(attenuation),
                         cutoff=draw(st.one_of(st.floats(0.0, 90.0), st.just(180.0))),
                         exponent=draw(st.floats(0.0, 128.0)))]
    mat = material(ka=draw(colour), kd=draw(colour), ks=draw(colour), shininess=draw(shininess),
                   emission=draw(st.tuples(*[st.floats(0.0, 0.5)] * 3)))
    model = model_matrix(draw(st.tuples(*[st.floats(-0.5, 0.5)] * 3)),
                         draw(st.tuples(*[st.floats(-180.0, 180.0)] * 3)),
                         draw(st.tuples(*[st.floats(0.5, 2.0)] * 3)))
    mesh = Mesh(jnp.asarray(verts, jnp.float32), SPHERE.faces, SPHERE.normals)
    return make_scene(mesh, draw(cameras()), lights, mat, model=model,
                      global_ambient=draw(colour), background=draw(colour))


# ------------------------------------------------------------------------ the loss


def params_of(scene):
    """Every float leaf of the scene but the normals, recomputed from the vertices."""
    return {"vertices": scene.mesh.vertices, "model": scene.model, "camera": scene.camera,
            "lights": scene.lights, "material": scene.material,
            "global_ambient": scene.global_ambient, "background": scene.background}


# as in test_hard_cases.py: LLVM's backend optimizations change no value beyond rounding
FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}


@functools.partial(jax.jit, static_argnames=("render_settings",), compiler_options=FAST_COMPILE)
def image_and_grads(params, like, weights, render_settings):
    def loss(p):
        verts, faces = p["vertices"], like.mesh.faces
        mesh = Mesh(verts, faces, vertex_normals(verts, faces))
        others = {k: v for k, v in p.items() if k != "vertices"}
        image = render(replace(like, mesh=mesh, **others), render_settings)
        return jnp.sum(weights * image), image

    (_, image), grads = jax.value_and_grad(loss, has_aux=True)(params)
    return image, grads


WEIGHTS = np.random.default_rng(3).uniform(0.5, 1.5, (SIZE, SIZE, 4)).astype(np.float32)


@PROPERTY_SETTINGS
@given(scene=scenes(), which=st.integers(0, len(RENDERS) - 1))
def test_random_scenes_render_finite_images_and_gradients(scene, which):
    render_settings = RENDERS[which]
    image, grads = image_and_grads(params_of(scene), scene, WEIGHTS, render_settings)
    image = np.asarray(image)
    assert np.all(np.isfinite(image))
    top = 1.0 + 4 * np.finfo(np.float32).eps  # a blend may round a few ulps above 1
    assert 0.0 <= image[..., 3].min() and image[..., 3].max() <= top
    if render_settings.clamp:
        assert 0.0 <= image[..., :3].min() and image[..., :3].max() <= top
    bad = [jax.tree_util.keystr(path) for path, g in jax.tree_util.tree_flatten_with_path(grads)[0]
           if not np.all(np.isfinite(np.asarray(g)))]
    assert not bad, f"non-finite gradient in {bad}"

"""Gradients of `render` against central finite differences, in float64, for every kind of
scene parameter: vertices, model matrix, camera (eye, target, up, fov_y), lights (positions,
directions, colours, attenuation, spot cutoff with the smooth edge and exponent), material
(ka, kd, ks, shininess, emission), global ambient and background.

The loss is sum(w * image) with fixed random weights w. For each parameter kind, the JAX
gradient (jax.jit(jax.grad(loss)), as an optimizer step computes it) projected on a few
random unit directions v must match
(f(x + h v) - f(x - h v)) / 2h with h = 1e-6. The candidate search is not differentiable,
so the check is only meaningful where it does not change within +-h: that is asserted for
the parameters that move geometry (the scenes keep pixel centres off triangle edges and
footprint boundaries; sigma = 2 px^2 and gamma = 1e-2 keep the soft image smooth).

Soft mode is checked for every shading mode; hard mode (no silhouette gradient by design)
for the same parameters: away from edges its image is smooth in all of them.
"""

import functools
import zlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffshade import (
    Mesh,
    RenderSettings,
    ambient_light,
    directional_light,
    icosphere,
    look_at,
    make_scene,
    material,
    point_light,
    rasterize_scene,
    render,
    replace,
    spot_light,
)
from diffshade.numerics import float_dtype

pytestmark = pytest.mark.usefixtures("x64")

H_STEP = 1e-6


def scene_for_gradients():
    """Icosphere (80 faces) on 20 x 18 px with its silhouette in view, lit by every light
    type (a smooth-edged spot cone crosses the sphere); colours stay below 1, so the clamp
    is inactive."""
    mesh = icosphere(1)
    dt = float_dtype()
    mesh = Mesh(jnp.asarray(mesh.vertices, dt), mesh.faces, jnp.asarray(mesh.normals, dt))
    cam = look_at((0.4, 0.3, 3.4), (0.05, -0.02, 0.0), width=20, height=18, fov_y=40.0)
    lights = [ambient_light(0.1),
              directional_light((-0.3, -0.5, -1.0), (0.3, 0.25, 0.2), ambient=0.05),
              point_light((2.0, 1.5, 3.0), 0.4, ambient=0.05, attenuation=(1.0, 0.1, 0.02)),
              spot_light((0.5, 0.5, 3.0), (-0.15, -0.1, -1.0), (0.4, 0.35, 0.3), cutoff=12.0,
                         exponent=2.0, ambient=0.05)]
    mat = material(ka=(0.2, 0.25, 0.3), kd=(0.4, 0.35, 0.3), ks=(0.25, 0.2, 0.15),
                   shininess=12.0, emission=(0.05, 0.02, 0.01))
    model = np.eye(4)
    model[:3, 3] = (0.03, -0.02, 0.05)
    return make_scene(mesh, cam, lights, mat, model=model, global_ambient=0.15,
                      background=(0.1, 0.15, 0.2))


def field(*path):
    """(get, set) of the scene attribute at `path` (attribute names)."""
    return (lambda scene: functools.reduce(getattr, path, scene),
            lambda scene, value: set_at(scene, path, value))


def set_at(obj, path, value):
    if len(path) == 1:
        return replace(obj, **{path[0]: value})
    return replace(obj, **{path[0]: set_at(getattr(obj, path[0]), path[1:], value)})


def model_block(rows, cols):
    """(get, set) of a block of the model matrix."""
    return (lambda scene: scene.model[rows, cols],
            lambda scene, value: replace(scene, model=scene.model.at[rows, cols].set(value)))


#: parameter kind -> (get, set); GEOMETRY kinds move the projected triangles
KINDS = {
    "vertices": field("mesh", "vertices"),
    "model_translation": model_block(slice(0, 3), 3),
    "model_linear": model_block(slice(0, 3), slice(0, 3)),
    "eye": field("camera", "eye"),
    "target": field("camera", "target"),
    "up": field("camera", "up"),
    "fov_y": field("camera", "fov_y"),
    "ambient_light": field("lights", "ambient", "ambient"),
    "directional_direction": field("lights", "directional", "direction"),
    "directional_ambient": field("lights", "directional", "ambient"),
    "directional_diffuse": field("lights", "directional", "diffuse"),
    "directional_specular": field("lights", "directional", "specular"),
    "point_position": field("lights", "point", "position"),
    "point_diffuse": field("lights", "point", "diffuse"),
    "point_specular": field("lights", "point", "specular"),
    "point_attenuation": field("lights", "point", "attenuation"),
    "spot_position": field("lights", "spot", "position"),
    "spot_direction": field("lights", "spot", "direction"),
    "spot_cutoff": field("lights", "spot", "cutoff"),
    "spot_exponent": field("lights", "spot", "exponent"),
    "spot_diffuse": field("lights", "spot", "diffuse"),
    "spot_ambient": field("lights", "spot", "ambient"),
    "ka": field("material", "ka"),
    "kd": field("material", "kd"),
    "ks": field("material", "ks"),
    "shininess": field("material", "shininess"),
    "emission": field("material", "emission"),
    "global_ambient": field("global_ambient"),
    "background": field("background"),
}
GEOMETRY = {"vertices", "model_translation", "model_linear", "eye", "target", "up", "fov_y"}


def with_params(scene, params):
    for name, value in params.items():
        scene = KINDS[name][1](scene, value)
    return scene


def weights(scene):
    """Fixed random loss weights [H, W, 4]."""
    cam = scene.camera
    return jnp.asarray(np.random.default_rng(7).normal(size=(cam.height, cam.width, 4)))


@functools.partial(jax.jit, static_argnames=("settings",))
def loss(params, scene, w, settings):
    return jnp.sum(w * render(with_params(scene, params), settings))


grad_loss = jax.jit(jax.grad(loss), static_argnames=("settings",))


def directions(name, shape, count=2):
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    for _ in range(count):
        v = rng.normal(size=shape)
        yield jnp.asarray(v / np.linalg.norm(v))


def assert_candidates_unchanged(scene, name, v, settings):
    """The finite-difference steps do not change which faces are candidates (their order
    may change: faces clamped to a shared vertex tie in depth, and the blend is a sum)."""
    get, set_ = KINDS[name]
    ids = [np.sort(rasterize_scene(set_(scene, get(scene) + s * H_STEP * v), settings).face_ids)
           for s in (-1.0, 0.0, 1.0)]
    np.testing.assert_array_equal(ids[0], ids[1])
    np.testing.assert_array_equal(ids[2], ids[1])


def check_kind(name, settings):
    scene = scene_for_gradients()
    w = weights(scene)
    params = {n: get(scene) for n, (get, _) in KINDS.items()}
    grads = grad_loss(params, scene, w, settings)
    for v in directions(name, jnp.shape(params[name])):
        if name in GEOMETRY:
            assert_candidates_unchanged(scene, name, v, settings)
        shifted = [loss({**params, name: params[name] + s * H_STEP * v}, scene, w, settings)
                   for s in (1.0, -1.0)]
        fd = float(shifted[0] - shifted[1]) / (2.0 * H_STEP)
        ad = float(jnp.vdot(grads[name], v))
        assert abs(fd) > 1e-4, f"{name}: the loss hardly depends on it ({fd}); a vacuous check"
        np.testing.assert_allclose(ad, fd, rtol=1e-4, err_msg=name)


SOFT = dict(raster="soft", faces_per_pixel=40, sigma=2.0, gamma=1e-2, spot_edge="smooth")


def test_soft_gradient_is_the_same_with_and_without_jit():
    # an optimizer step is jitted: jax.jit(jax.grad(f)) must be jax.grad(f). (A minimum of
    # computed values, such as the distance to the nearest of three edges, loses its
    # gradient under jit when it relies on jnp.minimum, whose derivative compares the
    # operand bitwise with the result, and XLA recomputes the operand: jax issue #40564.)
    scene, settings = scene_for_gradients(), RenderSettings(**SOFT)
    w = weights(scene)

    def f(vertices):
        return jnp.sum(w * render(replace(scene, mesh=replace(scene.mesh, vertices=vertices)),
                                  settings))
    eager = np.asarray(jax.grad(f)(scene.mesh.vertices))
    jitted = np.asarray(jax.jit(jax.grad(f))(scene.mesh.vertices))
    np.testing.assert_allclose(jitted, eager, rtol=0, atol=1e-9 * np.abs(eager).max())


@pytest.mark.parametrize("name", sorted(KINDS))
@pytest.mark.parametrize("shading", ["phong", "gouraud", "flat"])
def test_soft_gradient_matches_finite_differences(shading, name):
    check_kind(name, RenderSettings(shading=shading, **SOFT))


@pytest.mark.parametrize("name", sorted(GEOMETRY))
def test_soft_gradient_at_default_sigma_and_gamma(name):
    check_kind(name, RenderSettings(raster="soft", faces_per_pixel=40, spot_edge="smooth"))


@pytest.mark.parametrize("name", sorted(KINDS))
def test_hard_gradient_matches_finite_differences(name):
    check_kind(name, RenderSettings(spot_edge="smooth"))

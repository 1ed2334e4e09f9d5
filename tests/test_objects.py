"""Scenes of several objects (diffshade.scene.objects, make_scene(objects=...)).

References: each object rendered alone as a single-object scene (the code path that has
no object ids), composited by hand (hard raster: the nearer surface per pixel, from each
render's own depth buffer; soft raster with objects apart on screen: each pixel is the
one object's that covers it), and central finite differences in float64 for the
per-object material gradients.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffshade as ds
from diffshade.scene.objects import unstack_material

pytestmark = pytest.mark.usefixtures("x64")

# a four-sided pyramid without a base, apex off-centre: seen apex-first its faces are
# front faces; turned apex-away (rotate_deg y 180) one looks into it, at back faces
PYRAMID = ([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0],
            [0.13, 0.07, 0.9]], [[0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]])
FRONT_A = dict(ka=0.3, kd=(0.7, 0.2, 0.1), shininess=5.0)  # no ks, no emission
FRONT_B = dict(ka=0.1, kd=(0.1, 0.3, 0.8), ks=0.6, shininess=30.0, emission=0.05)
BACK_B = dict(ka=0.2, kd=(0.2, 0.8, 0.2), ks=0.3, shininess=10.0)
OVERLAPPING = (((-0.45, 0.1, 0.3), (0.0, 0.0, 0.0), (0.7,) * 3),
               ((0.5, -0.1, 0.0), (10.0, 180.0, 0.0), (0.8,) * 3))
H_STEP = 1e-6
APART = (((-1.5, 0.1, 0.0), (0.0, 0.0, 0.0), (0.5,) * 3),
         ((1.5, -0.1, 0.0), (0.0, 180.0, 0.0), (0.5,) * 3))


def parts(placement, two_sided=True):
    """(camera, lights, [(mesh, transform, material, back_material)] per object)."""
    mesh = ds.mesh_from_arrays(*PYRAMID)
    cam = ds.look_at((0.2, 0.3, 4.0), (0.0, 0.0, 0.0), width=24, height=16, fov_y=50.0)
    lights = [ds.directional_light((0.3, -0.4, -1.0), 0.6, ambient=0.1),
              ds.point_light((-1.0, 1.5, 3.0), (0.5, 0.4, 0.3), attenuation=(1.0, 0.1, 0.0))]
    back = ds.material(**BACK_B) if two_sided else None
    return cam, lights, [
        (mesh, ds.model_matrix(*placement[0]), ds.material(**FRONT_A), None),
        (mesh, ds.model_matrix(*placement[1]), ds.material(**FRONT_B), back)]


def single_scenes(placement, two_sided=True):
    cam, lights, objects = parts(placement, two_sided)
    return [ds.make_scene(mesh, cam, lights, mat, model=transform, back_material=back,
                          two_sided=two_sided) for mesh, transform, mat, back in objects]


def joined_scene(placement, two_sided=True):
    cam, lights, objects = parts(placement, two_sided)
    return ds.make_scene(objects=[ds.scene_object(mesh, mat, transform=transform,
                                                  back_material=back)
                                  for mesh, transform, mat, back in objects],
                         camera=cam, lights=lights, two_sided=two_sided)


def composite_nearer(settings, singles):
    """The hard-raster reference: per pixel, the covering object nearest the eye."""
    images = [np.asarray(ds.render(s, settings)) for s in singles]
    # coverage and depth do not depend on the shading mode: one compilation serves all
    frags = [ds.rasterize_scene(s, ds.RenderSettings()) for s in singles]
    depth = [np.where(f.valid[..., 0], f.depth[..., 0], np.inf) for f in frags]
    return np.where((depth[0] <= depth[1])[..., None], images[0], images[1]), depth


# gouraud reads per-vertex samples as flat_last does; the gradient test below renders it
@pytest.mark.parametrize("shading", ["phong", "flat", "flat_last"])
def test_two_objects_render_as_the_nearer_of_their_single_renders(shading):
    settings = ds.RenderSettings(shading=shading)
    want, depth = composite_nearer(settings, single_scenes(OVERLAPPING))
    got = np.asarray(ds.render(joined_scene(OVERLAPPING), settings))
    # the case is the one meant: the objects overlap on screen, and the back material shows
    both = np.isfinite(depth[0]) & np.isfinite(depth[1])
    assert both.sum() >= 5 and (np.isfinite(depth[0]) & ~both).sum() >= 5
    assert np.abs(want[..., 1] - want[..., 0]).max() > 0.2  # green back faces of object 1
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


def test_soft_render_of_objects_apart_is_each_objects_own():
    settings = ds.RenderSettings(raster="soft", sigma=0.5, gamma=1e-3)
    singles = [np.asarray(ds.render(s, settings)) for s in single_scenes(APART, False)]
    got = np.asarray(ds.render(joined_scene(APART, False), settings))
    first, second = singles[0][..., 3] > 0, singles[1][..., 3] > 0
    assert first.sum() > 20 and second.sum() > 20 and not np.any(first & second)
    want = np.where(first[..., None], singles[0], singles[1])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    np.testing.assert_allclose(got[..., 3], singles[0][..., 3] + singles[1][..., 3], atol=1e-9)


# ----------------------------------------------------------------------- transparency


@pytest.mark.parametrize("raster", ["hard", "soft"])
def test_each_fragment_takes_its_objects_kt(raster):
    """Object 0 transparent (RGB kt), object 1 opaque: apart on screen, each pixel is the
    pixel of that object rendered alone (its own transparent or opaque path)."""
    settings = ds.RenderSettings(raster=raster, sigma=0.5, gamma=1e-3, faces_per_pixel=4)
    cam, lights, objects = parts(APART, two_sided=False)
    mats = [ds.material(**FRONT_A, kt=(0.6, 0.3, 0.1)), ds.material(**FRONT_B)]
    objects = [(mesh, transform, mat)
               for (mesh, transform, _, _), mat in zip(objects, mats, strict=True)]
    singles = [np.asarray(ds.render(ds.make_scene(mesh, cam, lights, mat, model=transform),
                                    settings)) for mesh, transform, mat in objects]
    joined = ds.make_scene(objects=[ds.scene_object(mesh, mat, transform=transform)
                                    for mesh, transform, mat in objects],
                           camera=cam, lights=lights)
    got = np.asarray(ds.render(joined, settings))
    first, second = singles[0][..., 3] > 0, singles[1][..., 3] > 0
    assert first.sum() >= 15 and second.sum() >= 15 and not np.any(first & second)
    # the case is the one meant: object 0 shows the background through it, object 1 not
    assert singles[0][..., 3].max() < singles[1][..., 3].max() - 0.1
    want = np.where(first[..., None], singles[0], singles[1])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)


# ------------------------------------------------------------------ material gradients


def test_per_object_material_gradients_match_central_differences():
    # the material reaches the image the same way in every mode: one (per-vertex) suffices
    settings = ds.RenderSettings(shading="gouraud")
    scene = joined_scene(OVERLAPPING)
    weights = jnp.asarray(np.random.default_rng(3).uniform(0.5, 1.5, (16, 24, 4)))

    @jax.jit
    def loss(materials):
        front, back = materials
        return jnp.sum(weights * ds.render(ds.replace(scene, material=front,
                                                      back_material=back), settings))

    at = (scene.material, scene.back_material)
    grads = jax.grad(loss)(at)
    rng = np.random.default_rng(4)
    for obj in (0, 1):
        # a direction that moves object `obj`'s front and back materials only
        direction = jax.tree.map(
            lambda x, obj=obj: np.where(np.arange(2).reshape((2,) + (1,) * (x.ndim - 1)) == obj,
                               rng.normal(size=x.shape), 0.0), at)
        terms = jax.tree.leaves(jax.tree.map(lambda g, d: np.asarray(g) * d, grads, direction))
        slope, scale = sum(t.sum() for t in terms), sum(np.abs(t).sum() for t in terms)
        moved = [jax.tree.map(lambda x, d, s=s: x + s * H_STEP * d, at, direction)
                 for s in (1, -1)]
        central = (loss(moved[0]) - loss(moved[1])) / (2 * H_STEP)
        assert scale > 1.0, f"object {obj}: its material barely moves the image"
        assert abs(slope - central) <= 1e-6 * scale, (obj, slope, central)


# ------------------------------------------------------------------------ the API


def test_one_object_is_the_single_object_form():
    cam, lights, objects = parts(OVERLAPPING)
    mesh, transform, mat, back = objects[1]
    model = ds.model_matrix((0.0, 0.2, 0.0))
    one = ds.make_scene(objects=[ds.scene_object(mesh, mat, transform=transform,
                                                 back_material=back)],
                        camera=cam, lights=lights, model=model)
    plain = ds.make_scene(mesh, cam, lights, mat, model=model @ transform, back_material=back)
    assert one.objects is None
    assert jax.tree.structure(one) == jax.tree.structure(plain)
    jax.tree.map(np.testing.assert_array_equal, one, plain)


def test_joined_scene_holds_each_objects_material_and_ids():
    scene = joined_scene(OVERLAPPING)
    assert scene.objects.faces.tolist() == [0] * 4 + [1] * 4
    assert scene.objects.vertices.tolist() == [0] * 5 + [1] * 5
    front_a = unstack_material(scene.material, 0)
    np.testing.assert_array_equal(front_a.kd, FRONT_A["kd"])
    np.testing.assert_array_equal(front_a.ks, 0.0)  # absent: zeros, like the other's ks
    # object 0 has no back material: its front one serves its back faces
    np.testing.assert_array_equal(unstack_material(scene.back_material, 0).kd, FRONT_A["kd"])
    np.testing.assert_array_equal(unstack_material(scene.back_material, 1).kd, BACK_B["kd"])
    # the second mesh is moved by its transform: vertex 4 (apex) to the far side
    apex = scene.mesh.vertices[9]
    want = np.asarray(OVERLAPPING[1][0]) + 0.8 * np.array([0.13, 0.07, 0.9]) @ np.asarray(
        ds.model_matrix((0, 0, 0), OVERLAPPING[1][1])[:3, :3]).T
    np.testing.assert_allclose(apex, want, atol=1e-12)


@pytest.mark.parametrize("call, error, message", [
    (lambda m, c: ds.make_scene(objects=[m], camera=c), TypeError,
     "objects[0]: got Mesh; expected SceneObject"),
    (lambda m, c: ds.make_scene(objects=[], camera=c), TypeError,
     "objects: got []; expected a non-empty list of SceneObject"),
    (lambda m, c: ds.make_scene(m, c, objects=[ds.scene_object(m)]), ValueError,
     "objects: given with mesh; expected either objects"),
    (lambda m, c: ds.make_scene(objects=[ds.scene_object(m)], camera=c,
                                material=ds.material()), ValueError,
     "objects: given with material; expected either"),
    (lambda m, c: ds.scene_object(m, transform=np.zeros((4, 4))), ValueError,
     "transform: the upper 3x3 block is singular"),
    (lambda m, c: ds.scene_object(m, transform=np.eye(3)), ValueError,
     "transform: got an array of shape (3, 3); expected a finite 4x4 matrix"),
    (lambda m, c: ds.scene_object(m, material="red"), TypeError,
     "material: got str; expected Material or None"),
    (lambda m, c: ds.scene_object("cup.obj"), TypeError, "mesh: got str; expected Mesh"),
    (lambda m, c: ds.make_scene(None, c), TypeError, "mesh: got NoneType; expected Mesh"),
])
def test_bad_objects_are_clear_errors(call, error, message):
    cam, _, objects = parts(OVERLAPPING)
    with pytest.raises(error) as err:
        call(objects[0][0], cam)
    assert str(err.value).startswith(message), str(err.value)

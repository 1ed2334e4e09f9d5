"""Fitting with shadows and transparency (fitting.model.cache's shadow visibility and layers).

References: the targets and the float64 comparisons are full renders (`diffshade.render`,
which builds its shadow maps and composites its layers itself); the recovered values
are the known materials that rendered the targets; kt's gradient is checked against
central differences in float64.

The scene: a box on a table, lit by a point light that casts shadows and a sun that does
not; the box is transparent (kt), so pixels see the table through it. Everything runs in
float64 on 16 x 16 images, so the tests share their compiled programs.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import diffshade as ds
from diffshade.scene.lights import group_lights
from diffshade.scene.objects import unstack_material
from fitting import FitSpec, View, fit
from fitting.data.views import dataset_of_scene, view_scene
from fitting.model import build_cache, make_loss, predict
from fitting.spec import to_unconstrained

# (built in the tests, in the float dtype of each)
BOX = dict(ka=(0.25, 0.2, 0.15), kd=(0.6, 0.3, 0.2), ks=(0.4, 0.35, 0.3), shininess=30.0)
TABLE = dict(ka=(0.2, 0.25, 0.3), kd=(0.3, 0.45, 0.7), ks=0.1, shininess=8.0)
KT = (0.35, 0.5, 0.65)
SETTINGS = ds.RenderSettings(shadow_map_size=64)


def box_on_table(size, glass=False, shadows=True, truth=None):
    """A Dataset of two views of the box on the table, the targets rendered by `render`
    with `truth` (default the box and table materials, the box with kt when `glass`), its
    lights casting shadows or not (`shadows`: the fitted model's, not the targets')."""
    box_mat = ds.material(**BOX, kt=KT if glass else None)
    objects = [ds.scene_object(ds.box((0.7, 0.7, 0.7)), box_mat,
                               transform=ds.model_matrix((0.1, 0.35, 0.0), (0.0, 30.0, 0.0))),
               ds.scene_object(ds.box((2.4, 0.2, 1.8)), ds.material(**TABLE),
                               transform=ds.model_matrix((0.0, -0.1, 0.0)))]
    camera = ds.look_at((0.0, 1.5, 2.5), (0.0, 0.2, 0.0), width=size, height=size)
    scene = ds.make_scene(objects=objects, camera=camera, global_ambient=0.3)
    truth = scene.material if truth is None else truth
    targets, views = [], []
    for eye in ((0.4, 1.8, 2.4), (-1.6, 1.4, 1.8)):
        camera = ds.look_at(eye, (0.0, 0.2, 0.0), width=size, height=size, fov_y=50.0)
        for cast in (True, shadows):
            lights = group_lights([ds.point_light((1.2, 2.2, 0.8), 0.8, shadows=cast),
                                      ds.directional_light((0.3, -1.0, -0.5), 0.3)])
            views.append(View(camera, lights, np.zeros((size, size, 3))))
    blank = dataset_of_scene(scene, views[::2], truth=truth, settings=SETTINGS)
    targets = [np.asarray(ds.render(view_scene(blank, i, truth), SETTINGS))[..., :3]
               for i in range(2)]
    return dataclasses.replace(blank, views=[dataclasses.replace(v, target=t) for v, t
                                             in zip(views[1::2], targets, strict=True)])


def perturbed(material):
    """Another material of the same structure, every value moved."""
    return jax.tree.map(lambda x: 0.8 * x + 0.1 * jnp.flip(x, -1) if x.ndim else 1.3 * x,
                        material)


pytestmark = pytest.mark.usefixtures("x64")


@pytest.fixture(scope="module")
def glass():
    with jax.enable_x64(True):
        return box_on_table(16, glass=True)


def test_cached_pixels_equal_render_with_shadows_and_layers(glass):
    data = build_cache(glass, glass.truth, edge_margin=0)
    assert data.views[0].layers is not None and data.views[0].shadows is not None
    for material in (glass.truth, perturbed(glass.truth)):
        for i, samples in enumerate(data.views):
            scene = view_scene(glass, i, material)
            image = np.asarray(ds.render(scene, SETTINGS))[..., :3].reshape(-1, 3)
            got = predict(material, data.lights[i], data.global_ambient, samples, data.settings)
            np.testing.assert_allclose(got, image[np.asarray(samples.pixels)], atol=1e-12,
                                       rtol=0)
    # the comparison is not of unshadowed images: the light misses some samples
    seen = np.concatenate([np.ravel(v.shadows[("point", 0)]) for v in data.views])
    assert np.sum(seen == 0.0) >= 20 and np.sum(seen == 1.0) >= 20


def test_cached_loss_gradient_wrt_kt_equals_central_differences(glass):
    data = build_cache(glass, glass.truth, edge_margin=0)
    spec = FitSpec.from_names(["kd", "kt"])
    params = to_unconstrained(perturbed(glass.truth), spec)
    check_grads(lambda p: make_loss(spec)(p, data), (params,), order=1, modes=["rev"],
                eps=1e-6, atol=1e-7, rtol=1e-6)


def test_fit_recovers_kd_and_kt_of_a_glass_box_over_a_table_from_shadowed_targets(glass):
    truth = glass.truth
    # held at the truth: ka, ks, shininess; kd starts at 0.5, kt at 0.5 (the box) and at
    # 0.05 (the table, truly 0: nearly opaque, as one would start a table)
    kt = jnp.asarray([[0.5] * 3, [0.05] * 3], truth.kd.dtype)
    init = dataclasses.replace(truth, kd=jnp.full_like(truth.kd, 0.5), kt=kt)
    result = fit(glass, FitSpec.from_names(["kd", "kt"]), init, steps=30,
                 with_uncertainty=False)
    fitted = [unstack_material(result.material, i) for i in range(2)]
    np.testing.assert_allclose(fitted[0].kt, KT, atol=1e-5)
    np.testing.assert_allclose(fitted[1].kt, 0.0, atol=1e-4)  # at its bound: slower
    for i in range(2):
        np.testing.assert_allclose(fitted[i].kd, unstack_material(truth, i).kd, rtol=1e-5,
                                   err_msg=f"object {i}")
    assert "objects[1].kt[r]" in result.at_bound and "objects[0].kt[r]" not in result.at_bound


def test_kt_is_one_row_of_the_table_and_the_files_carry_it():
    from fitting.data.folder import material_dict, material_from_dict
    from fitting.inputs import fit_spec
    from fitting.spec.params import KINDS, TRANSFORMS, at_bound
    assert TRANSFORMS[KINDS["kt"].transform].bounds(3.0) == (0.0, 1.0)  # whatever `upper`
    spec = fit_spec("kd,kt", "kt")  # --fit kd,kt --grey kt
    assert spec == FitSpec(ka=None, ks=None, shininess=False, kt="grey")
    assert list(at_bound({"kt": np.array([0.0, 0.5, 1.0])}, spec)) == [True, False, True]
    glassy = ds.material(kd=0.5, kt=(0.1, 0.2, 0.3))
    np.testing.assert_allclose(material_from_dict(material_dict(glassy), "x").kt, glassy.kt)
    assert material_from_dict(material_dict(ds.material()), "x").kt is None

"""Fitting the materials of several objects at once (fitting with a stacked material).

References: the targets are rendered by `diffshade.render` with known materials (the
truth the fit must recover); the cached pixels are compared with full renders; the .mtl
text is parsed back.
"""

import dataclasses

import jax
import numpy as np
import pytest

import diffshade as ds
from diffshade.scene.lights import group_lights
from diffshade.scene.objects import unstack_material
from fitting import FitSpec, View, fit, view_scene
from fitting.data.views import dataset_of_scene
from fitting.model import build_cache, make_loss
from fitting.report.result import mtl_text
from fitting.spec import to_unconstrained

TRUTH = [ds.material(ka=(0.25, 0.2, 0.15), kd=(0.6, 0.3, 0.2), ks=(0.5, 0.45, 0.4),
                     shininess=30.0),
         ds.material(ka=(0.1, 0.15, 0.2), kd=(0.2, 0.35, 0.7), ks=(0.3, 0.3, 0.35),
                     shininess=12.0)]
SIZE = 32


@pytest.fixture(scope="module")
def dataset():
    """A sphere resting on a slab, two views, each lit by a sun and a bulb."""
    objects = [ds.scene_object(ds.icosphere(2, 0.5), TRUTH[0],
                               transform=ds.model_matrix((0.0, 0.5, 0.0))),
               ds.scene_object(ds.box((2.0, 0.2, 1.6)), TRUTH[1],
                               transform=ds.model_matrix((0.0, -0.1, 0.0)))]
    cam = ds.look_at((0.0, 1.5, 2.5), (0.0, 0.2, 0.0), width=SIZE, height=SIZE)
    scene = ds.make_scene(objects=objects, camera=cam, global_ambient=0.3)
    views = []
    for eye, sun in (((0.3, 1.6, 2.4), (-0.4, -1.0, -0.6)), ((-1.8, 1.2, 1.6), (0.5, -1.0, -0.3))):
        lights = group_lights([ds.directional_light(sun, 0.7),
                               ds.point_light((1.0, 2.0, 1.5), 0.5)])
        camera = ds.look_at(eye, (0.0, 0.2, 0.0), width=SIZE, height=SIZE, fov_y=50.0)
        views.append(View(camera, lights, np.zeros((SIZE, SIZE, 3))))
    blank = dataset_of_scene(scene, views, truth=scene.material)
    targets = [np.asarray(ds.render(view_scene(blank, i, scene.material)))[..., :3]
               for i in range(len(views))]
    return dataclasses.replace(blank, views=[dataclasses.replace(v, target=t) for v, t
                                             in zip(views, targets, strict=True)])


def test_cached_loss_equals_full_render_loss_with_two_objects(dataset):
    guess = jax.tree.map(lambda *a: np.stack(a),
                         ds.material(ka=0.2, kd=(0.3, 0.7, 0.5), ks=0.6, shininess=9.0),
                         ds.material(ka=0.1, kd=(0.8, 0.2, 0.4), ks=0.2, shininess=40.0))
    data = build_cache(dataset, dataset.truth, edge_margin=0)
    assert data.views[0].objects is not None
    cached = float(make_loss(FitSpec())(to_unconstrained(guess, FitSpec()), data))
    squares = count = 0.0
    for i, view in enumerate(dataset.views):
        image = np.asarray(ds.render(view_scene(dataset, i, guess)))
        kept = image[..., 3] > 0
        diff = image[..., :3][kept].astype(np.float64) - view.target[kept]
        squares, count = squares + np.sum(diff**2), count + diff.size
    assert cached == pytest.approx(squares / count, rel=1e-5)


def test_fit_recovers_both_materials_with_a_report_and_a_newmtl_each(dataset):
    init = jax.tree.map(lambda *a: np.stack(a), *[ds.material(ka=0.3, kd=0.5, ks=0.3,
                                                              shininess=20.0)] * 2)
    result = fit(dataset, FitSpec(), init, steps=40)
    for i in range(2):
        fitted, truth = unstack_material(result.material, i), TRUTH[i]
        for name in ("ka", "kd", "ks", "shininess"):
            np.testing.assert_allclose(getattr(fitted, name), getattr(truth, name), rtol=2e-3,
                                       err_msg=f"object {i} {name}")
        assert max(np.max(e) for e in result.errors["objects"][i].values()) < 2e-3
    reports = result.object_reports()
    assert [r.names[0] for r in reports] == ["objects[0].ka[r]", "objects[1].ka[r]"]
    assert all(len(r.names) == 10 and np.all(np.isfinite(r.std_errors)) for r in reports)
    # the table: one row per object's scalar, with its true value from the stacked truth
    rows = {line.split()[0]: line.split()[1:] for line in result.summary().splitlines()
            if line.startswith("objects[")}
    assert len(rows) == 2 * 10
    for i in range(2):
        for name, c in (("kd[b]", 2), ("ks[r]", 0), ("shininess", None)):
            want = getattr(TRUTH[i], name.split("[")[0])
            true, fitted = (float(x) for x in rows[f"objects[{i}].{name}"][:2])
            want = float(want if c is None else want[c])
            assert true == pytest.approx(want, rel=1e-4) and fitted == pytest.approx(
                want, rel=2e-3), (i, name, rows[f"objects[{i}].{name}"])
    entries = mtl_text(result.material).split("newmtl ")[1:]
    assert [e.split("\n")[0] for e in entries] == ["diffshade_fit_0", "diffshade_fit_1"]
    for entry, i in zip(entries, range(2), strict=True):
        kd = [line for line in entry.split("\n") if line.startswith("Kd ")][0]
        np.testing.assert_allclose([float(x) for x in kd.split()[1:]], TRUTH[i].kd, atol=2e-3)


def test_dataset_folder_of_several_objects_round_trips(dataset, tmp_path):
    from fitting.data.folder import load_dataset, save_dataset
    loaded = load_dataset(save_dataset(dataset, tmp_path / "data"))
    np.testing.assert_array_equal(loaded.mesh.vertices, dataset.mesh.vertices)
    for field in ("faces", "vertices"):
        np.testing.assert_array_equal(getattr(loaded.objects, field),
                                      getattr(dataset.objects, field))
    for i, truth in enumerate(TRUTH):
        for name in ("ka", "kd", "ks", "shininess"):
            np.testing.assert_array_equal(np.asarray(getattr(loaded.truth, name))[i],
                                          getattr(truth, name))
    for mine, theirs in zip(loaded.views, dataset.views, strict=True):
        np.testing.assert_array_equal(mine.target, theirs.target)

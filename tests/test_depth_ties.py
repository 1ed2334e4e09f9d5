"""Hard raster's depth ties (docs/rendering.md#coplanar-faces): fragments within DEPTH_TIE
in NDC depth are ordered by face index, so coplanar faces of different objects come out
in one order on every path.

References: a naive NumPy loop over pixels and objects that orders each pixel's
fragments by the documented rule (stacked quads seen by an orthographic camera, their
corners on pixel centres); the host and the JAX searches against it and against each
other (float64 and float32, square and non-square images); the fitting cache's
prediction against `render` on tests/test_fit_effects' box resting on a table (the
pixel-for-pixel claim of fitting.model.cache), and a fit of kd and kt there against the
known truth.
"""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import diffshade as ds
from diffshade.host.candidates import DEPTH_TIE
from diffshade.raster.search import search_faces
from diffshade.scene.objects import unstack_material
from fitting import FitSpec, fit
from fitting.data.views import view_scene
from fitting.model import build_cache, predict

#: (z, box x0, x1, y0, y1) of the stacked quads, in the scene's order. The corners lie on
#: pixel centres (pixels are 0.25 wide): their edges and diagonals pass through centres.
#: "label" and "table" are coplanar; "film" lies a hair (far below the tie width) in front
#: of them and "cover" and "floor" well in front of and behind them.
QUADS = {
    "label": (0.0, -0.875, 0.625, -0.625, 0.375),
    "table": (0.0, -1.375, 1.125, -1.125, 0.875),
    "film": (2.0 ** -30, -0.375, 1.375, -0.875, 0.625),
    "cover": (0.5, -0.125, 0.875, -0.375, 1.125),
    "floor": (-0.5, -1.125, 0.375, -0.875, 0.625),
}
LAYERS = len(QUADS)
NEAR, FAR, EYE_Z = 0.5, 10.0, 3.0
#: powers of two, so that NDC pixel centres are exact: centres on the quads' outlines and
#: corners lie on them exactly
SIZES = ((16, 16), (32, 16), (16, 32))


def quad_mesh(z, x0, x1, y0, y1):
    """Two counter-clockwise triangles (split along a diagonal) in the plane z."""
    verts = [[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]]
    return ds.mesh_from_arrays(np.asarray(verts), np.array([[0, 1, 2], [0, 2, 3]]))


def stacked_quads(width, height, dtype=np.float64):
    """The QUADS, one object each, seen along -z by an orthographic camera whose pixels are
    0.25 wide."""
    objects = [ds.scene_object(quad_mesh(*np.asarray(q, dtype)), ds.material())
               for q in QUADS.values()]
    camera = ds.look_at((0.0, 0.0, EYE_Z), (0.0, 0.0, 0.0), width=width, height=height,
                        projection="orthographic", ortho_height=height / 4, near=NEAR,
                        far=FAR)
    return ds.make_scene(objects=objects, camera=camera)


def ndc_depth(z):
    """The orthographic camera's NDC depth of the plane z (glOrtho)."""
    return (2.0 * (EYE_Z - z) - (FAR + NEAR)) / (FAR - NEAR)


def before(a, b):
    """The documented order of two fragments (ndc depth, object): -1 when a comes first."""
    if abs(a[0] - b[0]) <= DEPTH_TIE:
        return -1 if a[1] < b[1] else 1
    return -1 if a[0] < b[0] else 1


def reference_layers(width, height):
    """[H, W, LAYERS] object of each layer, nearest first by the documented rule (-1:
    none). A quad covers the half-open box x0 <= x < x1, y0 < y <= y1 of pixel centres
    (the top-left rule on its outline; its diagonal is shared by its own two faces)."""
    layers = np.full((height, width, LAYERS), -1)
    for row in range(height):
        for col in range(width):
            x, y = (col + 0.5 - width / 2) / 4, (height / 2 - row - 0.5) / 4
            found = [(ndc_depth(z), i) for i, (z, x0, x1, y0, y1) in enumerate(QUADS.values())
                     if x0 <= x < x1 and y0 < y <= y1]
            for a in found:  # the tie relation is transitive here: a sort is defined
                for b in found:
                    for c in found:
                        assert not (before(a, b) < 0 and before(b, c) < 0
                                    and before(c, a) < 0)
            ordered = sorted(found, key=functools.cmp_to_key(before))
            layers[row, col, :len(ordered)] = [i for _, i in ordered]
    return layers


def searched_layers(scene, kernels, k=LAYERS):
    """(face ids [H, W, k], object of each [H, W, k], -1: none) of the hard search."""
    settings = ds.RenderSettings(kernels=kernels)
    clip = ds.project(scene).clip
    ids, dropped = jax.jit(search_faces, static_argnums=(3, 5))(
        clip, scene.mesh.faces, scene.camera, k, settings, False)
    ids = np.asarray(ids)
    assert int(dropped) == 0
    objects = np.asarray(scene.objects.faces)[np.maximum(ids, 0)]
    return ids, np.where(ids >= 0, objects, -1)


def test_the_documented_tie_width_is_the_searches_and_the_references():
    """docs/rendering.md states 2^-18; tests/reference.py's naive z-buffer uses it too."""
    import reference
    assert DEPTH_TIE == reference.DEPTH_TIE == 2.0 ** -18


def test_the_reference_scene_has_ties_that_depth_alone_would_order_otherwise():
    """"film" is nearer than "label" and "table" by 2^-30 (in NDC about 2e-10, a tie), and
    is listed after them; the reference places it behind them, a sort by depth would not."""
    layers = reference_layers(16, 16).reshape(-1, LAYERS).tolist()
    label, table, film = 0, 1, 2
    runs = [p for p in layers if any(p[i:i + 3] == [label, table, film] for i in range(3))]
    assert len(runs) >= 10
    assert 0.0 < ndc_depth(0.0) - ndc_depth(2.0 ** -30) < DEPTH_TIE / 1000


@pytest.mark.parametrize("kernels", ["host", "jax"])
@pytest.mark.parametrize("size", SIZES, ids=lambda s: f"{s[0]}x{s[1]}")
def test_layers_follow_the_tie_rule_against_a_naive_loop(size, kernels, x64):
    width, height = size
    _, objects = searched_layers(stacked_quads(width, height), kernels)
    np.testing.assert_array_equal(objects, reference_layers(width, height))


@pytest.mark.parametrize("size", SIZES, ids=lambda s: f"{s[0]}x{s[1]}")
def test_float32_paths_give_the_float64_layers(size):
    """float32 vertices (the JAX search computes in float32, the host in float64): the
    same objects in the same order as the reference."""
    width, height = size
    want = reference_layers(width, height)
    for kernels in ("host", "jax"):
        _, objects = searched_layers(stacked_quads(width, height, np.float32), kernels)
        np.testing.assert_array_equal(objects, want, err_msg=kernels)


# ------------------------------------------------- a glass box resting on a table (perspective)


@pytest.fixture(scope="module")
def resting():
    """{"glass": ..., "opaque": ...}: tests/test_fit_effects' box resting on the table,
    64 x 64, float32 (the default dtype, whose rounding made the paths disagree)."""
    from test_fit_effects import box_on_table
    return {name: box_on_table(64, glass=name == "glass") for name in ("glass", "opaque")}


def contact_faces(scene):
    """[F] bool: the faces in the plane y = 0, where the box (object 0) rests on the table
    (object 1): the box's bottom and the table's top."""
    y = np.asarray(scene.mesh.vertices, np.float64)[np.asarray(scene.mesh.faces), 1]
    return np.all(np.abs(y) < 1e-6, -1)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
@pytest.mark.parametrize("size", [(64, 64), (48, 32)], ids=lambda s: f"{s[0]}x{s[1]}")
def test_host_and_jax_searches_give_the_same_layers_where_the_box_rests(size, dtype):
    """The box's bottom and the table's top lie in one plane: where both are layers of a
    pixel (dozens of pixels), and everywhere else, both searches give the same faces in
    the same order, the box's before the table's."""
    from test_fit_effects import box_on_table

    width, height = size
    with jax.enable_x64(dtype == "float64"):
        dataset = box_on_table(16, glass=True)
        for eye in ((0.4, 1.8, 2.4), (-1.6, 1.4, 1.8)):
            camera = ds.look_at(eye, (0.0, 0.2, 0.0), width=width, height=height, fov_y=50.0)
            scene = ds.replace(view_scene(dataset, 0, dataset.truth), camera=camera)
            host, objects = searched_layers(scene, "host", k=4)
            jax_ids, _ = searched_layers(scene, "jax", k=4)
            np.testing.assert_array_equal(jax_ids, host)
            contact = contact_faces(scene)[np.maximum(host, 0)] & (host >= 0)
            both = contact.sum(-1) == 2
            assert both.sum() >= 20
            tied = objects[both][contact[both]].reshape(-1, 2)
            np.testing.assert_array_equal(tied, np.tile([0, 1], (len(tied), 1)))


@pytest.mark.cost(15)
@pytest.mark.parametrize("name", ["glass", "opaque"])
def test_cached_pixels_equal_render_on_a_box_resting_on_a_table(resting, name):
    """The fitting cache rasterizes with its own programs, which round the projection
    otherwise than render's: at the truth, every kept pixel (edge_margin 0) equals render's
    to float32 rounding, the pixels whose layers hold the box's bottom on the table's top
    (dozens in each glass view) included."""
    from test_fit_effects import SETTINGS

    dataset = resting[name]
    data = build_cache(dataset, dataset.truth, edge_margin=0)
    for i, samples in enumerate(data.views):
        scene = view_scene(dataset, i, dataset.truth)
        image = np.asarray(ds.render(scene, SETTINGS))[..., :3].reshape(-1, 3)
        got = predict(dataset.truth, data.lights[i], data.global_ambient, samples,
                      data.settings)
        np.testing.assert_allclose(got, image[np.asarray(samples.pixels)], atol=1e-6,
                                   err_msg=f"view {i}")
        if name == "glass":
            faces = np.asarray(ds.rasterize_scene(scene, SETTINGS).face_ids)
            kept = faces.reshape(-1, faces.shape[-1])[np.asarray(samples.pixels)]
            on_contact = contact_faces(scene)[np.maximum(kept, 0)] & (kept >= 0)
            assert (on_contact.sum(-1) == 2).sum() >= 20


@pytest.mark.cost(20)
def test_fit_recovers_kt_of_a_glass_box_resting_on_a_table(resting):
    """kd and kt fitted from 0.5 (the table's kt from 0.05; ka, ks and shininess held at
    the truth) at 64 x 64 in float32: the known truth, to the tolerance of
    tests/test_fit_effects' transparency fit."""
    dataset = resting["glass"]
    truth = dataset.truth
    kt = jnp.asarray([[0.5] * 3, [0.05] * 3], truth.kd.dtype)
    init = dataclasses.replace(truth, kd=jnp.full_like(truth.kd, 0.5), kt=kt)
    result = fit(dataset, FitSpec.from_names(["kd", "kt"]), init, method="linear",
                 with_uncertainty=False)
    fitted = [unstack_material(result.material, i) for i in range(2)]
    np.testing.assert_allclose(fitted[0].kt, unstack_material(truth, 0).kt, atol=1e-5)
    np.testing.assert_allclose(fitted[1].kt, 0.0, atol=1e-4)
    for i in range(2):
        np.testing.assert_allclose(fitted[i].kd, unstack_material(truth, i).kd, atol=1e-5,
                                   err_msg=f"object {i}")

"""Tests for data_synth/: material ranges, the layout that separates the parameters
(checked on diffshade.render_parts images), noise and quantization statistics, and the
dataset folder round trip (including re-rendering the saved scene files)."""

import dataclasses
import json
import os
import re

import jax
import numpy as np
import pytest
import trimesh

import diffshade as ds
from data_synth import (
    COEFFICIENT_RANGES,
    SHININESS_RANGE,
    degrade,
    load_dataset,
    make_dataset,
    random_material,
    save_dataset,
)
from fitting import view_scene

SPHERE = ds.icosphere(2)
MAT = ds.material(ka=(0.3, 0.4, 0.5), kd=(0.6, 0.3, 0.4), ks=0.4, shininess=40.0)


@pytest.fixture(scope="module")
def sphere_data():
    return make_dataset(SPHERE, MAT, n_views=2, n_lights=2, size=32, seed=5)


def test_random_material_ranges():
    rng = np.random.default_rng(0)
    mats = [random_material(rng) for _ in range(400)]
    for name, (lo, hi) in COEFFICIENT_RANGES.items():
        values = np.stack([np.asarray(getattr(m, name)) for m in mats])
        assert values.shape == (400, 3) and values.min() >= lo and values.max() <= hi
        assert values.max() - values.min() > 0.9 * (hi - lo)  # the whole range is used
    log_s = np.log([float(m.shininess) for m in mats])
    lo, hi = np.log(SHININESS_RANGE)
    assert log_s.min() >= lo and log_s.max() <= hi
    # log-uniform: each half of the log range holds about half of the draws
    assert abs(np.mean(log_s < (lo + hi) / 2) - 0.5) < 0.08


def test_make_dataset_layout(sphere_data):
    assert len(sphere_data.views) == 4
    assert sphere_data.truth is MAT
    for view in sphere_data.views:
        assert view.target.shape == (32, 32, 3) and view.target.dtype == np.float32
        assert 0.0 <= view.target.min() and view.target.max() <= 1.0
        light_count = sum(len(jax.tree.leaves(g)[0]) for g in jax.tree.leaves(
            view.lights, is_leaf=lambda x: hasattr(x, "diffuse")))
        assert light_count == 1
    again = make_dataset(SPHERE, MAT, n_views=2, n_lights=2, size=32, seed=5)
    for a, b in zip(sphere_data.views, again.views, strict=True):
        np.testing.assert_array_equal(a.target, b.target)


def test_every_image_shows_shadow_and_highlight(sphere_data):
    """Each image has covered pixels unlit by its light (ka alone) and a highlight."""
    unit = ds.material(ka=1.0, kd=1.0, ks=1.0, shininess=40.0)
    for i in range(len(sphere_data.views)):
        scene = view_scene(sphere_data, i, unit)
        covered = np.asarray(ds.render(scene, sphere_data.settings))[..., 3] > 0
        parts = ds.render_parts(scene, sphere_data.settings)
        diffuse, specular = np.asarray(parts.diffuse), np.asarray(parts.specular)
        assert np.sum(covered & (diffuse.max(-1) == 0)) > 20
        assert np.sum(covered & (specular.max(-1) > 0.05)) > 3


def test_random_material_is_seeded():
    a, b, c = (make_dataset(SPHERE, None, n_views=1, n_lights=1, size=16, seed=s).truth
               for s in (1, 1, 2))
    np.testing.assert_array_equal(a.kd, b.kd)
    assert not np.array_equal(a.kd, c.kd)


def test_degrade_noise_and_quantization():
    rng = np.random.default_rng(1)
    clean = np.full((200, 200, 3), 0.5)
    noisy = degrade(clean, rng, noise_std=0.02)
    assert np.std(noisy - clean) == pytest.approx(0.02, rel=0.02)
    assert abs(np.mean(noisy - clean)) < 1e-3
    quantized = degrade(np.linspace(-0.1, 1.1, 300).reshape(1, -1, 3), rng, quantize_8bit=True)
    codes = quantized * 255.0
    np.testing.assert_allclose(codes, np.round(codes), atol=1e-4)
    assert quantized.min() == 0.0 and quantized.max() == 1.0


def test_quantized_dataset_is_the_rounded_float_one(sphere_data):
    quantized = make_dataset(SPHERE, MAT, n_views=2, n_lights=2, size=32, seed=5,
                             quantize_8bit=True)
    for a, b in zip(sphere_data.views, quantized.views, strict=True):
        np.testing.assert_allclose(b.target, np.round(a.target * 255.0) / 255.0, atol=1e-6)


def test_save_load_round_trip(sphere_data, tmp_path):
    save_dataset(sphere_data, tmp_path)
    files = sorted(os.listdir(tmp_path))
    assert not [f for f in files if f.endswith(".tmp")]
    assert {"dataset.json", "truth.json", "view_000.png", "view_003.npy",
            "view_002.json"} <= set(files)
    loaded = load_dataset(tmp_path)
    assert loaded.settings == sphere_data.settings
    np.testing.assert_array_equal(loaded.model, sphere_data.model.astype(np.float32))
    # the mesh comes from the scene files: exact vertices and faces; the normals are
    # normalized again on reading (a float32 rounding apart)
    np.testing.assert_array_equal(loaded.mesh.vertices, sphere_data.mesh.vertices)
    np.testing.assert_array_equal(loaded.mesh.faces, sphere_data.mesh.faces)
    np.testing.assert_allclose(loaded.mesh.normals, sphere_data.mesh.normals, rtol=0,
                               atol=2.5e-7)
    assert not [f for f in files if f.startswith("mesh_")]  # no separate mesh arrays
    for a, b in zip(sphere_data.views, loaded.views, strict=True):
        np.testing.assert_array_equal(a.target, b.target)
        for x, y in zip(jax.tree.leaves((a.camera, a.lights)), jax.tree.leaves((b.camera,
                                                                                b.lights)),
                        strict=True):
            np.testing.assert_array_equal(x, y)
    for name in ("ka", "kd", "ks", "shininess"):
        np.testing.assert_allclose(getattr(loaded.truth, name), getattr(MAT, name), rtol=1e-7)
    with open(tmp_path / "truth.json", encoding="utf-8") as file:
        assert json.load(file)["shininess"] == pytest.approx(40.0)


def test_targets_are_the_renders_bit_for_bit():
    """make_dataset renders each view by rasterize_scene (without its lights) and
    render_fragments: exactly diffshade.render's image, with a gain too (the unclamped
    render times the gain, then clipped), and one rasterization program for both light
    layouts (a directional and a point light)."""
    from diffshade.pipeline.rendering import _rasterize_scene

    _rasterize_scene.clear_cache()  # another test may have compiled this very program
    gains = [2.0, 0.5]
    dataset = make_dataset(SPHERE, MAT, n_views=1, n_lights=2, size=24, seed=1, gains=gains)
    assert _rasterize_scene._cache_size() == 1
    unclamped = dataclasses.replace(dataset.settings, clamp=False)
    for i, view in enumerate(dataset.views):
        image = np.asarray(ds.render(view_scene(dataset, i, MAT), unclamped))[..., :3]
        want = np.clip(image.astype(np.float64) * gains[i], 0.0, 1.0).astype(np.float32)
        np.testing.assert_array_equal(view.target, want)
    plain = make_dataset(SPHERE, MAT, n_views=1, n_lights=2, size=24, seed=1)
    for i, view in enumerate(plain.views):
        image = np.asarray(ds.render(view_scene(plain, i, MAT), plain.settings))[..., :3]
        np.testing.assert_array_equal(view.target, image)


def test_each_camera_is_rasterized_once_for_all_its_lights(monkeypatch):
    """The images of one camera (one per light) share its fragments: a dataset of 2
    cameras and 3 lights each rasterizes twice, not 6 times, and each image is still
    diffshade.render's."""
    calls = []
    rasterize = ds.rasterize_scene

    def counted(scene, settings):
        calls.append(np.asarray(scene.camera.eye))
        return rasterize(scene, settings)

    monkeypatch.setattr(ds, "rasterize_scene", counted)
    dataset = make_dataset(SPHERE, MAT, n_views=2, n_lights=3, size=16, seed=2)
    assert len(calls) == 2 and not np.allclose(calls[0], calls[1])
    for i, view in enumerate(dataset.views):
        image = np.asarray(ds.render(view_scene(dataset, i, MAT), dataset.settings))[..., :3]
        np.testing.assert_array_equal(view.target, image)


def test_saved_scene_files_render_the_targets(sphere_data, tmp_path):
    save_dataset(sphere_data, tmp_path)
    for i, view in enumerate(sphere_data.views):
        scene, settings = ds.load_scene(tmp_path / f"view_{i:03d}.json")
        image = np.asarray(ds.render(scene, settings))[..., :3]
        np.testing.assert_allclose(image, view.target, atol=1e-6)


def test_png_targets_are_read_when_there_is_no_npy(sphere_data, tmp_path):
    save_dataset(sphere_data, tmp_path)
    os.remove(tmp_path / "view_001.npy")
    loaded = load_dataset(tmp_path)
    codes = np.round(ds.linear_to_srgb(np.clip(sphere_data.views[1].target, 0, 1)) * 255.0)
    np.testing.assert_allclose(loaded.views[1].target, ds.srgb_to_linear(codes / 255.0),
                               atol=1e-6)  # the PNG is 8-bit sRGB
    np.testing.assert_array_equal(loaded.views[0].target, sphere_data.views[0].target)


def test_masks_round_trip(sphere_data, tmp_path):
    mask = np.zeros((32, 32), bool)
    mask[4:20, 8:30] = True
    views = list(sphere_data.views)
    views[2] = type(views[2])(views[2].camera, views[2].lights, views[2].target, mask)
    save_dataset(type(sphere_data)(sphere_data.mesh, views, model=sphere_data.model,
                                   global_ambient=0.4), tmp_path)
    loaded = load_dataset(tmp_path)
    np.testing.assert_array_equal(loaded.views[2].mask, mask)
    assert loaded.views[0].mask is None and loaded.truth is None


def test_mesh_file_shape(tmp_path):
    path = tmp_path / "blob.obj"
    trimesh.creation.icosphere(subdivisions=1, radius=3.0).export(path)
    dataset = make_dataset(str(path), MAT, n_views=1, n_lights=1, size=16)
    world = np.asarray(dataset.mesh.vertices) @ dataset.model[:3, :3].T + dataset.model[:3, 3]
    radii = np.linalg.norm(world, axis=1)
    assert radii.max() == pytest.approx(1.0, rel=1e-5)  # normalized to the unit sphere
    save_dataset(dataset, tmp_path / "out")
    scene, settings = ds.load_scene(tmp_path / "out" / "view_000.json")
    np.testing.assert_allclose(np.asarray(ds.render(scene, settings))[..., :3],
                               dataset.views[0].target, atol=1e-5)


@pytest.mark.parametrize("kwargs, message", [
    ({"n_views": 0}, "n_views: got 0"),
    ({"size": 2.5}, "size: got 2.5"),
    ({"noise_std": -1.0}, "noise_std: got -1.0"),
    ({"shape": "teapot"}, "shape: got 'teapot'"),
])
def test_make_dataset_rejects_bad_arguments(kwargs, message):
    with pytest.raises(ValueError, match=message):
        make_dataset(**kwargs)


@pytest.mark.parametrize("change, shown", [
    (lambda mesh: mesh["faces"][3].__setitem__(1, 500),
     "view_001.json: mesh.faces: index 500 out of range for 162 vertices"),
    (lambda mesh: mesh["faces"][0].__setitem__(0, -1), "view_001.json: mesh.faces: index -1"),
    (lambda mesh: mesh["vertices"][7].__setitem__(2, "nan"), "view_001.json: mesh.vertices[7]"),
    (lambda mesh: mesh["vertices"][7].__setitem__(2, 1e39), "mesh.vertices: row 7"),
    (lambda mesh: mesh["normals"][1].__setitem__(0, 1e39), "mesh.normals: row 1"),
])
def test_load_dataset_checks_the_scene_files_mesh(sphere_data, tmp_path, change, shown):
    """The dataset's mesh is its scene files' mesh, checked as every mesh is (a bad face
    index used to reach the rasterizer and crash it; a NaN vertex used to fit silently)."""
    save_dataset(sphere_data, tmp_path)
    scene = json.loads((tmp_path / "view_001.json").read_text())
    change(scene["mesh"])
    (tmp_path / "view_001.json").write_text(json.dumps(scene))
    with pytest.raises(ValueError, match=re.escape(shown)):
        load_dataset(tmp_path)


def test_load_dataset_refuses_views_of_different_meshes(sphere_data, tmp_path):
    """One dataset, one mesh: a scene file that shows another one is named."""
    save_dataset(sphere_data, tmp_path)
    scene = json.loads((tmp_path / "view_002.json").read_text())
    scene["mesh"]["vertices"][5][0] += 0.25
    (tmp_path / "view_002.json").write_text(json.dumps(scene))
    with pytest.raises(ValueError, match=re.escape("views[2] (view_002.json): its mesh "
                                                   "differs from views[0]'s")):
        load_dataset(tmp_path)

"""Property tests (hypothesis): malformed dataset folders and scene files load cleanly or
are refused cleanly (the style of test_malformed_meshes.py).

A valid dataset.json and a valid scene file (two cameras, lights, transform, settings) are
mutated at random: values replaced by any JSON value, huge or non-finite numbers, other
file names (missing, a folder, undecodable, NaN, negative or wrongly sized targets), keys
dropped or added; the JSON text is also cut short or nested beyond the parser's depth.
Each either loads into something a fit can use (finite, non-negative targets of their
camera's size, a mesh whose faces index its vertices, image sizes within the cap) or raises
ValueError or OSError: never another exception type (IndexError, KeyError, TypeError,
RecursionError...), which `diffshade fit` would print as a traceback. Nothing is rendered.
"""

import copy
import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import diffshade as ds
from diffshade.scene.camera import MAX_IMAGE_SIZE
from fitting import load_dataset

PROPERTY_SETTINGS = settings(max_examples=60, deadline=None, derandomize=True, database=None,
                             suppress_health_check=[HealthCheck.too_slow,
                                                    HealthCheck.function_scoped_fixture])
CLEAN_ERRORS = (ValueError, OSError)
PYRAMID = {"vertices": [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1]],
           "faces": [[0, 2, 1], [0, 3, 2], [0, 1, 4], [1, 2, 4], [2, 3, 4], [3, 0, 4]]}
CAMERA = {"eye": [0.5, 0.5, 3], "target": [0.5, 0.5, 0], "width": 8, "height": 6}
SCENE = {"version": 1, "mesh": PYRAMID, "transform": {"translate": [0, 0.1, 0]},
         "cameras": [CAMERA, {**CAMERA, "eye": [2, 1, 2]}],
         "lights": [{"type": "directional", "direction": [0, -1, -1], "color": 0.8},
                    {"type": "point", "position": [1, 2, 2], "color": [0.5, 0.4, 0.3]}],
         "material": {"ka": 0.2, "kd": 0.5, "ks": 0.3, "shininess": 10},
         "global_ambient": 0.3, "settings": {"shading": "phong"}}
DATASET = {"format": "diffshade-dataset", "version": 1, "color_space": "srgb",
           "saturation": 0.99,
           "views": [{"scene": "scene.json", "camera": 0, "image": "rgb.png"},
                     {"scene": "scene.json", "camera": 1, "image": "rgba.png",
                      "mask": "mask.png"},
                     {"scene": "one.json", "image": "missing.png", "target": "t.npy",
                      "color_space": "linear"}],
           "info": {"made": "by hand"}}
FILES = ["scene.json", "one.json", "rgb.png", "rgba.png", "mask.png", "t.npy", "nan.npy",
         "negative.npy", "wide.npy", "grey.npy", "garbage.png", "missing.png", "sub", "",
         "../scene.json", "deep.json"]


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    root = tmp_path_factory.mktemp("dataset")
    (root / "scene.json").write_text(json.dumps(SCENE))
    (root / "one.json").write_text(json.dumps({**{k: v for k, v in SCENE.items()
                                                  if k != "cameras"}, "camera": CAMERA}))
    (root / "deep.json").write_text("[" * 50_000 + "]" * 50_000)
    rng = np.random.default_rng(0)
    image = rng.uniform(0, 1, (6, 8, 3))
    ds.write_png(root / "rgb.png", image)
    ds.write_png(root / "rgba.png", np.concatenate([image, rng.uniform(0, 1, (6, 8, 1))], -1))
    ds.write_png(root / "mask.png", rng.uniform(0, 1, (6, 8, 1)), color_space="linear")
    np.save(root / "t.npy", image.astype(np.float32))
    np.save(root / "nan.npy", np.where(image > 0.9, np.nan, image))
    np.save(root / "negative.npy", image - 0.5)
    np.save(root / "wide.npy", rng.uniform(0, 1, (6, 9, 3)))
    np.save(root / "grey.npy", image[..., 0])
    (root / "garbage.png").write_bytes(b"\x89PNG\r\n\x1a\n not really")
    (root / "sub").mkdir()
    return root


json_scalar = st.one_of(st.none(), st.booleans(), st.integers(-3, 10),
                        st.sampled_from([10**30, 2**31, MAX_IMAGE_SIZE + 1, -(10**30)]),
                        st.floats(allow_nan=True, allow_infinity=True),
                        st.sampled_from(["", "x", "srgb", "linear", "phong", "point"]))
json_value = st.recursive(json_scalar, lambda inner: st.one_of(
    st.lists(inner, max_size=4), st.dictionaries(st.sampled_from(["a", "type", "width"]),
                                                 inner, max_size=2)), max_leaves=8)
replacement = st.one_of(json_value, st.sampled_from(FILES))


@st.composite
def mutated(draw, value, faults=3):
    """value (a JSON tree) with up to `faults` faults: a node replaced, a key dropped or
    added, a list item dropped or duplicated."""
    value = copy.deepcopy(value)
    for _ in range(draw(st.integers(1, faults))):
        path, node = [], value
        while isinstance(node, (dict, list)) and node and draw(st.integers(0, 2)):
            key = draw(st.sampled_from(sorted(node) if isinstance(node, dict)
                                       else list(range(len(node)))))
            path.append(node)
            node = node[key]
            path.append(key)
        if not path:
            continue
        parent, key = path[-2], path[-1]
        fault = draw(st.sampled_from(["replace", "replace", "drop", "add", "copy"]))
        if fault == "replace":
            parent[key] = draw(replacement)
        elif fault == "drop":
            del parent[key]
        elif fault == "add" and isinstance(parent, dict):
            parent[draw(st.sampled_from(["colour", "cameras", "camera", "mask", "x"]))] = \
                draw(replacement)
        elif isinstance(parent, list):
            parent.append(copy.deepcopy(parent[key]))
    return value


@st.composite
def json_text(draw, value):
    """The JSON text of a mutated value, sometimes cut short."""
    text = json.dumps(draw(mutated(value)))
    return text[: draw(st.integers(0, len(text)))] if draw(st.integers(0, 5)) == 0 else text


def assert_usable(dataset):
    """What a fit may rely on: targets finite, >= 0 and of their camera's size; a mesh
    whose faces index its vertices; image sizes within the cap."""
    vertices, faces = np.asarray(dataset.mesh.vertices), np.asarray(dataset.mesh.faces)
    assert np.all(np.isfinite(vertices)) and faces.min() >= 0 and faces.max() < len(vertices)
    for view in dataset.views:
        height, width = view.camera.height, view.camera.width
        assert 0 < width <= MAX_IMAGE_SIZE and 0 < height <= MAX_IMAGE_SIZE
        assert view.target.shape == (height, width, 3)
        assert np.all(np.isfinite(view.target)) and view.target.min() >= 0
        assert view.mask is None or view.mask.shape == (height, width)


@PROPERTY_SETTINGS
@given(data=st.data())
def test_malformed_dataset_json_loads_or_raises_a_clean_error(folder, data):
    (folder / "dataset.json").write_text(data.draw(json_text(DATASET)))
    try:
        dataset = load_dataset(folder)
    except CLEAN_ERRORS:
        return
    assert_usable(dataset)


@PROPERTY_SETTINGS
@given(data=st.data())
def test_malformed_scene_file_loads_or_raises_a_clean_error(folder, data):
    (folder / "drawn.json").write_text(data.draw(json_text(SCENE)))
    try:
        scenes, _ = ds.load_scenes(folder / "drawn.json")
    except CLEAN_ERRORS:
        return
    assert len(scenes) >= 1
    for scene in scenes:
        assert 0 < scene.camera.width <= MAX_IMAGE_SIZE
        assert 0 < scene.camera.height <= MAX_IMAGE_SIZE
        assert np.all(np.isfinite(np.asarray(scene.mesh.vertices)))


def test_the_unmutated_files_load(folder):
    """The property tests start from files that are valid (else they test nothing)."""
    (folder / "dataset.json").write_text(json.dumps(DATASET))
    dataset = load_dataset(folder)
    assert_usable(dataset)
    assert len(dataset.views) == 3 and dataset.views[1].mask is not None
    scenes, _ = ds.load_scenes(folder / "scene.json")
    assert [s.camera.width for s in scenes] == [8, 8]


# ---- a view's target and mask, and why no pixel of it counts (issue 26)


def one_view(root, image, meta=None, **entry):
    """A dataset folder of one view of an 8 x 6 camera whose target file is `image`."""
    (root / "one.json").write_text(json.dumps({**{k: v for k, v in SCENE.items()
                                                  if k != "cameras"}, "camera": CAMERA}))
    view = {"scene": "one.json", "image": image, **entry}
    (root / "dataset.json").write_text(json.dumps({"format": "diffshade-dataset",
                                                   "version": 1, "views": [view],
                                                   **(meta or {})}))
    return root


def rgb_codes():
    rng = np.random.default_rng(1)
    return rng.integers(20, 230, (6, 8, 3), dtype=np.uint8)


def save(path, codes):
    from PIL import Image
    Image.fromarray(codes).save(path)


@pytest.mark.parametrize("case, shown", [
    ("black_mask", "no pixel counts: the mask 'mask.png' is black everywhere"),
    ("alpha_zero", "no pixel counts: the target's alpha is at most 0.5 everywhere"),
    ("saturation", "no pixel counts: every pixel reaches the saturation threshold 1e-09"),
])
def test_a_view_where_no_pixel_counts_says_which_filter_left_none(tmp_path, case, shown):
    codes, meta, entry = rgb_codes(), None, {}
    if case == "alpha_zero":
        codes = np.concatenate([codes, np.zeros((6, 8, 1), np.uint8)], -1)
    if case == "black_mask":
        save(tmp_path / "mask.png", np.zeros((6, 8), np.uint8))
        entry = {"mask": "mask.png"}
    if case == "saturation":
        meta = {"saturation": 1e-9}
    save(tmp_path / "target.png", codes)
    with pytest.raises(ValueError) as info:
        load_dataset(one_view(tmp_path, "target.png", meta, **entry))
    assert str(info.value).startswith(f"views[0]: {shown}"), info.value
    assert "expected" in str(info.value)


def test_a_cmyk_jpeg_target_is_fitted_as_its_rgb(tmp_path):
    from PIL import Image
    codes = np.full((6, 8, 3), (200, 100, 30), np.uint8)
    Image.fromarray(codes).convert("CMYK").save(tmp_path / "target.jpg", quality=100)
    dataset = load_dataset(one_view(tmp_path, "target.jpg"))
    expected = ds.io.srgb_to_linear(np.array([200, 100, 30]) / 255.0)
    np.testing.assert_allclose(dataset.views[0].target, np.broadcast_to(expected, (6, 8, 3)),
                               atol=0.01)
    assert dataset.views[0].mask is None


def test_a_grey_target_is_repeated_into_rgb(tmp_path):
    grey = rgb_codes()[..., 0]
    save(tmp_path / "grey.png", grey)
    target = load_dataset(one_view(tmp_path, "grey.png")).views[0].target
    np.testing.assert_allclose(target, np.repeat(ds.io.srgb_to_linear(grey / 255.0)[..., None],
                                                 3, -1), atol=1e-6)


def test_colour_space_keys_are_read_in_any_case(tmp_path):
    save(tmp_path / "target.png", rgb_codes())
    dataset = load_dataset(one_view(tmp_path, "target.png", {"color_space": "Linear"},
                                    color_space="LINEAR"))
    np.testing.assert_allclose(dataset.views[0].target, rgb_codes() / 255.0, atol=1e-6)


def test_a_target_of_another_size_is_refused_from_its_header(tmp_path):
    """A 12000 x 12000 PNG for an 8 x 6 camera: its pixel data is garbage, so only a size
    read from the header, before decoding, gives this message."""
    import struct
    import zlib

    def chunk(kind, payload):
        return (struct.pack(">I", len(payload)) + kind + payload
                + struct.pack(">I", zlib.crc32(kind + payload)))
    ihdr = struct.pack(">IIBBBBB", 12000, 12000, 8, 2, 0, 0, 0)
    (tmp_path / "huge.png").write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
                                        + chunk(b"IDAT", b"garbage") + chunk(b"IEND", b""))
    with pytest.raises(ValueError, match=r"^views\[0\]: 'huge.png': got an image of "
                       r"12000x12000 pixels; expected 8x6, the size of its camera$"):
        load_dataset(one_view(tmp_path, "huge.png"))


def test_a_mislabelled_target_says_what_it_holds(tmp_path):
    save(tmp_path / "target.png", rgb_codes())
    (tmp_path / "target.png").rename(tmp_path / "target.npy")
    with pytest.raises(ValueError, match=r"target.npy' holds a PNG image; expected a NumPy "
                       r"array \(.npy\), as its extension '.npy' says"):
        load_dataset(one_view(tmp_path, "missing.png", target="target.npy"))

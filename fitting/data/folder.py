"""Dataset folders, the one home of the format: `save_dataset` writes one (data_synth,
`diffshade synth`), `load_dataset` reads and checks one (`diffshade fit`).

A dataset is a folder of target images and diffshade scene files (docs/scene-format.md):

    dataset.json   {"format": "diffshade-dataset", "version": 1, "views": [...]}, and
                   optionally "color_space", "saturation" and "info" (free-form)
    *.json         scene files: the mesh (a mesh file through trimesh, a built-in shape or
                   inline arrays), model transform, camera(s), lights, global ambient and
                   render settings. One file per view, or one file whose "cameras" list
                   serves several views
    images         the targets: PNG or JPEG (decoded to linear), or .npy (linear floats)
    masks          optional, per view: white where the pixel counts
    truth.json     optional: the true material; of several objects, {"objects": {name:
                   material}} or {"objects": [one material per object]} (or one
                   material, which every object has); a textured kd (ks, shininess) is
                   {"texture": FILE} (docs/textures.md), FILE beside it (synth writes
                   truth.kd.npy, linear, and truth.kd.png to look at)

A view entry is {"scene": file, "image": file} with optional "camera" (index into the
scene file's cameras, default 0), "target" (a .npy read instead of "image" when it
exists), "mask" (file) and "color_space". Every view must show the same mesh (or the
same "objects", in the same order), model, global ambient, lighting switches and
settings (the Dataset has one of each); each view has its own camera and lights. A
dataset of several objects (scene files with "objects") has one material per object.

Which pixels count: inside the view's mask file, where an RGBA target's alpha is above
0.5, and not saturated: a pixel is left out when any channel of its decoded target
reaches the saturation threshold (linear). The threshold is load_dataset's `saturation`,
else dataset.json's "saturation" (a number, or null for none), else 1.0 (the top code, 255
of an 8-bit file) for image targets and none for .npy targets.

A camera with lens distortion ("dist", docs/calibrated-cameras.md) has its target and
mask resampled on load into its pinhole image (the one diffshade renders, same K); only
pixels whose resampled value comes wholly from counted photo pixels count.

Image targets are decoded with, first found: load_dataset's `color_space`, the view's
"color_space", dataset.json's "color_space", what the file declares, sRGB
(diffshade.read_image). Masks are read as data. Every problem is a ValueError (or an
OSError for a missing file) naming the file or key, the value and what was expected.
"""

import dataclasses
import hashlib
import math
import os

import numpy as np

import diffshade as ds
from diffshade.io import (
    check_color_space,
    image_header,
    pinhole,
    read_json,
    save_textures,
    scene_to_dict,
    texture,
    undistort_image,
    undistort_mask,
    write_json,
)
from diffshade.scene import stack_materials, unstack_material
from fitting.data.rounding import resampled_rounding
from fitting.data.views import Dataset, View, material_for, view_scene
from fitting.spec.params import DEFAULT_INIT, object_count

FORMAT = "diffshade-dataset"
VERSION = 1
TOP_KEYS = ("format", "version", "views", "info", "color_space", "saturation")
VIEW_KEYS = ("scene", "camera", "image", "target", "mask", "color_space")
IMAGE_SATURATION = 1.0
_SHARED = ("model", "global_ambient", "local_viewer", "two_sided")


# ---- materials ----

MATERIAL_KEYS = ("ka", "kd", "ks", "shininess", "emission", "kt")


def _check_material_value(key, value, where):
    """JSON material values: numbers ([r, g, b] for a coefficient; null for ks and
    emission and kt, which may be absent; {"texture": FILE} for kd, ks, shininess).
    material() checks the ranges and lengths."""
    if value is None and key in ("ks", "emission", "kt"):
        return
    if isinstance(value, dict) and key in _TEXTURED:
        if set(value) != {"texture"} or not isinstance(value["texture"], str):
            _fail(where, value, '{"texture": FILE}')
        return
    items = value if isinstance(value, list) and key != "shininess" else [value]
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in items):
        _fail(where, value, "a number" if key == "shininess" else "a number or [r, g, b]")


_TEXTURED = ("kd", "ks", "shininess")


def _textures(data, where, base_dir):
    """data with each {"texture": FILE} read (FILE relative to base_dir)."""
    out = dict(data)
    for key in _TEXTURED:
        if isinstance(data.get(key), dict):
            if base_dir is None:
                _fail(f"{where}: {key}", data[key], "numbers here (a texture only in a "
                      "dataset's truth.json)")
            out[key] = texture(os.path.join(base_dir, data[key]["texture"]))
    return out


def _one_material_from_dict(data, where, base_dir=None):
    if not isinstance(data, dict) or set(data) - set(MATERIAL_KEYS):
        extra = sorted(set(data) - set(MATERIAL_KEYS)) if isinstance(data, dict) else \
            type(data).__name__
        raise ValueError(f"{where} has {extra}; expected an object with keys among "
                         f"{MATERIAL_KEYS}")
    for key, value in data.items():
        _check_material_value(key, value, f"{where}: {key}")
    try:
        return ds.material(**_textures(data, where, base_dir))
    except ValueError as err:
        raise ValueError(f"{where}: {err}") from err


def material_from_dict(data, where, base_dir=None):
    """Material from a parsed JSON object with keys among MATERIAL_KEYS (truth.json, an
    --init file); for several objects (diffshade.scene.objects) {"objects": [one such object
    per object]} gives a stacked Material and {"objects": {name: one such object}} a dict
    {name: Material} (fitting.data.views.material_for puts it in the objects' order).
    ValueError naming `where` and the key otherwise. base_dir: the folder textures
    ({"texture": FILE}) are read from; None: no textures."""
    if not (isinstance(data, dict) and "objects" in data):
        return _one_material_from_dict(data, where, base_dir)
    entries = data["objects"]
    if set(data) != {"objects"}:
        raise ValueError(f"{where} has {sorted(set(data) - {'objects'})} beside "
                         "\"objects\"; expected only \"objects\" (one material per "
                         "object) or the keys of one material")
    if not isinstance(entries, (list, dict)) or not entries:
        _fail(f"{where}: objects", entries, "a non-empty list of materials, one per object, "
              "or an object {name: material}")
    if isinstance(entries, dict):
        return {name: _one_material_from_dict(e, f"{where}: objects.{name}")
                for name, e in entries.items()}
    return stack_materials([_one_material_from_dict(e, f"{where}: objects[{i}]")
                            for i, e in enumerate(entries)])


# ---- writing ----


def material_dict(mat, names=None, texture_refs=None) -> dict:
    """{'ka', 'kd', 'ks', 'shininess', 'emission', 'kt'} as JSON-ready lists (None when
    absent); of a stacked Material (several objects), {'objects': [one such dict per
    object]}, or {'objects': {name: one such dict}} given the objects' `names`
    (material_from_dict reads them all). texture_refs: {field: FILE} of a textured
    material's textures, written as {"texture": FILE}."""
    count = object_count(mat)
    if count is not None:
        dicts = [material_dict(unstack_material(mat, i)) for i in range(count)]
        return {"objects": dicts if names is None else dict(zip(names, dicts, strict=True))}

    refs = texture_refs or {}

    def rgb(value, key=None, write=lambda v: np.asarray(v, np.float64).tolist()):
        if key in refs:
            return {"texture": refs[key]}
        return None if value is None else write(value)
    return {"ka": rgb(mat.ka), "kd": rgb(mat.kd, "kd"), "ks": rgb(mat.ks, "ks"),
            "shininess": rgb(mat.shininess, "shininess", float),
            "emission": rgb(mat.emission), "kt": rgb(mat.kt)}


def _write_view(out_dir, dataset, i, texture_refs=None):
    """view_NNN.json (mesh inline, or the built-in shape's reference), .png, .npy, mask."""
    view, name = dataset.views[i], f"view_{i:03d}"
    scene = view_scene(dataset, i, material_for(dataset, dataset.truth or DEFAULT_INIT))
    write_json(os.path.join(out_dir, f"{name}.json"),
               scene_to_dict(scene, dataset.settings, dataset.info.get("mesh_ref"),
                             texture_refs))
    ds.write_png(os.path.join(out_dir, f"{name}.png"), view.target)
    ds.write_npy(os.path.join(out_dir, f"{name}.npy"), view.target.astype(np.float32))
    entry = {"scene": f"{name}.json", "image": f"{name}.png", "target": f"{name}.npy",
             "mask": None}
    if view.mask is not None:
        entry["mask"] = f"{name}_mask.png"
        ds.write_png(os.path.join(out_dir, entry["mask"]), view.mask.astype(np.float64),
                     color_space="linear")
    return entry


def _write_truth_textures(out_dir, truth):
    """{field: FILE} of the truth's textures, written as truth.FIELD.npy (linear, what
    the scene files and truth.json refer to) and truth.FIELD.png (sRGB, to look at)."""
    if truth is None or object_count(truth) is not None:
        return {}
    refs = save_textures(os.path.join(out_dir, "truth.json"), truth, "truth")
    for key in refs:
        texels = np.asarray(getattr(truth, key).texels)
        ds.write_png(os.path.join(out_dir, f"truth.{key}.png"),
                     texels if key != "shininess" else texels / max(texels.max(), 1e-12))
    return refs


def _names(dataset):
    """The names of a dataset's named objects, else None."""
    return None if dataset.objects is None else dataset.objects.names


def save_dataset(dataset: Dataset, out_dir) -> str:
    """Write `dataset` to the folder out_dir (created if missing), every file atomically;
    returns its path. The float targets (.npy) are what load_dataset reads back."""
    out_dir = os.fspath(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    refs = _write_truth_textures(out_dir, dataset.truth)
    entries = [_write_view(out_dir, dataset, i, refs) for i in range(len(dataset.views))]
    if dataset.truth is not None:
        write_json(os.path.join(out_dir, "truth.json"),
                   material_dict(dataset.truth, _names(dataset), refs))
    write_json(os.path.join(out_dir, "dataset.json"),
               {"format": FORMAT, "version": VERSION, "views": entries, "info": dataset.info})
    return out_dir


# ---- checking dataset.json ----


def _fail(where, value, expected):
    shown = repr(value)
    raise ValueError(f"{where}: got {shown if len(shown) <= 60 else shown[:57] + '...'}; "
                     f"expected {expected}")


def _color_space(value, where):
    """None, or the colour space's name in lower case ('sRGB' is 'srgb')."""
    return None if value is None else check_color_space(value, where)


def _saturation(value, where):
    """None (off), or a positive number (math.inf: off)."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0:
        _fail(where, value, "a positive number (linear), or null for no saturation")
    return float(value)


def _check_keys(obj, known, where):
    """A misspelt key is an error, never silently ignored."""
    unknown = sorted(set(obj) - set(known))
    if unknown:
        raise ValueError(f"{where}: {unknown[0]!r}: unknown key; expected one of "
                         f"{', '.join(known)}")


def _file_name(entry, key, where, required=False):
    value = entry.get(key)
    if value is None and not required:
        return None
    if not isinstance(value, str) or not value:
        _fail(f"{where}.{key}", value, "a file name" + ("" if required else " or null"))
    return value


def _check_entry(entry, where):
    if not isinstance(entry, dict):
        _fail(where, entry, "an object with 'scene' and 'image' file names")
    _check_keys(entry, VIEW_KEYS, where)
    for key in ("scene", "image"):
        _file_name(entry, key, where, required=True)
    for key in ("target", "mask"):
        _file_name(entry, key, where)
    camera = entry.get("camera", 0)
    if isinstance(camera, bool) or not isinstance(camera, int) or camera < 0:
        _fail(f"{where}.camera", camera, "an index >= 0 into the scene file's cameras")
    _color_space(entry.get("color_space"), f"{where}.color_space")


def read_meta(path) -> dict:
    """dataset.json of the folder `path`, checked: format, version, keys, view entries."""
    meta_path = os.path.join(path, "dataset.json")
    if not os.path.isfile(meta_path):
        raise FileNotFoundError(f"DATASET: {path!r} has no dataset.json; expected a dataset "
                                "folder (docs/cli.md)")
    meta = read_json(meta_path, "dataset.json")
    if not isinstance(meta, dict):
        _fail(meta_path, meta, "a JSON object")
    if meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise ValueError(f"{meta_path}: format {meta.get('format')!r} version "
                         f"{meta.get('version')!r}; expected {FORMAT!r} version {VERSION}")
    _check_keys(meta, TOP_KEYS, meta_path)
    views = meta.get("views")
    if not isinstance(views, list) or not views:
        _fail(f"{meta_path}: views", views, "a non-empty list of view objects")
    for i, entry in enumerate(views):
        _check_entry(entry, f"{meta_path}: views[{i}]")
    _color_space(meta.get("color_space"), f"{meta_path}: color_space")
    _saturation(meta.get("saturation"), f"{meta_path}: saturation")
    if not isinstance(meta.get("info", {}), dict):
        _fail(f"{meta_path}: info", meta["info"], "an object")
    return meta


# ---- reading ----


def _pixel_problem(target, name, index):
    """ValueError naming the first non-finite or negative value of a target, or None."""
    bad = np.argwhere(~np.isfinite(target) | (target < 0))
    if not bad.size:
        return None
    value = target[tuple(bad[0])]
    kind = "NaN" if np.isnan(value) else "infinity" if np.isinf(value) else f"{value:.4g}"
    row, column = (int(i) for i in bad[0][:2])
    return ValueError(f"target image of view {index} ({name}) contains {kind} at pixel "
                      f"(row {row}, column {column}) ({len(bad)} bad values); expected "
                      "finite colours >= 0")


def _check_size(file, label, size, what):
    """The image file's header must give `size` (height, width): checked before decoding.
    label: how the message names the file."""
    found = image_header(file)
    if found.kind != "EXR" and (found.height, found.width) != size:
        raise ValueError(f"{label}: got an image of {found.width}x{found.height} pixels; "
                         f"expected {size[1]}x{size[0]}, the size of its {what}")


def _colour_image(image, name):
    """[H, W, 3 or 4]: a grey image (with alpha) repeated into RGB (RGBA)."""
    if image.ndim == 3 and image.shape[-1] in (1, 2):
        grey = np.repeat(image[..., :1], 3, axis=-1)
        return np.concatenate([grey, image[..., 1:]], axis=-1)
    if image.ndim != 3 or image.shape[-1] not in (3, 4):
        raise ValueError(f"{name!r} has shape {image.shape}; expected an "
                         "RGB or RGBA image [H, W, 3 or 4] (or grey, with or without alpha)")
    return image


def _read_target(path, entry, index, color_space, size):
    """(linear [H, W, 3] float32, alpha [H, W] or None, is_image); size: the camera's
    (height, width), which the file's header must give before it is decoded."""
    npy = entry.get("target")
    if npy and os.path.isfile(os.path.join(path, npy)):
        name, is_image, space = npy, False, None
    else:
        name, is_image, space = entry["image"], True, color_space
    file = os.path.join(path, name)
    if os.path.isfile(file):
        _check_size(file, repr(name), size, "camera")
    image = _colour_image(ds.read_image(file, space), name)
    problem = _pixel_problem(image[..., :3], name, index)
    if problem:
        raise problem
    alpha = image[..., 3] if image.shape[-1] == 4 else None
    return image[..., :3], alpha, is_image


def saturation_mask(target, threshold):
    """[H, W] bool: True where every channel of target [H, W, 3] is below threshold."""
    if threshold is None or math.isinf(threshold):
        return np.ones(target.shape[:2], bool)
    return np.all(np.asarray(target) < threshold, axis=-1)


def _file_mask(path, name, size):
    """[H, W] bool of the mask file: white (> 0.5 in its first channel) counts."""
    file = os.path.join(path, name)
    if os.path.isfile(file):
        _check_size(file, f"mask {name!r}", size, "target")
    file_mask = ds.read_image(file, color_space="linear")
    return file_mask.reshape(*file_mask.shape[:2], -1)[..., 0] > 0.5


def _view_mask(path, entry, target, alpha, threshold):
    """The pixels that count: mask file, alpha > 0.5 and unsaturated (None: all). A view
    where none counts is refused, naming the filter that left none."""
    filters = [(saturation_mask(target, threshold),
                f"every pixel reaches the saturation threshold {threshold} in some channel "
                "(expected a threshold above the colours that are not clipped)")]
    if alpha is not None:
        filters.append((alpha > 0.5, "the target's alpha is at most 0.5 everywhere "
                        "(expected alpha above 0.5 where the pixel counts)"))
    if entry.get("mask"):
        filters.append((_file_mask(path, entry["mask"], target.shape[:2]),
                        f"the mask {entry['mask']!r} is black everywhere (expected white "
                        "where the pixel counts)"))
    mask = np.ones(target.shape[:2], bool)
    for kept, why in filters:
        if not kept.any():
            raise ValueError(f"no pixel counts: {why}")
        mask &= kept
    if not mask.any():
        raise ValueError("no pixel counts: the mask file, the alpha channel and the "
                         "saturation threshold leave none together (expected some pixel "
                         "that all of them keep)")
    return None if mask.all() else mask


def _scenes(path, name, cache):
    """The scenes and settings of scene file `name` (each file parsed once)."""
    if name not in cache:
        cache[name] = ds.load_scenes(os.path.join(path, name))
    return cache[name]


def _same_objects(ids, ids0):
    """Whether two scenes split their (equal) meshes into the same objects."""
    if ids is None or ids0 is None:
        return ids is ids0
    arrays = zip((ids.faces, ids.vertices), (ids0.faces, ids0.vertices), strict=True)
    return ids.names == ids0.names and all(np.array_equal(a, b) for a, b in arrays)


def _check_same(first, scene, settings, where):
    """Every view must share view 0's mesh, model, ambient, switches and settings."""
    scene0, settings0 = first
    if scene.mesh is not scene0.mesh and not all(
            np.shape(a) == np.shape(b) and np.array_equal(a, b)
            for a, b in zip((scene.mesh.vertices, scene.mesh.faces),
                            (scene0.mesh.vertices, scene0.mesh.faces), strict=True)):
        raise ValueError(f"{where}: its mesh differs from views[0]'s; expected one mesh for "
                         "the whole dataset")
    if not _same_objects(scene.objects, scene0.objects):
        raise ValueError(f"{where}: its objects differ from views[0]'s; expected the same "
                         "objects, in the same order, in every view")
    for key in _SHARED:
        if not np.array_equal(getattr(scene, key), getattr(scene0, key)):
            raise ValueError(f"{where}: its {key} differs from views[0]'s; expected one "
                             f"{key} for the whole dataset")
    if settings != settings0:
        raise ValueError(f"{where}: its settings differ from views[0]'s; expected one "
                         "RenderSettings for the whole dataset")


def _load_view(path, entry, index, options, cache):
    color_space, shared_space, saturation = options
    scenes, settings = _scenes(path, entry["scene"], cache)
    camera = entry.get("camera", 0)
    if camera >= len(scenes):
        _fail("camera", camera,
              f"an index below {len(scenes)}, the cameras of {entry['scene']!r}")
    space = color_space or entry.get("color_space") or shared_space
    scene = scenes[camera]
    size = (scene.camera.height, scene.camera.width)
    target, alpha, is_image = _read_target(path, entry, index, space, size)
    threshold = saturation if saturation is not None else (
        IMAGE_SATURATION if is_image else None)
    mask = _view_mask(path, entry, target, alpha, threshold)
    return scene, settings, View(**_pinhole_view(scene.camera, target, mask),
                                 lights=scene.lights)


def _pinhole_view(camera, target, mask):
    """{camera, target, mask, rounding} of a distorted camera's photo resampled into its
    pinhole image (the one diffshade renders), the photo's 8-bit rounding carried through
    (fitting.data.rounding.resampled_rounding); others as given. A target of the wrong size
    is left for Dataset to name."""
    if not np.any(np.asarray(camera.dist)) or target.shape[:2] != (camera.height,
                                                                   camera.width):
        return {"camera": camera, "target": target, "mask": mask}
    mask = undistort_mask(mask, camera)
    return {"camera": pinhole(camera), "target": undistort_image(target, camera),
            "mask": None if mask.all() else mask,
            "rounding": resampled_rounding(target, camera)}


def load_dataset(path, color_space=None, saturation=None) -> Dataset:
    """The Dataset in the folder `path` (module docstring). color_space: 'srgb' or
    'linear' overrides the encoding of every image target; saturation: a linear threshold
    (math.inf: none) overriding dataset.json's and the default."""
    path = os.fspath(path)
    _color_space(color_space, "color_space")
    meta = read_meta(path)
    saturation = _saturation(saturation, "saturation")
    if saturation is None and "saturation" in meta:
        saturation = math.inf if meta["saturation"] is None else float(meta["saturation"])
    options = (color_space, meta.get("color_space"), saturation)
    cache, loaded = {}, []
    for i, entry in enumerate(meta["views"]):
        try:
            loaded.append(_load_view(path, entry, i, options, cache))
        except ValueError as err:
            raise type(err)(f"views[{i}]: {err}") from err
        if i:
            _check_same(loaded[0][:2], *loaded[i][:2], f"views[{i}] ({entry['scene']})")
    scene, settings, _ = loaded[0]
    dataset = Dataset(scene.mesh, [view for _, _, view in loaded],
                      model=np.asarray(scene.model),
                      global_ambient=np.asarray(scene.global_ambient), settings=settings,
                      local_viewer=scene.local_viewer, two_sided=scene.two_sided,
                      info=meta.get("info", {}), objects=scene.objects)
    truth_path = os.path.join(path, "truth.json")
    if not os.path.isfile(truth_path):
        return dataset
    truth = material_from_dict(read_json(truth_path, "truth.json"), truth_path, path)
    return dataclasses.replace(dataset, truth=material_for(dataset, truth, truth_path))


def fingerprint(dataset: Dataset) -> str:
    """sha256 of the targets and masks (shapes and bytes): what a fit sees."""
    digest = hashlib.sha256()
    for view in dataset.views:
        target = np.ascontiguousarray(view.target, np.float32)
        digest.update(repr(target.shape).encode())
        digest.update(target.tobytes())
        if view.mask is not None:
            digest.update(np.packbits(view.mask).tobytes())
    return digest.hexdigest()

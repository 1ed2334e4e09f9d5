"""Dataset folders: `save_dataset(dataset, out_dir)` and `load_dataset(out_dir)`.

Layout (every file written atomically through diffshade.io: a temporary file, then
os.replace):

    dataset.json       format, version, the view list, info (how the data were made);
                       optionally "color_space" (below), here or per view
    mesh_vertices.npy, mesh_faces.npy, mesh_normals.npy
                       the exact mesh arrays the targets were rendered with
    view_000.json      the view as a diffshade scene file (scene_to_dict): mesh (built-in
                       reference, or inline with its normals), model, camera, lights,
                       material (the truth when known), global ambient, settings;
                       `diffshade render` renders it
    view_000.png       the target, 8-bit sRGB-encoded and tagged so (docs/color.md)
    view_000.npy       the target, float32 [H, W, 3] (what a fit reads when present)
    view_000_mask.png  the mask, when the view has one (white = counts)
    truth.json         the true material, when the dataset knows it

`load_dataset` reads the cameras, lights, model, global ambient and settings from the
scene files, the mesh from mesh_*.npy, each target from its .npy or else its image (so
that targets rendered elsewhere can be dropped in as PNG or JPEG), and truth.json when
present. A .npy target is linear. An image target is decoded to linear with, first
found: load_dataset's `color_space` argument (`diffshade fit --color-space`), the view's
"color_space" key, dataset.json's "color_space" key, what the file declares, sRGB
(diffshade.read_image). Masks are read as data (no decoding).
"""

import json
import os

import numpy as np

import diffshade as ds
from diffshade.color import COLOR_SPACES
from diffshade.io import write_json
from diffshade.mesh import check_mesh
from diffshade.scenefile import scene_to_dict
from fitting.data import Dataset, View, view_scene
from fitting.params import DEFAULT_INIT

FORMAT = "diffshade-dataset"
MESH_ARRAYS = ("vertices", "faces", "normals")
VERSION = 1


def _material_dict(mat):
    def rgb(value):
        return None if value is None else np.asarray(value, np.float64).tolist()
    return {"ka": rgb(mat.ka), "kd": rgb(mat.kd), "ks": rgb(mat.ks),
            "shininess": float(mat.shininess), "emission": rgb(mat.emission)}


def _write_mesh(out_dir, dataset):
    """mesh_*.npy (exact arrays); returns the scene files' mesh reference: the built-in
    shape when the mesh is one, else None (the scene files then hold the mesh inline,
    normals included, so that they render exactly what the targets show)."""
    for name in MESH_ARRAYS:
        ds.write_npy(os.path.join(out_dir, f"mesh_{name}.npy"),
                     np.asarray(getattr(dataset.mesh, name)))
    return dataset.info.get("mesh_ref")


def _write_view(out_dir, dataset, i, mesh_ref):
    view, name = dataset.views[i], f"view_{i:03d}"
    scene = view_scene(dataset, i, dataset.truth or DEFAULT_INIT)
    write_json(os.path.join(out_dir, f"{name}.json"),
                  scene_to_dict(scene, dataset.settings, mesh_ref))
    ds.write_png(os.path.join(out_dir, f"{name}.png"), view.target)
    ds.write_npy(os.path.join(out_dir, f"{name}.npy"), view.target.astype(np.float32))
    entry = {"scene": f"{name}.json", "image": f"{name}.png", "target": f"{name}.npy",
             "mask": None}
    if view.mask is not None:
        entry["mask"] = f"{name}_mask.png"
        ds.write_png(os.path.join(out_dir, entry["mask"]), view.mask.astype(np.float64),
                     color_space="linear")
    return entry


def save_dataset(dataset: Dataset, out_dir) -> str:
    """Write `dataset` to the folder out_dir (created if missing); returns its path."""
    if dataset.objects is not None:
        raise ValueError("dataset: a dataset of several objects; save_dataset writes "
                         "datasets of one object (one mesh and one material) only")
    out_dir = os.fspath(out_dir)
    os.makedirs(out_dir, exist_ok=True)
    mesh_ref = _write_mesh(out_dir, dataset)
    entries = [_write_view(out_dir, dataset, i, mesh_ref) for i in range(len(dataset.views))]
    if dataset.truth is not None:
        write_json(os.path.join(out_dir, "truth.json"), _material_dict(dataset.truth))
    write_json(os.path.join(out_dir, "dataset.json"),
                  {"format": FORMAT, "version": VERSION, "views": entries,
                   "info": dataset.info})
    return out_dir


def _read_json(path):
    if not os.path.isfile(path):
        raise FileNotFoundError(f"dataset file not found: {path!r}")
    with open(path, encoding="utf-8") as file:
        return json.load(file)


def _color_space(value, where):
    if value is not None and value not in COLOR_SPACES:
        raise ValueError(f"{where}: got {value!r}; expected one of {COLOR_SPACES}")
    return value


def _load_target(out_dir, entry, index, color_space, shared):
    npy = entry.get("target")
    if npy and os.path.isfile(os.path.join(out_dir, npy)):
        return ds.read_image(os.path.join(out_dir, npy))[..., :3]
    own = _color_space(entry.get("color_space"), f"views[{index}].color_space")
    image = ds.read_image(os.path.join(out_dir, entry["image"]), color_space or own or shared)
    if image.shape[-1] not in (3, 4):
        raise ValueError(f"views[{index}].image: {entry['image']!r} has {image.shape[-1]} "
                         "channels; expected RGB or RGBA")
    return image[..., :3]


def _load_view(out_dir, entry, index, color_space, shared):
    data = _read_json(os.path.join(out_dir, entry["scene"]))
    scene, settings = ds.scene_from_dict(data, out_dir)
    target = _load_target(out_dir, entry, index, color_space, shared)
    mask = None
    if entry.get("mask"):
        mask_path = os.path.join(out_dir, entry["mask"])
        mask = ds.read_image(mask_path, color_space="linear")[..., 0] > 0.5
    return scene, settings, View(scene.camera, scene.lights, target, mask)


def _load_mesh(out_dir):
    """The Mesh of the exact saved arrays (checked; float32 stays float32, float64 is
    float64 under x64)."""
    def path(name):
        return os.path.join(out_dir, f"mesh_{name}.npy")
    arrays = [np.load(path(name), allow_pickle=False) for name in MESH_ARRAYS]
    return check_mesh(ds.Mesh(*arrays), name=path)


def load_dataset(out_dir, color_space=None) -> Dataset:
    """The Dataset saved in the folder out_dir (see module docstring); color_space:
    'srgb' or 'linear' overrides the encoding of every image target (None: as the dataset
    and the files say)."""
    out_dir = os.fspath(out_dir)
    _color_space(color_space, "color_space")
    meta = _read_json(os.path.join(out_dir, "dataset.json"))
    if meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise ValueError(f"{out_dir}/dataset.json: format {meta.get('format')!r} version "
                         f"{meta.get('version')!r}; expected {FORMAT!r} version {VERSION}")
    shared = _color_space(meta.get("color_space"), f"{out_dir}/dataset.json: color_space")
    loaded = [_load_view(out_dir, entry, i, color_space, shared)
              for i, entry in enumerate(meta["views"])]
    scene, settings, _ = loaded[0]
    truth_path = os.path.join(out_dir, "truth.json")
    truth = ds.material(**_read_json(truth_path)) if os.path.isfile(truth_path) else None
    return Dataset(_load_mesh(out_dir), [view for _, _, view in loaded],
                   model=np.asarray(scene.model), global_ambient=np.asarray(scene.global_ambient),
                   settings=settings, truth=truth, local_viewer=scene.local_viewer,
                   two_sided=scene.two_sided, info=meta.get("info", {}))

"""Datasets from calibrated captures: a COLMAP text model or a Blender/NeRF transforms.json,
plus a scene file for what a calibration does not hold (mesh, lights, settings).

`import_capture(source, scene, out_dir, images=None)` writes a dataset folder (the format
of fitting.data.folder): `scene.json`, the given scene file with its camera(s) replaced by
the capture's, one OpenCV camera per photo (docs/calibrated-cameras.md), and mesh paths
rewritten to stay valid from out_dir; and `dataset.json`, one view per photo, whose
"image" is the photo's path relative to out_dir (photos are not copied). `source` is a
COLMAP model folder (cameras.txt, images.txt; `images` is the folder its image names are
relative to) or a transforms.json file (frames' file_path relative to it).

Everything is checked before anything is written: the calibration (diffshade.io.colmap,
diffshade.io.nerf), the scene file (as a scene), that every photo exists with its
camera's size. Errors are ValueError or OSError naming the file, key and value.
"""

import os

import diffshade as ds
from diffshade.io import camera_to_dict, read_colmap, read_json, read_transforms, write_json
from fitting.data.folder import FORMAT, VERSION

SCENE_FILE = "scene.json"


def capture_cameras(source, images=None) -> list:
    """[(photo path, Camera)] of a COLMAP model folder (photos in `images`) or a
    transforms.json (photos relative to it)."""
    source = os.fspath(source)
    if os.path.isdir(source):
        if images is None:
            raise ValueError(f"images: got none for the COLMAP model {source!r}; expected "
                             "the folder its images.txt names are relative to")
        return [(os.path.join(images, name), camera) for name, camera in read_colmap(source)]
    if images is not None:
        raise ValueError(f"images: got {images!r} with a transforms.json; expected none "
                         "(its frames' file_path are relative to it)")
    folder = os.path.dirname(os.path.abspath(source))
    return [(os.path.join(folder, name), camera) for name, camera in read_transforms(source)]


def _check_photo(path, camera):
    """FileNotFoundError or ValueError unless `path` is an image of the camera's size."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"photo not found: {path!r} (named by the calibration)")
    height, width = ds.read_image(path).shape[:2]
    if (width, height) != (camera.width, camera.height):
        raise ValueError(f"photo {path!r}: got {width}x{height} pixels; expected "
                         f"{camera.width}x{camera.height}, its calibration's width x height")


def _moved_mesh(mesh, scene_dir, out_dir):
    """A scene file's mesh object with a file path made relative to out_dir."""
    if not isinstance(mesh, dict) or not isinstance(mesh.get("path"), str):
        return mesh
    full = os.path.join(scene_dir, mesh["path"])
    return {**mesh, "path": os.path.relpath(os.path.abspath(full), os.path.abspath(out_dir))}


def _moved_scene(data, scene_dir, out_dir):
    """The scene file's dict, without cameras, mesh paths valid from out_dir."""
    data = {k: v for k, v in data.items() if k not in ("camera", "cameras")}
    if "mesh" in data:
        data["mesh"] = _moved_mesh(data["mesh"], scene_dir, out_dir)
    if isinstance(data.get("objects"), list):
        data["objects"] = [{**o, "mesh": _moved_mesh(o.get("mesh"), scene_dir, out_dir)}
                           if isinstance(o, dict) else o for o in data["objects"]]
    return data


def _scene_dict(scene_path, cameras, out_dir):
    """The dataset's scene file: the given one with the capture's cameras, checked (from
    the scene file's own folder, as out_dir may not exist yet)."""
    scene_path = os.fspath(scene_path)
    data = read_json(scene_path, "scene file")
    if not isinstance(data, dict):
        raise ValueError(f"{scene_path}: got {type(data).__name__}; expected a scene object")
    scene_dir = os.path.dirname(os.path.abspath(scene_path))
    cameras = {"cameras": [camera_to_dict(camera) for camera in cameras]}
    try:
        ds.scenes_from_dict({**_moved_scene(data, scene_dir, scene_dir), **cameras},
                            base_dir=scene_dir)
    except ValueError as err:
        raise type(err)(f"{scene_path}: {err}") from err
    return {**_moved_scene(data, scene_dir, out_dir), **cameras}


def import_capture(source, scene, out_dir, images=None) -> str:
    """Write the dataset folder out_dir (module docstring) of a capture; returns its path.
    source: a COLMAP text model folder or a transforms.json; scene: a scene file (mesh,
    lights, material, settings; its cameras are replaced); images: COLMAP's image folder."""
    out_dir = os.fspath(out_dir)
    named = capture_cameras(source, images)
    for path, camera in named:
        _check_photo(path, camera)
    data = _scene_dict(scene, [camera for _, camera in named], out_dir)
    views = [{"scene": SCENE_FILE, "camera": i,
              "image": os.path.relpath(os.path.abspath(path), os.path.abspath(out_dir))}
             for i, (path, _) in enumerate(named)]
    os.makedirs(out_dir, exist_ok=True)
    write_json(os.path.join(out_dir, SCENE_FILE), data)
    write_json(os.path.join(out_dir, "dataset.json"),
               {"format": FORMAT, "version": VERSION, "views": views,
                "info": {"imported_from": os.path.abspath(os.fspath(source))}})
    return out_dir

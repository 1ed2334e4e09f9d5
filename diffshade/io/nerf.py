"""Blender/NeRF transforms.json <-> named Cameras.

The format of the NeRF synthetic scenes (and instant-ngp's extension of it): one set of
intrinsics for every frame and, per frame, `file_path` and `transform_matrix`, the
camera-to-world 4x4 matrix in OpenGL/Blender camera axes (x right, y up, looking down -z).
Intrinsics: `camera_angle_x` (radians, the full horizontal field of view) or `fl_x`
(pixels); optionally `camera_angle_y` or `fl_y` (default: square pixels), `cx`, `cy`
(default the image centre; like COLMAP, the top-left pixel's centre is (0.5, 0.5)), `w`,
`h` (default: the first frame's image size) and OpenCV's `k1`, `k2`, `p1`, `p2`, `k3`.
Other keys (aabb_scale, a frame's rotation, ...) do not describe the camera and are
ignored. A frame's file_path may leave out the image's extension (".png" is tried).

`read_transforms(path)` gives [(image path relative to the file's folder, Camera)];
`transforms_dict(named_cameras)` the inverse (cameras sharing one set of intrinsics).
Problems are ValueErrors "<file>: <key>: got ...; expected ...".
"""

import os

import numpy as np

from diffshade.io.images import read_image
from diffshade.io.scenefile import read_json
from diffshade.scene.calibration import camera_from_opencv, camera_to_opencv

#: the keys read from the top level; per-frame intrinsics are refused, not ignored
INTRINSIC_KEYS = ("camera_angle_x", "camera_angle_y", "fl_x", "fl_y", "cx", "cy", "w", "h",
                  "k1", "k2", "p1", "p2", "k3")
_GL_FROM_CV = np.diag([1.0, -1.0, -1.0])
#: transforms.json's pixel coordinates minus OpenCV's
PIXEL_OFFSET = 0.5


def _fail(where, value, expected):
    shown = repr(value)
    raise ValueError(f"{where}: got {shown if len(shown) <= 60 else shown[:57] + '...'}; "
                     f"expected {expected}")


def _number(data, key, where, positive=False):
    value = data[key]
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(
            value) or (positive and value <= 0):
        _fail(f"{where}: {key}", value, "a positive number" if positive else "a number")
    return float(value)


def _image_file(folder, file_path, where):
    """file_path as given, or with '.png' added when only that file exists."""
    if not isinstance(file_path, str) or not file_path:
        _fail(f"{where}.file_path", file_path, "an image path relative to transforms.json")
    for name in (file_path, file_path + ".png"):
        if os.path.isfile(os.path.join(folder, name)):
            return os.path.normpath(name)
    raise FileNotFoundError(f"{where}.file_path: image {file_path!r} not found in {folder!r}")


def _size(data, frames, folder, where):
    """(w, h): the file's keys, else the first frame's image size."""
    if "w" in data and "h" in data:
        return tuple(int(_number(data, k, where, positive=True)) for k in ("w", "h"))
    image = read_image(os.path.join(folder, frames[0][0]))
    return image.shape[1], image.shape[0]


def _focal(data, angle_key, focal_key, side, where):
    if focal_key in data:
        return _number(data, focal_key, where, positive=True)
    if angle_key not in data:
        return None
    angle = _number(data, angle_key, where, positive=True)
    if angle >= np.pi:
        _fail(f"{where}: {angle_key}", angle, "a field of view in radians, in (0, pi)")
    return 0.5 * side / np.tan(0.5 * angle)


def _intrinsics(data, width, height, where):
    """(K in OpenCV's pixel convention, dist) from the top-level keys."""
    fx = _focal(data, "camera_angle_x", "fl_x", width, where)
    if fx is None:
        raise ValueError(f"{where}: camera_angle_x: missing; expected the horizontal field "
                         "of view in radians (or fl_x in pixels)")
    fy = _focal(data, "camera_angle_y", "fl_y", height, where) or fx
    cx = _number(data, "cx", where) if "cx" in data else width / 2.0
    cy = _number(data, "cy", where) if "cy" in data else height / 2.0
    dist = [_number(data, k, where) if k in data else 0.0 for k in ("k1", "k2", "p1", "p2",
                                                                   "k3")]
    K = [[fx, 0.0, cx - PIXEL_OFFSET], [0.0, fy, cy - PIXEL_OFFSET], [0.0, 0.0, 1.0]]
    return K, dist


def _pose(matrix, where):
    """(R, t) in OpenCV's convention of a camera-to-world matrix in OpenGL axes."""
    try:
        c2w = np.asarray(matrix, np.float64)
    except (TypeError, ValueError):
        c2w = np.zeros(0)
    if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
        _fail(f"{where}.transform_matrix", matrix, "a finite 4x4 camera-to-world matrix")
    R = (c2w[:3, :3] @ _GL_FROM_CV).T
    return R, -R @ c2w[:3, 3]


def _frames(data, folder, where):
    """[(image file, frame)] of the file's frames, each checked for per-frame intrinsics."""
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        _fail(f"{where}: frames", frames, "a non-empty list of {file_path, transform_matrix}")
    named = []
    for i, frame in enumerate(frames):
        at = f"{where}: frames[{i}]"
        if not isinstance(frame, dict) or "transform_matrix" not in frame:
            _fail(at, frame, "an object with file_path and transform_matrix")
        own = sorted(set(frame) & set(INTRINSIC_KEYS))
        if own:
            raise ValueError(f"{at}: {own[0]}: per-frame intrinsics are not read; expected "
                             "them at the top level, one set for every frame")
        named.append((_image_file(folder, frame.get("file_path"), at), frame))
    return named


def read_transforms(path, near=0.1, far=100.0) -> list:
    """[(image path relative to the file's folder, Camera)] of a transforms.json, in its
    frames' order; near, far: the cameras' clip distances."""
    path = os.fspath(path)
    data = read_json(path, "transforms.json")
    if not isinstance(data, dict):
        _fail(path, data, "a JSON object with camera_angle_x and frames")
    folder = os.path.dirname(os.path.abspath(path))
    frames = _frames(data, folder, path)
    width, height = _size(data, frames, folder, path)
    K, dist = _intrinsics(data, width, height, path)
    named = []
    for i, (name, frame) in enumerate(frames):
        R, t = _pose(frame["transform_matrix"], f"{path}: frames[{i}]")
        try:
            named.append((name, camera_from_opencv(K, R, t, width, height, dist, near=near,
                                                   far=far)))
        except ValueError as err:
            raise ValueError(f"{path}: frames[{i}]: {err}") from err
    return named


def _frame(name, calibration):
    R, t = calibration["R"], calibration["t"]
    c2w = np.eye(4)
    c2w[:3, :3], c2w[:3, 3] = R.T @ _GL_FROM_CV, -R.T @ t
    return {"file_path": name, "transform_matrix": c2w.tolist()}


def transforms_dict(named_cameras) -> dict:
    """The transforms.json (a JSON-ready dict) of [(image path, Camera)], all cameras of
    one size, K and distortion (the format has one set of intrinsics)."""
    calibrations = [camera_to_opencv(camera) for _, camera in named_cameras]
    first = calibrations[0]
    for (name, _), other in zip(named_cameras, calibrations, strict=True):
        if not all(np.array_equal(first[k], other[k]) for k in ("K", "dist", "width",
                                                                "height")):
            raise ValueError(f"cameras: {name!r} has other intrinsics than the first; "
                             "expected one K, size and distortion (transforms.json has one)")
    K, width = first["K"], first["width"]
    intrinsics = {"camera_angle_x": float(2.0 * np.arctan(0.5 * width / K[0, 0])),
                  "fl_x": float(K[0, 0]), "fl_y": float(K[1, 1]),
                  "cx": float(K[0, 2] + PIXEL_OFFSET), "cy": float(K[1, 2] + PIXEL_OFFSET),
                  "w": width, "h": first["height"]}
    dist = dict(zip(("k1", "k2", "p1", "p2", "k3"), first["dist"].tolist(), strict=True))
    return {**intrinsics, **{k: v for k, v in dist.items() if v},
            "frames": [_frame(name, c) for (name, _), c in zip(named_cameras, calibrations,
                                                               strict=True)]}

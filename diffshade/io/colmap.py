"""COLMAP sparse models in text form: cameras.txt and images.txt <-> named Cameras.

`read_colmap(folder)` returns one (image name, Camera) per line of images.txt, in the
file's order; `colmap_text(named_cameras)` writes the two files' text back (the PINHOLE
model, or OPENCV where a camera has distortion). COLMAP's conventions: images.txt gives
the world-to-camera rotation as a unit quaternion (QW, QX, QY, QZ, Hamilton) and the
translation (TX, TY, TZ), x_cam = R x + t as in OpenCV; cameras.txt gives the intrinsics
with the centre of the top-left pixel at (0.5, 0.5), half a pixel from OpenCV's (0, 0).
The camera models read: SIMPLE_PINHOLE (f, cx, cy), PINHOLE (fx, fy, cx, cy),
SIMPLE_RADIAL (f, cx, cy, k), RADIAL (f, cx, cy, k1, k2), OPENCV (fx, fy, cx, cy, k1, k2,
p1, p2); their radial and tangential terms are OpenCV's k1, k2, p1, p2.

Every problem is a ValueError "<file>, line N: ..." naming the value and what was
expected (an unknown model, a camera id images.txt uses but cameras.txt lacks, a bad
quaternion, or a calibration camera_from_opencv refuses).
"""

import os

import numpy as np

from diffshade.scene.calibration import camera_from_opencv, camera_to_opencv

#: model name -> (parameter names, (fx, fy, cx, cy, dist) from the parameters)
MODELS = {
    "SIMPLE_PINHOLE": (("f", "cx", "cy"), lambda f, cx, cy: (f, f, cx, cy, None)),
    "PINHOLE": (("fx", "fy", "cx", "cy"), lambda fx, fy, cx, cy: (fx, fy, cx, cy, None)),
    "SIMPLE_RADIAL": (("f", "cx", "cy", "k"),
                      lambda f, cx, cy, k: (f, f, cx, cy, [k, 0.0, 0.0, 0.0])),
    "RADIAL": (("f", "cx", "cy", "k1", "k2"),
               lambda f, cx, cy, k1, k2: (f, f, cx, cy, [k1, k2, 0.0, 0.0])),
    "OPENCV": (("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
               lambda fx, fy, cx, cy, *dist: (fx, fy, cx, cy, list(dist))),
}
#: COLMAP's pixel coordinates minus OpenCV's
PIXEL_OFFSET = 0.5


def _lines(path):
    """(line number, fields) of the file's data lines, blank lines kept as []."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"COLMAP model file not found: {path!r}")
    with open(path, encoding="utf-8") as file:
        return [(n, line.split()) for n, line in enumerate(file, 1)
                if not line.lstrip().startswith("#")]


def _numbers(fields, where, what):
    try:
        values = [float(x) for x in fields]
    except ValueError:
        raise ValueError(f"{where}: got {' '.join(fields)!r}; expected {what}") from None
    if not np.all(np.isfinite(values)):
        raise ValueError(f"{where}: got {' '.join(fields)!r}; expected finite {what}")
    return values


def _intrinsics(fields, where):
    """{"model", "width", "height", "K", "dist"} of a cameras.txt line's fields."""
    if len(fields) < 4 or fields[1] not in MODELS:
        raise ValueError(f"{where}: got {' '.join(fields)!r}; expected CAMERA_ID MODEL WIDTH "
                         f"HEIGHT PARAMS with MODEL one of {', '.join(MODELS)}")
    names, convert = MODELS[fields[1]]
    if len(fields) != 4 + len(names) or not all(x.isdigit() for x in fields[2:4]):
        raise ValueError(f"{where}: got {' '.join(fields)!r}; expected CAMERA_ID "
                         f"{fields[1]} WIDTH HEIGHT {' '.join(names)}")
    fx, fy, cx, cy, dist = convert(*_numbers(fields[4:], where, " ".join(names)))
    K = [[fx, 0.0, cx - PIXEL_OFFSET], [0.0, fy, cy - PIXEL_OFFSET], [0.0, 0.0, 1.0]]
    return {"width": int(fields[2]), "height": int(fields[3]), "K": K, "dist": dist}


def read_cameras_txt(path) -> dict:
    """{camera id: intrinsics (width, height, K in OpenCV's pixel convention, dist)}."""
    cameras = {}
    for number, fields in _lines(path):
        if fields:
            cameras[fields[0]] = _intrinsics(fields, f"{path}, line {number}")
    return cameras


def quaternion_to_rotation(q):
    """[3, 3] rotation of the unit quaternion q = (w, x, y, z) (Hamilton)."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def rotation_to_quaternion(R):
    """(w, x, y, z), w >= 0, of the rotation R [3, 3] (the eigenvector of the symmetric
    4x4 matrix of Bar-Itzhack's method: stable for every angle)."""
    (a, b, c), (d, e, f), (g, h, i) = np.asarray(R, np.float64)
    k = np.array([[a - e - i, d + b, g + c, h - f], [d + b, e - a - i, h + f, c - g],
                  [g + c, h + f, i - a - e, d - b], [h - f, c - g, d - b, a + e + i]]) / 3
    x, y, z, w = np.linalg.eigh(k)[1][:, -1]
    return np.array([w, x, y, z]) * (1.0 if w >= 0 else -1.0)


def _pose(fields, where):
    """(R, t, camera id, name) of an images.txt image line."""
    if len(fields) < 10:
        raise ValueError(f"{where}: got {' '.join(fields)!r}; expected IMAGE_ID QW QX QY QZ "
                         "TX TY TZ CAMERA_ID NAME")
    q = np.array(_numbers(fields[1:5], where, "a quaternion QW QX QY QZ"))
    norm = np.linalg.norm(q)
    if abs(norm - 1.0) > 1e-3:
        raise ValueError(f"{where}: quaternion {fields[1:5]} has norm {norm:.6g}; expected "
                         "a unit quaternion QW QX QY QZ")
    t = _numbers(fields[5:8], where, "a translation TX TY TZ")
    # the name may contain spaces; it is the rest of the line
    return quaternion_to_rotation(q / norm), t, fields[8], " ".join(fields[9:])


def _image_lines(path):
    """(line number, fields) of each image line (each is followed by its points line)."""
    lines, images, i = _lines(path), [], 0
    while i < len(lines):
        if lines[i][1]:
            images.append(lines[i])
            i += 1  # skip its POINTS2D line
        i += 1
    return images


def read_colmap(folder, near=0.1, far=100.0) -> list:
    """[(image name, Camera)] of a COLMAP text model folder (cameras.txt, images.txt), in
    images.txt's order; near, far: the cameras' clip distances (the model's units)."""
    folder = os.fspath(folder)
    cameras_path = os.path.join(folder, "cameras.txt")
    images_path = os.path.join(folder, "images.txt")
    intrinsics = read_cameras_txt(cameras_path)
    named = []
    for number, fields in _image_lines(images_path):
        where = f"{images_path}, line {number}"
        R, t, camera_id, name = _pose(fields, where)
        if camera_id not in intrinsics:
            raise ValueError(f"{where}: CAMERA_ID {camera_id} is not in {cameras_path} "
                             f"(it has {', '.join(intrinsics) or 'none'})")
        try:
            camera = camera_from_opencv(R=R, t=t, near=near, far=far, **intrinsics[camera_id])
        except ValueError as err:
            raise ValueError(f"{where} (camera {camera_id}): {err}") from err
        named.append((name, camera))
    if not named:
        raise ValueError(f"{images_path}: no images; expected one line per image")
    return named


def _model_line(camera_id, calibration):
    K, dist = calibration["K"], calibration["dist"]
    fx, fy = K[0, 0], K[1, 1]
    cx, cy = K[0, 2] + PIXEL_OFFSET, K[1, 2] + PIXEL_OFFSET
    model, params = ("OPENCV", [fx, fy, cx, cy, *dist[:4]]) if np.any(dist) else (
        "PINHOLE", [fx, fy, cx, cy])
    if dist[4]:
        raise ValueError(f"camera {camera_id}: k3 = {dist[4]}; expected 0 (COLMAP's OPENCV "
                         "model has k1, k2, p1, p2 only)")
    text = " ".join(repr(float(p)) for p in params)
    return f"{camera_id} {model} {calibration['width']} {calibration['height']} {text}"


def colmap_text(named_cameras) -> tuple[str, str]:
    """(cameras.txt, images.txt) text of [(image name, Camera)]: one COLMAP camera per
    image (PINHOLE, or OPENCV with distortion), no 2D points."""
    cameras, images = ["# CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]"], [
        "# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME", "# POINTS2D[] as (X, Y, POINT3D_ID)"]
    for i, (name, camera) in enumerate(named_cameras, 1):
        calibration = camera_to_opencv(camera)
        cameras.append(_model_line(i, calibration))
        pose = [*rotation_to_quaternion(calibration["R"]), *calibration["t"]]
        images += [f"{i} {' '.join(repr(float(x)) for x in pose)} {i} {name}", ""]
    return "\n".join(cameras) + "\n", "\n".join(images) + "\n"

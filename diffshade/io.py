"""Atomic file output and image input.

Every writer builds the complete file contents in memory, writes them to a hidden
temporary file in the target's directory and moves it over the target with `os.replace`:
a reader sees either the old file or the new one, never a partial file, and on any error
the temporary file is removed (the old target, if any, is left untouched). Missing parent
directories are created. Each writer returns the path it wrote, as a str.

Images are (H, W, C) float arrays in [0, 1], row 0 at the top, C in {1, 3, 4}; PNGs are
8-bit, round(clip(x, 0, 1) * 255). `read_image` returns float32 [H, W, C]: PNG (and the
other formats pillow reads, 8 or 16 bit) scaled from integers to [0, 1], .npy as stored.
"""

import io
import json
import os
import uuid

import imageio.v3 as iio
import numpy as np

__all__ = ["read_image", "write_json", "write_npy", "write_png", "write_text"]


def _write_atomic(path, data: bytes) -> str:
    """Write `data` to `path` through a temporary file in the same directory."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    tmp = os.path.join(folder, f".{os.path.basename(path)}.{uuid.uuid4().hex[:12]}.tmp")
    # os.open with mode 0o666 lets the umask decide permissions, as a plain open() would
    # (tempfile.mkstemp would leave every output readable by its owner only).
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as file:
            file.write(data)
            file.flush()
            # Without fsync a crash soon after the rename can leave an empty target.
            os.fsync(file.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise
    return path


def _image_array(image, path):
    """image as a float64 [H, W, C] array with C in {1, 3, 4}, or ValueError."""
    arr = np.asarray(image, dtype=np.float64)
    if arr.ndim == 2:
        arr = arr[..., None]
    if arr.ndim != 3 or arr.shape[2] not in (1, 3, 4) or arr.size == 0:
        raise ValueError(f"image for {path!r}: shape {arr.shape}; expected [H, W, C] with "
                         "H, W >= 1 and C in (1, 3, 4)")
    bad = int(np.count_nonzero(~np.isfinite(arr)))
    if bad:
        raise ValueError(f"image for {path!r}: {bad} values are NaN or infinite; "
                         "expected finite values")
    return arr


def write_png(path, image) -> str:
    """Write image ([H, W, C] float in [0, 1], C in {1, 3, 4}) as an 8-bit PNG."""
    path = os.fspath(path)
    pixels = np.round(np.clip(_image_array(image, path), 0.0, 1.0) * 255.0).astype(np.uint8)
    if pixels.shape[2] == 1:
        pixels = pixels[..., 0]
    return _write_atomic(path, iio.imwrite("<bytes>", pixels, extension=".png"))


def write_npy(path, array) -> str:
    """Write array (any shape and dtype, e.g. float RGBA [H, W, 4]) as a .npy file."""
    buffer = io.BytesIO()
    np.save(buffer, np.asarray(array), allow_pickle=False)
    return _write_atomic(path, buffer.getvalue())


def _is_container(value):
    return isinstance(value, (dict, list, tuple))


def _json_text(obj, indent, depth=0):
    """JSON text with one line per member or element, except that an array of scalars
    stays on one line, so vectors and matrix rows read as such."""
    if not _is_container(obj) or not obj or (
            not isinstance(obj, dict) and not any(map(_is_container, obj))):
        return json.dumps(obj, allow_nan=False)
    pad, inner = " " * indent * depth, " " * indent * (depth + 1)
    if isinstance(obj, dict):
        # json's own key rules: non-string keys (1, true, null) become their JSON text.
        keys = [json.dumps(k if isinstance(k, str) else json.dumps(k)) + ": " for k in obj]
        items, brackets = zip(keys, obj.values(), strict=True), "{}"
    else:
        items, brackets = (("", value) for value in obj), "[]"
    lines = [inner + key + _json_text(value, indent, depth + 1) for key, value in items]
    return brackets[0] + "\n" + ",\n".join(lines) + "\n" + pad + brackets[1]


def write_json(path, obj, *, indent=2) -> str:
    """Write obj (dicts, lists, str, numbers, bool, None) as strict JSON: NaN and infinity
    are errors, as JSON has no such numbers. Arrays of scalars stay on one line."""
    try:
        text = _json_text(obj, indent) + "\n"
    except ValueError as err:
        raise ValueError(f"obj for {os.fspath(path)!r}: {err}; expected finite numbers "
                         "(JSON has no NaN or infinity)") from err
    return _write_atomic(path, text.encode("utf-8"))


def write_text(path, text: str) -> str:
    """Write text as UTF-8."""
    return _write_atomic(path, text.encode("utf-8"))


def _unit_range(arr):
    """Integer pixel values scaled to [0, 1]; floating values kept as stored."""
    if np.issubdtype(arr.dtype, np.integer):
        return arr.astype(np.float32) / np.float32(np.iinfo(arr.dtype).max)
    return arr.astype(np.float32)


def read_image(path) -> np.ndarray:
    """Image file -> float32 [H, W, C] in [0, 1] (PNG and pillow's formats, or .npy).

    Raises FileNotFoundError naming the path when there is no such file, and ValueError
    when the file cannot be decoded or does not hold an [H, W] or [H, W, C] image.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"image file not found: {path!r}")
    try:
        if path.lower().endswith(".npy"):
            arr = np.load(path, allow_pickle=False)
        else:
            # Naming the plugin skips imageio's probing of every other format.
            arr = iio.imread(path, plugin="pillow")
    # numpy and pillow raise many exception types; all mean "cannot decode".
    except Exception as err:
        raise ValueError(f"path: cannot read image file {path!r}: {err}") from err
    if arr.ndim == 2:
        arr = arr[..., None]
    is_real = np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)
    if arr.ndim != 3 or not is_real:
        raise ValueError(f"path: image file {path!r} holds {arr.dtype} of shape {arr.shape}; "
                         "expected real numbers of shape [H, W] or [H, W, C]")
    return _unit_range(arr)

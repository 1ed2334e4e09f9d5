"""Atomic file output and image input.

Every writer builds the complete file contents in memory, writes them to a hidden
temporary file in the target's directory and moves it over the target with `os.replace`:
a reader sees either the old file or the new one, never a partial file, and on any error
the temporary file is removed (the old target, if any, is left untouched). Missing parent
directories are created. Each writer returns the path it wrote, as a str.

Images are (H, W, C) float arrays of *linear* colours, row 0 at the top, C in {1, 3, 4}
(a 4th channel is alpha, never encoded). Files hold encoded values (docs/color.md):
`write_png` encodes (sRGB by default, tagged with sRGB and gAMA chunks; or linear, tagged
gAMA 1.0) and quantizes to 8 or 16 bits, round(clip(encoded, 0, 1) * (2^bits - 1)).
`read_image` returns float32 linear [H, W, C]: integer-coded files (PNG 8 or 16 bit, JPEG
and the other formats pillow reads) are scaled to [0, 1] and decoded with the transfer
the file declares (`image_transfer`), sRGB when it declares none, or with the caller's
`color_space` (any case: 'sRGB' is 'srgb'); .npy (and EXR, when an imageio plugin for it
is installed) is linear and read as stored. The format is the one the file's first bytes
say (a name that says another is refused), and the size its header gives is checked
against the memory budget (diffshade.budget) before anything is decoded
(diffshade.io.image_formats, which also says how colour modes such as CMYK and palette
are converted).
"""

import io
import json
import os
import uuid

import imageio.v3 as iio
import numpy as np

from diffshade import budget
from diffshade.io.color import COLOR_SPACES, decode, encode
from diffshade.io.image_formats import decode_pillow, header
from diffshade.io.png import color_chunks, decode_png16, encode_png, png_header, png_transfer

__all__ = ["check_color_space", "check_writable", "image_transfer", "read_image",
           "write_json", "write_npy", "write_png", "write_text"]

_LINEAR_FORMATS = ("NPY", "EXR")


def _write_atomic(path, data: bytes) -> str:
    """Write `data` to `path` through a temporary file in the same directory."""
    path = os.fspath(path)
    folder = os.path.dirname(os.path.abspath(path))
    os.makedirs(folder, exist_ok=True)
    tmp = os.path.join(folder, f".{os.path.basename(path)}.{uuid.uuid4().hex[:12]}.tmp")
    # os.open with mode 0o666 lets the umask decide permissions, as a plain open() would
    # (tempfile.mkstemp would leave every output readable by its owner only).
    try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    except OSError as err:  # the user's path, not the hidden temporary, is what failed
        raise type(err)(err.errno, err.strerror, path) from None
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


def check_writable(path, name, kind="file"):
    """Raise an OSError naming `name` (the option or argument) and `path` unless path can
    be written, checked before the work whose result goes there. kind: 'file' (written
    through a temporary file beside it), 'folder' (files are written inside it: itself
    when it exists must be writable) or 'replaced' (a folder made beside it and renamed
    over it). The folder that must be writable is the nearest one that exists."""
    path = os.fspath(path)
    place = os.path.abspath(path)
    if kind == "file" and os.path.isdir(place):
        raise IsADirectoryError(f"{name}: {path!r} is a folder; expected a file to write")
    if kind != "file" and os.path.exists(place) and not os.path.isdir(place):
        raise NotADirectoryError(f"{name}: {path!r} is a file; expected a folder to write")
    if not (kind == "folder" and os.path.isdir(place)):
        place = os.path.dirname(place)
    while not os.path.exists(place):
        place = os.path.dirname(place)
    if not os.path.isdir(place):
        raise NotADirectoryError(f"{name}: cannot write {path!r}: {place!r} is a file; "
                                 "expected a folder")
    problem = _write_problem(place)
    if problem:
        raise PermissionError(f"{name}: cannot write {path!r}: the folder {place!r} is not "
                              f"writable ({problem}); expected a writable place")
    return path


def _write_problem(folder):
    """Why a file cannot be created in `folder` (its strerror), or None. Tried, not
    inferred from the mode bits: root ignores those, while a read-only mount or an
    immutable folder refuses everyone. The probe file is removed at once."""
    probe = os.path.join(folder, f".diffshade-probe-{uuid.uuid4().hex[:12]}")
    try:
        os.close(os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600))
    except OSError as err:
        return err.strerror
    os.remove(probe)
    return None


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


def check_color_space(color_space, name="color_space"):
    """color_space in lower case ('sRGB' is 'srgb'), or ValueError naming `name`."""
    if not isinstance(color_space, str) or color_space.lower() not in COLOR_SPACES:
        raise ValueError(f"{name}: got {color_space!r}; expected one of {COLOR_SPACES} "
                         "(in any case)")
    return color_space.lower()


def _colour_channels(arr, fn):
    """fn applied to the colour channels of [H, W, C]; alpha (C = 2 or 4) passes as is."""
    if arr.shape[-1] in (2, 4):
        return np.concatenate([fn(arr[..., :-1]), arr[..., -1:]], axis=-1)
    return fn(arr)


def write_png(path, image, *, color_space="srgb", bits=8) -> str:
    """Write image ([H, W, C] linear float, C in {1, 3, 4}) as a PNG of `bits` (8 or 16)
    per channel, its colour channels encoded in `color_space` ('srgb' or 'linear')."""
    path = os.fspath(path)
    color_space = check_color_space(color_space)
    if bits not in (8, 16):
        raise ValueError(f"bits: got {bits!r}; expected 8 or 16")
    encoded = _colour_channels(_image_array(image, path), lambda c: encode(c, color_space))
    top = 2 ** bits - 1
    codes = np.round(np.clip(encoded, 0.0, 1.0) * top).astype(np.uint8 if bits == 8 else
                                                                np.uint16)
    return _write_atomic(path, encode_png(codes, color_chunks(color_space)))


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


def _load(path, kind):
    """(array as stored in the file, the transfer its colour chunks declare or None), by
    the file's format (its first bytes, image_formats.header)."""
    if kind == "NPY":
        return np.load(path, allow_pickle=False), "linear"
    if kind == "EXR":
        return iio.imread(path), "linear"  # whichever installed plugin reads EXR
    with open(path, "rb") as file:
        data = file.read()
    if kind != "PNG":
        return decode_pillow(data), None
    _, _, depth, color, interlace = png_header(data)
    if depth == 16 and color != 0 and interlace:
        raise ValueError("an interlaced 16-bit colour PNG (pillow would read it at 8 bits); "
                         "expected a non-interlaced one")
    pixels = decode_png16(data) if depth == 16 and not interlace else decode_pillow(data)
    return pixels, png_transfer(data)


def _check_decoded_size(path, found):
    """The decoded image must fit the memory budget: checked on its header's size."""
    pixels = found.width * found.height
    budget.check("path", repr(path), budget.image_bytes(found.width, found.height,
                                                          found.channels),
                 f"decoding its {found.width}x{found.height} pixels of {found.channels} "
                 "channels", pixels * found.channels, host=True)


def _decode_failure(err, kind):
    """The reason a file of format `kind` did not decode, in the user's terms (Pillow's
    "cannot identify image file <_io.BytesIO ...>" names an object, not the file)."""
    text = str(err)
    if "cannot identify image file" in text or not text:
        text = f"its data does not decode as {kind}"
    return f"{text}; expected an undamaged {kind} file"


def _read(path):
    """(array as stored, declared transfer or None, format) of the image file at path."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"image file not found: {path!r}")
    found = header(path)
    _check_decoded_size(path, found)
    try:
        arr, transfer = _load(path, found.kind)
    # numpy, pillow and zlib raise many exception types; all mean "cannot decode".
    except Exception as err:
        raise ValueError(f"path: cannot read image file {path!r}: "
                         f"{_decode_failure(err, found.kind)}") from err
    if arr.ndim == 2:
        arr = arr[..., None]
    is_real = np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)
    if arr.ndim != 3 or not is_real:
        raise ValueError(f"path: image file {path!r} holds {arr.dtype} of shape {arr.shape}; "
                         "expected real numbers of shape [H, W] or [H, W, C]")
    return arr, transfer, found.kind


def image_transfer(path):
    """How the file at `path` encodes colours: 'linear' (.npy, EXR, float pixels, a PNG
    tagged linear), 'srgb' (tagged so, or integer-coded and untagged), or a PNG gAMA
    exponent g (linear = value^(1/g))."""
    arr, transfer, kind = _read(path)
    if kind in _LINEAR_FORMATS or not np.issubdtype(arr.dtype, np.integer):
        return "linear"
    return transfer or "srgb"


def read_image(path, color_space=None) -> np.ndarray:
    """Image file -> float32 linear [H, W, C] (module docstring). color_space: 'srgb' or
    'linear' overrides what an integer-coded file declares; .npy and EXR are always linear.

    Raises FileNotFoundError naming the path when there is no such file, and ValueError
    when the file cannot be decoded or does not hold an [H, W] or [H, W, C] image.
    """
    if color_space is not None:
        color_space = check_color_space(color_space)
    arr, transfer, kind = _read(path)
    if not np.issubdtype(arr.dtype, np.integer):
        return arr.astype(np.float32)
    unit = arr.astype(np.float64) / np.iinfo(arr.dtype).max
    if kind in _LINEAR_FORMATS:
        return unit.astype(np.float32)
    transfer = color_space or transfer or "srgb"
    return _colour_channels(unit, lambda c: decode(c, transfer)).astype(np.float32)

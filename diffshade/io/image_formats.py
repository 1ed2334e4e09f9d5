"""What an image file holds, known before it is decoded: its format, size and channels.

`header(path)` reads the format from the file's first bytes (never from its name), then
the size and colour mode from its header alone (the PNG's IHDR, the .npy header, or
pillow's `Image.open`, which decodes nothing), so that a caller can compare the size
with what it expects, and with the memory budget, before decoding. A file whose name
says one format and whose bytes another is refused, saying what was found; so is an
empty file, or one in no format diffshade reads.

`decode_pillow(data)` decodes through pillow, converting the colour modes that have a
defined conversion to the ones diffshade works in: palette to RGB (RGBA where the palette
has transparency), CMYK, YCbCr, HSV and RGBX to RGB, bilevel to grey, premultiplied alpha
to straight alpha. A mode without a conversion (CIE L*a*b*) is refused by name.
"""

import io
import os
from typing import NamedTuple

import numpy as np
from PIL import Image

from diffshade.io.png import SIGNATURE, png_header

__all__ = ["Header", "decode_pillow", "header"]

#: format -> (first bytes, what the file is called in messages)
_MAGIC = {
    "PNG": ((SIGNATURE,), "a PNG image"),
    "JPEG": ((b"\xff\xd8\xff",), "a JPEG image"),
    "NPY": ((b"\x93NUMPY",), "a NumPy array (.npy)"),
    "EXR": ((b"\x76\x2f\x31\x01",), "an OpenEXR image"),
    "GIF": ((b"GIF87a", b"GIF89a"), "a GIF image"),
    "BMP": ((b"BM",), "a BMP image"),
    "TIFF": ((b"II*\x00", b"MM\x00*"), "a TIFF image"),
}
#: file extension -> the format its name promises
_EXTENSIONS = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG", ".npy": "NPY", ".exr": "EXR",
               ".gif": "GIF", ".bmp": "BMP", ".tif": "TIFF", ".tiff": "TIFF"}
_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}  # colour type -> channels (palette: RGB)
#: pillow mode -> the mode it is decoded as
_CONVERSIONS = {"1": "L", "PA": "RGBA", "CMYK": "RGB", "YCbCr": "RGB", "HSV": "RGB",
                "RGBX": "RGB", "RGBa": "RGBA", "La": "LA"}
_REFUSED = {"LAB": "CIE L*a*b* colour"}


class Header(NamedTuple):
    """kind: a key of _MAGIC (or pillow's format name); width, height, channels: of the
    decoded image; mode: pillow's colour mode (None for PNG read by diffshade and .npy)."""

    kind: str
    width: int
    height: int
    channels: int
    mode: str | None


def _kind(head):
    """The format whose magic bytes start `head`, or None."""
    for kind, (starts, _) in _MAGIC.items():
        if head.startswith(starts):
            return kind
    if head[:4] == b"RIFF" and head[8:12] == b"WEBP":
        return "WEBP"
    return None


def _described(kind):
    return _MAGIC[kind][1] if kind in _MAGIC else f"a {kind} image"


def _check_name(path, kind, head):
    """Refuse a file whose extension promises another format than its bytes hold."""
    extension = os.path.splitext(path)[1].lower()
    promised = _EXTENSIONS.get(extension)
    if not head:
        raise ValueError(f"path: {path!r} is empty (0 bytes); expected an image file")
    if promised and kind != promised:
        found = _described(kind) if kind else f"no image format diffshade reads (first "\
            f"bytes {head[:8].hex(' ')})"
        raise ValueError(f"path: {path!r} holds {found}; expected {_described(promised)}, "
                         f"as its extension {extension!r} says")


_NPY_HEADERS = {(1, 0): np.lib.format.read_array_header_1_0,
                (2, 0): np.lib.format.read_array_header_2_0}


def _npy_header(path):
    with open(path, "rb") as file:
        version = np.lib.format.read_magic(file)
        if version not in _NPY_HEADERS:
            raise ValueError(f".npy format version {version}; expected 1.0 or 2.0")
        shape, _, dtype = _NPY_HEADERS[version](file)
    if dtype.hasobject:
        raise ValueError(f"path: {path!r} holds Python objects ({dtype}), which only "
                         "unpickling could read; expected an array of numbers")
    height, width = (shape + (0, 0))[:2]
    return Header("NPY", width, height, shape[2] if len(shape) == 3 else 1, None)


def _pillow_mode(image):
    """The mode `image` decodes as (module docstring), or ValueError naming its mode."""
    if image.mode in _REFUSED:
        raise ValueError(f"colour mode {image.mode!r} ({_REFUSED[image.mode]}) has no "
                         "conversion to RGB here; expected RGB, RGBA, grey, palette or CMYK")
    if image.mode == "P":
        return "RGBA" if "transparency" in image.info else "RGB"
    return _CONVERSIONS.get(image.mode, image.mode)


def _pillow_header(path, kind):
    try:
        with Image.open(path) as image:
            mode = _pillow_mode(image)
            return Header(kind or image.format, image.width, image.height,
                          Image.getmodebands(mode), image.mode)
    except (OSError, SyntaxError) as err:  # pillow: no format of its own recognizes the file
        if kind is None:
            raise ValueError(f"path: {path!r} holds no image format diffshade reads; "
                             "expected PNG, JPEG (or another format pillow reads), .npy or "
                             "EXR") from err
        raise ValueError(f"path: cannot read image file {path!r}: {err}") from err


def header(path) -> Header:
    """The Header of the image file at path (module docstring); ValueError naming the path
    when its name and content disagree or its header cannot be read."""
    path = os.fspath(path)
    with open(path, "rb") as file:
        head = file.read(16)
    kind = _kind(head)
    _check_name(path, kind, head)
    try:
        return _read_header(path, kind)
    # numpy's and pillow's header parsers raise many exception types: all mean "cannot read"
    except Exception as err:
        if isinstance(err, ValueError) and str(err).startswith("path: "):
            raise
        raise ValueError(f"path: cannot read image file {path!r}: {err}") from err


def _read_header(path, kind):
    if kind == "NPY":
        return _npy_header(path)
    if kind == "EXR":
        return Header("EXR", 0, 0, 0, None)  # its plugin reads it whole
    if kind == "PNG":
        with open(path, "rb") as file:
            width, height, _, color, _ = png_header(file.read(33))
        return Header("PNG", width, height, _PNG_CHANNELS.get(color, 4), None)
    return _pillow_header(path, kind)


def decode_pillow(data: bytes) -> np.ndarray:
    """The pixels of an image pillow reads, in the mode it decodes as (module docstring)."""
    with Image.open(io.BytesIO(data)) as image:
        mode = _pillow_mode(image)
        return np.asarray(image if mode == image.mode else image.convert(mode))

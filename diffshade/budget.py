"""Memory budget: the bytes a size-like setting implies, checked before anything is allocated.

Every size a user can set turns into bytes here, one formula per kind, and `check` compares
them with two caps (docs/cli.md, "Sizes and memory"):
- MAX_ELEMENTS values in one array: JAX indexes arrays, and diffshade counts fragments and
  pixels, in int32, so a larger array would overflow an index (or abort inside XLA);
- the memory available: DIFFSHADE_MEMORY_LIMIT (bytes, or a number with a K, M, G or T
  suffix, powers of 1024) when set, else the free memory of JAX's default device (an
  accelerator's, from its memory statistics; the CPU's: MemAvailable of /proc/meminfo, or
  the available pages of os.sysconf where there is no /proc); what numpy holds on the
  host (decoded images, a synthetic dataset's targets) is compared with the host's.
A request beyond either raises `SizeError` (a ValueError), one line naming the key, the
value, the bytes needed and what is available.

The formulas are upper bounds, not predictions. The per-unit byte counts below were set
above what XLA's own memory analysis reports for small renders made with kernels='jax'
(tests/test_budget.py checks that they stay above it) and above the peak memory of
large ones, compilation included (benchmarks/memory_budget.py):
- a render: BASE_BYTES (compiling it, its small arrays and constants) + pixels x
  (PIXEL_BYTES + slots x SLOT_BYTES), slots being the fragments kept per pixel
  (faces_per_pixel in soft raster or for a transparent scene, else 1), plus the mesh
  (faces x FACE_BYTES) and the shadow maps;
- a shadow map side M: each map is rasterized at M x M texels (a texel costs what a hard
  raster's pixel does, PIXEL_BYTES + SLOT_BYTES) and kept as M x M depths; a point light
  has 6 maps (a cube), an area or sphere light 6 per sample, kept all at once while the
  maps are rasterized one sample's cube at a time;
- an image file or a dataset's images: pixels x channels x 8 bytes (decoded in float64);
- a texture in a render: texels x channels x TEXEL_BYTES (the texels, the cells that
  bilinear sampling reads and, differentiated, their gradients).
"""

import os
import re

import jax

__all__ = ["MAX_ELEMENTS", "SizeError", "available_bytes", "check", "image_bytes",
           "mesh_bytes", "render_bytes", "shadow_bytes", "texture_bytes"]

MAX_ELEMENTS = 2**31 - 1
BASE_BYTES = 512 * 2**20
PIXEL_BYTES = 256
SLOT_BYTES = 256
FACE_BYTES = 1024
DEPTH_BYTES = 8  # a stored shadow-map depth (float64 under jax_enable_x64)
DECODED_BYTES = 8  # a decoded image value (float64)
CUBE = 6
#: a texture's value in a render (float64): itself, the 6 values of its cell's columns
#: that sampling reads, and both again as gradients, with room for XLA's temporaries
TEXEL_BYTES = 96
LIMIT_VARIABLE = "DIFFSHADE_MEMORY_LIMIT"
_SUFFIXES = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


class SizeError(ValueError):
    """A size whose memory is beyond the budget (message: key, value, bytes, available)."""


def _limit_from_environment():
    """DIFFSHADE_MEMORY_LIMIT in bytes, or None when unset."""
    text = os.environ.get(LIMIT_VARIABLE)
    if text is None:
        return None
    match = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([KMGT]?)i?B?\s*", text, re.IGNORECASE)
    if not match:
        raise ValueError(f"{LIMIT_VARIABLE}: got {text!r}; expected bytes, or a number with "
                         "a K, M, G or T suffix (e.g. 8G)")
    return int(float(match.group(1)) * _SUFFIXES[match.group(2).upper()])


def _host_available():
    """(bytes, where from) of the host's available memory."""
    try:
        with open("/proc/meminfo") as file:
            for line in file:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024, "MemAvailable in /proc/meminfo"
    except OSError:
        pass
    pages = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    return pages, "available pages (os.sysconf)"


def _device_available():
    """(bytes, where from) of the default device's free memory, or None on the CPU (or
    where the device reports no statistics)."""
    if jax.default_backend() == "cpu":
        return None
    device = jax.devices()[0]
    stats = device.memory_stats() or {}
    if "bytes_limit" not in stats:
        return None
    free = stats["bytes_limit"] - stats.get("bytes_in_use", 0)
    return free, f"free memory of {device.device_kind}"


def available_bytes(host=False):
    """(bytes, where the figure comes from): the memory a request may use (module
    docstring); host=True: the host's, for what is held in numpy (a decoded image)."""
    limit = _limit_from_environment()
    if limit is not None:
        return limit, LIMIT_VARIABLE
    return (None if host else _device_available()) or _host_available()


def show_bytes(count):
    """'6.4 GB (6442450944 bytes)': decimal units, then the exact count."""
    for unit, size in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if count >= size:
            return f"{count / size:.3g} {unit} ({count} bytes)"
    return f"{count} bytes"


def check(key, value, needed, what, elements=0, host=False):
    """Raise SizeError unless `needed` bytes fit the memory available (host=True: the
    host's) and `elements` (the largest array's values) fit MAX_ELEMENTS. key, value: the
    setting to name; what: the request in words ('a render of 64x64 pixels')."""
    if elements > MAX_ELEMENTS:
        raise SizeError(f"{key}: got {value}; {what} needs an array of {elements} values; "
                        f"expected at most {MAX_ELEMENTS} (2^31 - 1) values in one array")
    available, source = available_bytes(host)
    if needed > available:
        raise SizeError(f"{key}: got {value}; {what} needs {show_bytes(needed)} of memory; "
                        f"expected at most {show_bytes(available)}, the memory available "
                        f"({source}; set {LIMIT_VARIABLE} to change it)")


def render_bytes(pixels, slots):
    """Bytes of the per-pixel work of a render (or of a shadow map's rasterization):
    pixels x (PIXEL_BYTES + slots x SLOT_BYTES)."""
    return pixels * (PIXEL_BYTES + slots * SLOT_BYTES)


def mesh_bytes(faces):
    """Bytes of a mesh's per-face work (its arrays and their projected copies)."""
    return faces * FACE_BYTES


def shadow_bytes(side, cubes, flat_maps=0):
    """Bytes of the shadow maps: `cubes` cube maps (6 maps each: a point light, or a sample
    of an area light) and `flat_maps` single maps (spot, directional) of side x side texels,
    all kept, plus the rasterization of one cube (or one map) at a time."""
    texels = side * side
    kept = (CUBE * cubes + flat_maps) * texels * DEPTH_BYTES
    in_flight = (CUBE if cubes else 1) * render_bytes(texels, 1) if cubes or flat_maps else 0
    return kept + in_flight


def image_bytes(width, height, channels):
    """Bytes of an image decoded to floats."""
    return width * height * channels * DECODED_BYTES


def texture_bytes(texels, channels):
    """Bytes of a texture of `texels` texels in a render (module docstring)."""
    return texels * channels * TEXEL_BYTES


"""The parts of PNG that pillow does not give: colour chunks, 16-bit colour, writing them.

Pillow reads 16-bit RGB and RGBA PNGs at 8 bits (13.0 still truncates them), and
through imageio it exposes gAMA and sRGB but not cICP. So diffshade reads a PNG's chunk
list itself (`png_transfer`), decodes non-interlaced 16-bit PNGs itself (`decode_png16`)
and writes every PNG itself (`encode_png`: 8 or 16 bit, filter 0, one IDAT, with the
colour chunks the caller gives). 8-bit and interlaced files are left to pillow.

The transfer a PNG declares, in the PNG specification's order of precedence:
- cICP: transfer characteristics 13 -> "srgb", 8 -> "linear" (other codes are ignored);
- iCCP: not interpreted (ICC profiles are not parsed); the chunks below still decide;
- sRGB -> "srgb";
- gAMA g: 1.0 -> "linear", 0.45455 (what sRGB writers store) -> "srgb", else g itself
  (a power law, see diffshade.io.color);
- none of them -> None (the caller's default applies).
"""

import struct
import zlib

import numpy as np

__all__ = ["color_chunks", "decode_png16", "encode_png", "png_header", "png_transfer"]

SIGNATURE = b"\x89PNG\r\n\x1a\n"
_COLOR_TYPES = {0: 1, 2: 3, 4: 2, 6: 4}  # PNG colour type -> channels (no palette)
_SRGB_GAMMA = 45455  # the gAMA value the PNG specification pairs with an sRGB chunk
_CICP_TRANSFERS = {13: "srgb", 8: "linear"}


def _chunks(data):
    """(type, payload) of each chunk, in file order, up to IEND."""
    pos = len(SIGNATURE)
    while pos + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        yield kind, data[pos + 8:pos + 8 + length]
        if kind == b"IEND":
            return
        pos += 12 + length


def png_header(data: bytes):
    """(width, height, bit depth, colour type, interlace) from IHDR."""
    kind, payload = next(_chunks(data), (None, b""))
    if kind != b"IHDR" or len(payload) != 13:
        raise ValueError("no IHDR chunk at the start; expected a PNG file")
    width, height, depth, color, _, _, interlace = struct.unpack(">IIBBBBB", payload)
    return width, height, depth, color, interlace


def png_transfer(data: bytes):
    """"srgb", "linear", a gAMA exponent, or None (module docstring)."""
    found = {kind: payload for kind, payload in _chunks(data) if kind in (
        b"cICP", b"sRGB", b"gAMA")}
    cicp = found.get(b"cICP", b"")
    if len(cicp) == 4 and cicp[1] in _CICP_TRANSFERS:
        return _CICP_TRANSFERS[cicp[1]]
    if b"sRGB" in found:
        return "srgb"
    if len(found.get(b"gAMA", b"")) == 4:
        gamma = struct.unpack(">I", found[b"gAMA"])[0]
        if gamma == 100000:
            return "linear"
        if abs(gamma - _SRGB_GAMMA) <= 10:
            return "srgb"
        return gamma / 100000.0 if gamma > 0 else None
    return None


def _predict(kind, left, up, up_left):
    """Filter 3 (average) or 4 (Paeth) predictions, as int arrays."""
    if kind == 3:
        return (left + up) // 2
    pa, pb, pc = np.abs(up - up_left), np.abs(left - up_left), np.abs(left + up - 2 * up_left)
    return np.where((pa <= pb) & (pa <= pc), left, np.where(pb <= pc, up, up_left))


def _unfilter_row(kind, line, prev, bpp):
    """One row's bytes [stride] uint8 with its filter undone (PNG spec section 9)."""
    if kind == 0:
        return line.copy()
    if kind == 1:  # uint8 sums wrap modulo 256, as the filter's arithmetic does
        return np.cumsum(line.reshape(-1, bpp), axis=0, dtype=np.uint8).ravel()
    if kind == 2:
        return line + prev
    if kind not in (3, 4):
        raise ValueError(f"row filter {kind}; expected 0 to 4")
    row, up = np.zeros(line.size, np.int64), prev.astype(np.int64)
    zero = np.zeros(bpp, np.int64)
    for x in range(0, line.size, bpp):  # each pixel depends on the one before it
        left = row[x - bpp:x] if x else zero
        up_left = up[x - bpp:x] if x else zero
        row[x:x + bpp] = (line[x:x + bpp] + _predict(kind, left, up[x:x + bpp], up_left)) & 255
    return row.astype(np.uint8)


def decode_png16(data: bytes) -> np.ndarray:
    """A non-interlaced 16-bit PNG -> uint16 [H, W, C] (C: 1 grey, 2 grey + alpha, 3, 4)."""
    width, height, depth, color, interlace = png_header(data)
    if depth != 16 or color not in _COLOR_TYPES or interlace:
        raise ValueError(f"bit depth {depth}, colour type {color}, interlace {interlace}; "
                         "expected a non-interlaced 16-bit PNG")
    channels = _COLOR_TYPES[color]
    stride, bpp = width * channels * 2, channels * 2
    raw = zlib.decompress(b"".join(p for kind, p in _chunks(data) if kind == b"IDAT"))
    rows = np.frombuffer(raw, np.uint8)[:height * (stride + 1)].reshape(height, stride + 1)
    out, prev = np.empty((height, stride), np.uint8), np.zeros(stride, np.uint8)
    for y in range(height):
        prev = out[y] = _unfilter_row(int(rows[y, 0]), rows[y, 1:], prev, bpp)
    return out.view(">u2").astype(np.uint16).reshape(height, width, channels)


def _chunk(kind: bytes, payload: bytes) -> bytes:
    crc = zlib.crc32(kind + payload) & 0xFFFFFFFF
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", crc)


def color_chunks(color_space) -> list:
    """The chunks that declare `color_space`: sRGB (perceptual intent) with its gAMA, or
    gAMA 1.0 for linear values."""
    if color_space == "srgb":
        return [(b"sRGB", b"\x00"), (b"gAMA", struct.pack(">I", _SRGB_GAMMA))]
    return [(b"gAMA", struct.pack(">I", 100000))]


def encode_png(codes: np.ndarray, chunks=()) -> bytes:
    """uint8 or uint16 [H, W, C] (C in 1 to 4) -> PNG bytes with `chunks` ((type, payload)
    pairs) before the image data."""
    height, width, channels = codes.shape
    color = {v: k for k, v in _COLOR_TYPES.items()}[channels]
    depth = 16 if codes.dtype == np.uint16 else 8
    rows = np.ascontiguousarray(codes, ">u2" if depth == 16 else np.uint8)
    rows = rows.view(np.uint8).reshape(height, -1)
    raw = np.concatenate([np.zeros((height, 1), np.uint8), rows], axis=1).tobytes()
    header = struct.pack(">IIBBBBB", width, height, depth, color, 0, 0, 0)
    parts = [_chunk(b"IHDR", header), *(_chunk(k, p) for k, p in chunks),
             _chunk(b"IDAT", zlib.compress(raw, 6)), _chunk(b"IEND", b"")]
    return SIGNATURE + b"".join(parts)

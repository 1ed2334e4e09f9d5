"""Compiled forward and backward kernels of the bilinear texture lookup (GL_LINEAR).

diffshade.shading.texturing wraps these in a FragmentOp (hostop.py): the forward kernel
reads each sample's four texels straight from the texture, and the backward kernel
scatters the cotangents into the texels and gives the UVs their gradient, in one pass
each, where the same lookup in XLA on the CPU (gathers, and a serial scatter-add as their
transpose) costs several times more.

Conventions: M samples; `ids` [M] int32 is the offset of the sample's texture in the
flat texels [T, C] (0 for one texture; b * height * width for member b of a batch folded
into one call), -1 for no sample (zeros, no gradient); uv [M, 2] (v = 0 at the image's
bottom row); `height`, `width` the texture's size, so a texture is the rows [offset,
offset + height * width) of texels, row-major from the image's top row. `clamp`: the
wrap, True for 'clamp' (edge texels), False for 'repeat' (u and v modulo 1). The texel
coordinates are computed in float64, the blend in the texels' dtype.

Every read is in range whatever the UV: a coordinate that is not finite (NaN, or an
infinite one under 'repeat') reads texel 0 of its axis with weight NaN, so the value is
NaN, as in the jax.numpy lookup; an offset whose texture would end past the texels reads
nothing (zeros). Kernels split the samples into `chunks` parts run in parallel; the
backward kernel accumulates the texels' gradient in one buffer per part (no races).
"""

import numba
import numpy as np
from numba import prange


@numba.njit(cache=True, nogil=True, inline="always")
def _axis(coord, size, clamp):
    """(index of the texel at or before coord, index of the next one, the next one's
    weight, d weight / d coord) along an axis of `size` texels, texel centres at integers:
    wrapped modulo size ('repeat') or clamped to the edge texels ('clamp')."""
    if clamp:
        if coord > size - 1.0:
            return size - 1, size - 1, 0.0, 0.0
        if coord < 0.0:
            return 0, 0, 0.0, 0.0
        if coord != coord:  # NaN: a NaN weight, in-range reads
            return 0, 0, np.nan, 1.0
    elif not (coord >= 0.0 and coord < size):  # (the modulo only where it changes coord)
        coord = coord - size * np.floor(coord / size)
        # the modulo of a tiny negative number rounds to size itself: that is texel 0
        if coord >= size:
            coord -= size
        if not (coord >= 0.0 and coord < size):  # NaN or infinite: as above
            return 0, 0, np.nan, 1.0
    low = int(coord)
    nxt = low + 1
    if nxt == size:
        nxt = 0 if not clamp else low
    return low, nxt, coord - low, 1.0


@numba.njit(cache=True, nogil=True, inline="always")
def _cell(u, v, height, width, clamp):
    """The four texel rows of a sample at (u, v) in one texture, top-left, top-right,
    bottom-left, bottom-right (relative to its offset), its weights (fx, fy) and their
    slopes d fx / d u and d fy / d v."""
    x0, x1, fx, sx = _axis(u * width - 0.5, width, clamp)
    y0, y1, fy, sy = _axis((1.0 - v) * height - 0.5, height, clamp)
    return (y0 * width + x0, y0 * width + x1, y1 * width + x0, y1 * width + x1, fx, fy,
            sx * width, -sy * height)


@numba.njit(cache=True, nogil=True, inline="always")
def _offset(ids, i, area, total):
    """Sample i's texture offset, or -1 where it has none or it would end past `total`."""
    base = ids[i]
    return base if base >= 0 and base + area <= total else -1


@numba.njit(cache=True, nogil=True, inline="always")
def _weights(weights, gx, gy, fx, fy):
    """The four texels' bilinear weights in the texels' dtype, through `weights` [4] of
    that dtype: float32 products and sums of float32 texels run faster than float64 ones
    (and a float64 weight would promote them)."""
    weights[0], weights[1], weights[2], weights[3] = gy * gx, gy * fx, fy * gx, fy * fx
    return weights[0], weights[1], weights[2], weights[3]


@numba.njit(cache=True, nogil=True, inline="always")
def _blend(out, i, texels, rows, w, nc):
    """out[i] = the four texel rows [4] blended by their weights w [4], nc channels."""
    for ch in range(nc):
        out[i, ch] = (w[0] * texels[rows[0], ch] + w[1] * texels[rows[1], ch]
                      + w[2] * texels[rows[2], ch] + w[3] * texels[rows[3], ch])


@numba.njit(cache=True, nogil=True, inline="always")
def _scatter(acc, g_out, i, rows, w, nc):
    """Sample i's cotangent g_out[i] into the four texel rows of acc by their weights."""
    for ch in range(nc):
        g = g_out[i, ch]
        acc[rows[0], ch] += w[0] * g
        acc[rows[1], ch] += w[1] * g
        acc[rows[2], ch] += w[2] * g
        acc[rows[3], ch] += w[3] * g


@numba.njit(cache=True, nogil=True)
def _chunk(chunk, chunks, n):
    """The sample range [start, stop) of one of `chunks` equal parts."""
    step = (n + chunks - 1) // chunks
    return chunk * step, min(n, (chunk + 1) * step)


@numba.njit(cache=True, nogil=True)
def sample_forward(ids, uv, texels, height, width, clamp, chunks):
    """Bilinear values [M, C] of the samples (module docstring)."""
    out = np.empty((ids.shape[0], texels.shape[1]), texels.dtype)
    sample_forward_into(ids, uv, texels, height, width, clamp, chunks, out)
    return out


@numba.njit(cache=True, nogil=True, parallel=True)
def sample_forward_into(ids, uv, texels, height, width, clamp, chunks, out):
    """sample_forward writing every element of out [M, C]."""
    n, nc = ids.shape[0], texels.shape[1]
    area, total = height * width, texels.shape[0]
    for chunk in prange(chunks):
        weights = np.empty(4, texels.dtype)
        start, stop = _chunk(chunk, chunks, n)
        for i in range(start, stop):
            base = _offset(ids, i, area, total)
            if base < 0:
                for ch in range(nc):
                    out[i, ch] = 0.0
                continue
            t00, t01, t10, t11, fx, fy, _, _ = _cell(uv[i, 0], uv[i, 1], height, width, clamp)
            rows = base + t00, base + t01, base + t10, base + t11
            w = _weights(weights, 1.0 - fx, 1.0 - fy, fx, fy)
            if nc == 3:  # RGB, the common case: a loop of constant length, unrolled
                _blend(out, i, texels, rows, w, 3)
            else:
                _blend(out, i, texels, rows, w, nc)
    return out


@numba.njit(cache=True, nogil=True)
def sample_backward(ids, uv, texels, g_out, height, width, clamp, uv_grad, chunks):
    """Gradients of sample_forward: (g_uv [M, 2], g_texels [T, C]); g_uv is zeros unless
    uv_grad (the texels are then not read)."""
    g_uv = np.empty(uv.shape, uv.dtype)
    g_texels = np.empty(texels.shape, texels.dtype)
    sample_backward_into(ids, uv, texels, g_out, height, width, clamp, uv_grad, chunks, g_uv,
                         g_texels)
    return g_uv, g_texels


@numba.njit(cache=True, nogil=True, parallel=True)
def sample_backward_into(ids, uv, texels, g_out, height, width, clamp, uv_grad, chunks, g_uv,
                         g_texels):
    """sample_backward writing every element of g_uv and g_texels."""
    n, nc = ids.shape[0], texels.shape[1]
    area, total = height * width, texels.shape[0]
    acc = np.zeros((chunks,) + texels.shape, texels.dtype)
    for chunk in prange(chunks):
        weights = np.empty(4, texels.dtype)
        part = acc[chunk]
        start, stop = _chunk(chunk, chunks, n)
        for i in range(start, stop):
            base = _offset(ids, i, area, total)
            if base < 0:
                g_uv[i, 0] = g_uv[i, 1] = 0.0
                continue
            t00, t01, t10, t11, fx, fy, su, sv = _cell(uv[i, 0], uv[i, 1], height, width,
                                                       clamp)
            t00, t01, t10, t11 = base + t00, base + t01, base + t10, base + t11
            gx, gy = 1.0 - fx, 1.0 - fy
            w = _weights(weights, gx, gy, fx, fy)
            if nc == 3:  # as in the forward
                _scatter(part, g_out, i, (t00, t01, t10, t11), w, 3)
            else:
                _scatter(part, g_out, i, (t00, t01, t10, t11), w, nc)
            du = dv = 0.0
            if uv_grad:
                for ch in range(nc):
                    g = g_out[i, ch]
                    a, b = texels[t00, ch], texels[t01, ch]
                    c, d = texels[t10, ch], texels[t11, ch]
                    du += g * (gy * (b - a) + fy * (d - c))
                    dv += g * (gx * (c - a) + fx * (d - b))
            g_uv[i, 0], g_uv[i, 1] = du * su, dv * sv
    _sum_parts(acc, g_texels)


@numba.njit(cache=True, nogil=True, parallel=True)
def _sum_parts(acc, out):
    """out [T, C] = acc [parts, T, C] summed over its parts, texel rows in parallel."""
    for t in prange(acc.shape[1]):
        for ch in range(acc.shape[2]):
            s = acc[0, t, ch]
            for part in range(1, acc.shape[0]):
                s += acc[part, t, ch]
            out[t, ch] = s

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
coordinates and weights are computed in float64, the blend in the texels' dtype.

Every read is in range whatever the UV: a coordinate that is not finite (NaN, or an
infinite one under 'repeat') reads texel 0 of its axis with weight NaN, so the value is
NaN, as in the jax.numpy lookup; an offset whose texture would end past the texels reads
nothing (zeros). Kernels split the samples into blocks (_BLOCK) for `chunks` parts run in
parallel. The forward's parts claim the blocks one at a time from a shared counter: they
end together where the samples that read a texture come first (the compacted active
slots: a fixed split would give one part them all) and where XLA runs other work beside
the kernel (a part whose thread waits for a core takes fewer blocks). The backward's parts
take the blocks in turn (block c, c + chunks, ...), each accumulating the texels' gradient
in a buffer of its own (no races), so that its sums run in the same order at every call.
"""

import numba
import numpy as np
from numba import prange, types
from numba.core import cgutils
from numba.extending import intrinsic

from diffshade.host import numba_cache  # noqa: F401 (numba's cache saves, locked)
from diffshade.host.intrinsics import ROW_LANES, Rows, claim

#: samples per block: a block's cells (texel rows and weights) are computed in one loop
#: over the block, which LLVM vectorizes (several samples per instruction: one at a time,
#: the coordinates' arithmetic took most of the lookup's time), into scratch rows that
#: stay in the L1 cache; then the block is blended or scattered
_BLOCK = 256
#: a block's scratch (_scratch) is three flat buffers of rows _BLOCK long, at offsets that
#: are constant multiples of _BLOCK (so LLVM sees that the rows do not overlap): int32 the
#: four texel rows of each sample (top-left, top-right, bottom-left, bottom-right) and
#: whether it reads a texture (_VALID); in the texels' dtype the four bilinear weights;
#: float64 the weights of the next texels along u and v (_FX, _FY) and their slopes
#: d fx / d u and d fy / d v (_SU, _SV)
_VALID = 4
_FX, _FY, _SU, _SV = 0, 1, 2, 3


@numba.njit(cache=True, nogil=True, inline="always")
def _axis(coord, size, clamp):
    """(index of the texel at or before coord, index of the next one, the next one's
    weight, d weight / d coord) along an axis of `size` texels, texel centres at integers:
    wrapped modulo size ('repeat') or clamped to the edge texels ('clamp'). Selects, no
    branches: the loop over a block vectorizes."""
    fsize = float(size)
    if clamp:
        above, below, nan = coord > fsize - 1.0, coord < 0.0, coord != coord
        c = fsize - 1.0 if above else coord
        c = 0.0 if below | nan else c
        low = int(c)
        nxt = low if (low + 1 == size) | above | below | nan else low + 1
        # NaN: a NaN weight, in-range reads
        return low, nxt, np.nan if nan else c - low, 0.0 if above | below else 1.0
    # the modulo only where it changes coord; that of a tiny negative number rounds to
    # size itself: that is texel 0
    c = coord if (coord >= 0.0) & (coord < fsize) else coord - fsize * np.floor(coord / fsize)
    c = c - fsize if c >= fsize else c
    ok = (c >= 0.0) & (c < fsize)  # else NaN or infinite: as NaN above
    c = c if ok else 0.0
    low = int(c)
    nxt = 0 if low + 1 == size else low + 1
    return low, nxt if ok else low, c - low if ok else np.nan, 1.0


@numba.njit(cache=True, nogil=True, inline="always")
def _cells(ids, uv, height, width, clamp, total, rows, weights, cell):
    """The cells of a block's samples, ids [n] and uv [2 n] (flat: u, v, u, ...), into the
    block's scratch (rows, weights, cell: see _VALID). A sample reads a texture where its
    offset is not -1 and the texture ends within `total` texels; else its rows are 0.
    Returns how many do."""
    area, count = height * width, 0
    for j in range(ids.shape[0]):
        base = ids[j]
        valid = (base >= 0) & (base + area <= total)
        base = base if valid else 0
        x0, x1, fx, sx = _axis(uv[2 * j] * width - 0.5, width, clamp)
        y0, y1, fy, sy = _axis((1.0 - uv[2 * j + 1]) * height - 0.5, height, clamp)
        top, bottom = base + y0 * width, base + y1 * width
        rows[j], rows[_BLOCK + j] = top + x0, top + x1
        rows[2 * _BLOCK + j], rows[3 * _BLOCK + j] = bottom + x0, bottom + x1
        rows[_VALID * _BLOCK + j] = valid
        count += valid
        gx, gy = 1.0 - fx, 1.0 - fy
        weights[j], weights[_BLOCK + j] = gy * gx, gy * fx
        weights[2 * _BLOCK + j], weights[3 * _BLOCK + j] = fy * gx, fy * fx
        cell[_FX * _BLOCK + j], cell[_FY * _BLOCK + j] = fx, fy
        cell[_SU * _BLOCK + j], cell[_SV * _BLOCK + j] = sx * width, -sy * height
    return count


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _block_cells(ids, uv, lo, hi, height, width, clamp, total, scratch):
    """_cells of the samples [lo, hi), with `clamp` a constant in each loop (no branch in
    the loop); uv [M, 2]. Returns how many read a texture."""
    # slices indexed from 0 (an index lo + j could be negative to numba: a wraparound
    # select per read), and the UVs flat (uv[j, 0] strides by a row length known only at
    # run time, which LLVM versions on being 1: the vector loop never ran)
    ids, uv = ids[lo:hi], uv.reshape(-1)[2 * lo:2 * hi]
    rows, weights, cell = scratch
    if clamp:
        return _cells(ids, uv, height, width, True, total, rows, weights, cell)
    return _cells(ids, uv, height, width, False, total, rows, weights, cell)


@numba.njit(cache=True, nogil=True, inline="always")
def _scratch(dtype):
    """A block's scratch for _cells: (rows, weights, cell), see _VALID."""
    return (np.empty(5 * _BLOCK, np.int32), np.empty(4 * _BLOCK, dtype),
            np.empty(4 * _BLOCK, np.float64))


@numba.njit(cache=True, nogil=True, inline="always")
def _corners(scratch, j):
    """Sample j's texel rows (4) and weights (4) from its block's scratch."""
    rows, weights, _ = scratch
    return (rows[j], rows[_BLOCK + j], rows[2 * _BLOCK + j], rows[3 * _BLOCK + j],
            weights[j], weights[_BLOCK + j], weights[2 * _BLOCK + j], weights[3 * _BLOCK + j])


@intrinsic
def _blend_texels(typingctx, texels, a, b, c, d, w0, w1, w2, w3, out, j):
    """out[j] = w0 texels[a] + w1 texels[b] + w2 texels[c] + w3 texels[d] for C <=
    ROW_LANES channels (texels [T, C] and out [n, C] C-contiguous, one float dtype, the
    weights' too), each row one vector (intrinsics.Rows), added in that order, as _blend's
    loop over the channels: the same numbers. (The same for _scatter, a masked store then
    a masked load of the row the next sample adds to, took twice as long as its loop:
    a load that overlaps a masked store waits for it to reach the cache.)"""
    if not (isinstance(texels, types.Array) and isinstance(out, types.Array)
            and texels.dtype in (types.float32, types.float64) and out.dtype == texels.dtype
            and texels.ndim == out.ndim == 2 and texels.layout == out.layout == "C"
            and w0 == w1 == w2 == w3 == texels.dtype):
        return None

    def codegen(context, builder, signature, args):
        texels, a, b, c, d, w0, w1, w2, w3, out, j = args
        kinds = signature.args
        array = context.make_array(kinds[0])(context, builder, texels)
        channels = cgutils.unpack_tuple(builder, array.shape, 2)[1]
        rows = Rows(context, builder, kinds[0].dtype, channels)
        start = lambda at, index: builder.mul(
            context.cast(builder, index, kinds[at], types.int64), channels)
        term = lambda at, index, w: builder.fmul(rows.weight(w, kinds[at + 4]),
                                                 rows.load(array.data, start(at, index)))
        total = builder.fadd(builder.fadd(builder.fadd(term(1, a, w0), term(2, b, w1)),
                                          term(3, c, w2)), term(4, d, w3))
        rows.store(total, context.make_array(kinds[9])(context, builder, out).data,
                   start(10, j))
        return context.get_dummy_value()
    return types.none(texels, a, b, c, d, w0, w1, w2, w3, out, j), codegen


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _blend(texels, scratch, out, nc):
    """out [n, nc] = each sample's four texel rows blended by their weights (0 where it
    reads no texture); a row of up to ROW_LANES channels as one vector (_blend_texels)."""
    valid = scratch[0][_VALID * _BLOCK:]
    for j in range(out.shape[0]):
        a, b, c, d, w0, w1, w2, w3 = _corners(scratch, j)
        if nc <= ROW_LANES and valid[j]:
            _blend_texels(texels, a, b, c, d, w0, w1, w2, w3, out, j)
            continue
        for ch in range(nc):
            value = (w0 * texels[a, ch] + w1 * texels[b, ch] + w2 * texels[c, ch]
                     + w3 * texels[d, ch])
            out[j, ch] = value if valid[j] else 0.0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _scatter(acc, g_out, scratch, nc):
    """Each sample's cotangent g_out [n, nc] into its four texel rows of acc by their
    weights (none where it reads no texture)."""
    valid = scratch[0][_VALID * _BLOCK:]
    for j in range(g_out.shape[0]):
        if not valid[j]:
            continue
        a, b, c, d, w0, w1, w2, w3 = _corners(scratch, j)
        for ch in range(nc):
            g = g_out[j, ch]
            acc[a, ch] += w0 * g
            acc[b, ch] += w1 * g
            acc[c, ch] += w2 * g
            acc[d, ch] += w3 * g


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _uv_gradient(texels, g_out, scratch, g_uv):
    """g_uv [n, 2]: the gradient of each sample's value (cotangent g_out [n, C]) with
    respect to its UV (0 where it reads no texture)."""
    valid, cell = scratch[0][_VALID * _BLOCK:], scratch[2]
    for j in range(g_uv.shape[0]):
        a, b, c, d = _corners(scratch, j)[:4]
        fx, fy = cell[_FX * _BLOCK + j], cell[_FY * _BLOCK + j]
        gx, gy = 1.0 - fx, 1.0 - fy
        du = dv = 0.0
        for ch in range(texels.shape[1]):
            g = g_out[j, ch]
            t00, t01, t10, t11 = texels[a, ch], texels[b, ch], texels[c, ch], texels[d, ch]
            du += g * (gy * (t01 - t00) + fy * (t11 - t10))
            dv += g * (gx * (t10 - t00) + fx * (t11 - t01))
        g_uv[j, 0] = du * cell[_SU * _BLOCK + j] if valid[j] else 0.0
        g_uv[j, 1] = dv * cell[_SV * _BLOCK + j] if valid[j] else 0.0


@numba.njit(cache=True, nogil=True)
def _block(block, n):
    """The sample range [lo, hi) of block number `block` of n samples."""
    return block * _BLOCK, min(n, (block + 1) * _BLOCK)


def sample_forward(ids, uv, texels, height, width, clamp, chunks):
    """Bilinear values [M, C] of the samples (module docstring)."""
    out = np.empty((ids.shape[0], texels.shape[1]), texels.dtype)
    sample_forward_into(ids, uv, texels, height, width, clamp, chunks, out)
    return out


@numba.njit(cache=True, nogil=True, parallel=True)
def sample_forward_into(ids, uv, texels, height, width, clamp, chunks, out):
    """sample_forward writing every element of out [M, C]."""
    n, nc = ids.shape[0], texels.shape[1]
    blocks, counter = (n + _BLOCK - 1) // _BLOCK, np.empty(1, np.int64)
    counter[0] = 0
    for _ in prange(chunks):
        scratch = _scratch(texels.dtype)
        block = claim(counter)
        while block < blocks:
            lo, hi = _block(block, n)
            if not _block_cells(ids, uv, lo, hi, height, width, clamp, texels.shape[0],
                                scratch):  # none reads a texture (the compacted tail)
                out[lo:hi] = 0.0
            elif nc == 3:  # RGB, the common case: a loop of constant length, unrolled
                _blend(texels, scratch, out[lo:hi], 3)
            else:
                _blend(texels, scratch, out[lo:hi], nc)
            block = claim(counter)
    return out


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
    acc = np.empty((chunks,) + texels.shape, texels.dtype)
    for chunk in prange(chunks):
        part, scratch = acc[chunk], _scratch(texels.dtype)
        part[:] = 0.0  # here, not before the loop: the parts in parallel
        # dealt in turn, not claimed: which part sums which samples stays fixed, so the
        # texels' gradient is the same bit for bit from call to call
        for block in range(chunk, (n + _BLOCK - 1) // _BLOCK, chunks):
            lo, hi = _block(block, n)
            # count: how many of the block's samples read a texture (none in the
            # compacted tail: nothing to scatter)
            count = _block_cells(ids, uv, lo, hi, height, width, clamp, texels.shape[0],
                                 scratch)
            if count and nc == 3:  # as in the forward
                _scatter(part, g_out[lo:hi], scratch, 3)
            elif count:
                _scatter(part, g_out[lo:hi], scratch, nc)
            if uv_grad and count:
                _uv_gradient(texels, g_out[lo:hi], scratch, g_uv[lo:hi])
            else:
                g_uv[lo:hi] = 0.0
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

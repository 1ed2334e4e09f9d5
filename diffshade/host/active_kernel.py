"""The compiled kernels of diffshade.shading.compact: the positions of the first `capacity`
True entries of a boolean mask and how many there are (`first_active`, behind
compact.active_indices), the scatter of gathered rows back into a zeroed array
(`put_rows`, the transpose of compact.take_rows), and the sums of rows per group of
consecutive indices (`sum_rows`: a soft render's weighted colours per pixel).

`first_active` is one pass over the mask, eight entries at a time, written for numba:
XLA's own `jnp.nonzero` (a cumulative sum and a scatter) costs more than lighting the
active slots it finds. `put_rows` zeroes and scatters in parallel chunks, where XLA on CPU
runs the transpose of a gather (a zero fill and a scatter-add) in one thread; `sum_rows`
is one pass in the calling thread, where XLA's scatter-add costs several times as much.
Each is called from NumPy on the callback path and through its FFI handler (the `_into`
form, writing into XLA's buffers) under jit.
"""

import numba
import numpy as np
from llvmlite import ir
from numba import prange, types
from numba.extending import intrinsic

from diffshade.host import numba_cache  # noqa: F401 (numba's cache saves, locked)
from diffshade.host.intrinsics import compress, popcount


@numba.njit(cache=True, nogil=True)
def first_active(mask, capacity):
    """(indices [capacity] int32 of the first `capacity` True entries of mask [N], padded
    with N; count [] int32 of all True entries)."""
    idx, count = np.empty(capacity, np.int32), np.empty(1, np.int32)
    first_active_into(mask, idx, count)
    return idx, count[0]


@intrinsic
def _active8(typingctx, mask, start, idx, found):
    """Write the positions among start..start + 7 where mask [N] bool is True to idx [C]
    int32 from index `found`, in order, as vector operations without branches (a
    compress); returns found plus their number. It writes 8 entries from found whatever
    that number (the caller keeps found + 8 <= C; those past the new found are
    overwritten next)."""
    if not (isinstance(mask, types.Array) and mask.dtype == types.boolean and mask.ndim == 1
            and mask.layout == "C" and isinstance(idx, types.Array)
            and idx.dtype == types.int32 and idx.ndim == 1 and idx.layout == "C"):
        return None

    def codegen(context, builder, signature, args):
        mask_type, _, idx_type, _ = signature.args
        mask, start, idx, found = args
        start = context.cast(builder, start, signature.args[1], types.int64)
        found = context.cast(builder, found, signature.args[3], types.int64)
        byte, word = ir.IntType(8), ir.IntType(32)
        lanes = lambda element: ir.PointerType(ir.VectorType(element, 8))
        data = context.make_array(mask_type)(context, builder, mask).data
        flags = builder.load(builder.bitcast(builder.gep(data, [start]), lanes(byte)), align=1)
        on = builder.icmp_unsigned("!=", flags, ir.Constant(flags.type, [0] * 8))
        first = builder.insert_element(ir.Constant(ir.VectorType(word, 8), None),
                                       builder.trunc(start, word), ir.Constant(word, 0))
        splat = builder.shuffle_vector(first, ir.Constant(first.type, None),
                                       ir.Constant(ir.VectorType(word, 8), [0] * 8))
        positions = builder.add(splat, ir.Constant(splat.type, list(range(8))))
        out = context.make_array(idx_type)(context, builder, idx).data
        builder.store(compress(builder, positions, on),
                      builder.bitcast(builder.gep(out, [found]), lanes(word)), align=4)
        return builder.add(found, popcount(builder, on))
    return types.int64(mask, start, idx, found), codegen


@numba.njit(cache=True, nogil=True)
def first_active_into(mask, idx, count):
    """first_active writing into idx [capacity] and count [1] (the FFI handler's form):
    eight entries at a time (_active8) while eight more positions fit, then one at a
    time (a branch per entry was mispredicted wherever the mask changes)."""
    n = mask.shape[0]
    found, start = 0, 0
    while start + 8 <= n and found + 8 <= idx.shape[0]:
        found = _active8(mask, start, idx, found)
        start += 8
    for i in range(start, n):
        if mask[i]:
            if found < idx.shape[0]:
                idx[found] = i
            found += 1
    for i in range(min(found, idx.shape[0]), idx.shape[0]):
        idx[i] = n
    count[0] = found


def put_rows(idx, rows, count, clip, chunks):
    """out [count, D]: rows [C, D] put at out[idx[i]] (indices in [0, count) distinct),
    zeros elsewhere. A row whose index is out of range is dropped, or with `clip` added to
    the nearest end row (out[0] or out[count - 1]), as the transpose of a gather with
    clipped indices."""
    out = np.empty((count, rows.shape[1]), rows.dtype)
    put_rows_into(idx, rows, clip, chunks, out)
    return out


@numba.njit(cache=True, nogil=True, inline="always")
def _part(chunk, chunks, n):
    """The range [start, stop) of one of `chunks` equal parts of n."""
    step = (n + chunks - 1) // chunks
    return chunk * step, min(n, (chunk + 1) * step)


@numba.njit(cache=True, nogil=True, parallel=True)
def put_rows_into(idx, rows, clip, chunks, out):
    """put_rows writing every element of out [N, D], in `chunks` parallel parts."""
    n, width = out.shape
    for chunk in prange(chunks):
        start, stop = _part(chunk, chunks, n)
        out[start:stop] = 0.0
    # the rows of clipped indices, summed per part: they may share their end row
    ends = np.zeros((chunks, 2, width), rows.dtype)
    for chunk in prange(chunks):
        start, stop = _part(chunk, chunks, idx.shape[0])
        for i in range(start, stop):
            j = idx[i]
            if 0 <= j < n:
                for c in range(width):
                    out[j, c] = rows[i, c]
            elif clip:
                for c in range(width):
                    ends[chunk, 0 if j < 0 else 1, c] += rows[i, c]
    if n == 0 or not clip:
        return
    for chunk in range(chunks):
        for c in range(width):
            out[0, c] += ends[chunk, 0, c]
            out[n - 1, c] += ends[chunk, 1, c]


def sum_rows(idx, rows, count, group):
    """out [count, 3]: out[p] = the sum of the rows [C, 3] whose idx // group == p, for idx
    [C] ascending (active_indices' order); rows of other entries (the padding) are dropped.
    The transpose of a gather of rows by idx // group."""
    out = np.empty((count, 3), rows.dtype)
    sum_rows_into(idx, rows, group, out)
    return out


@numba.njit(cache=True, nogil=True)
def sum_rows_into(idx, rows, group, out):
    """sum_rows writing every element of out [P, 3]: one pass over the rows (idx is
    ascending), in the calling thread. A parallel form (a part of the pixels per thread,
    its first row found by bisection) took longer in the render, where waking the threads
    from the XLA thread that calls it costs more than the pass; the sums, in index order,
    are the same bit for bit either way."""
    i = np.searchsorted(idx, 0)
    for p in range(out.shape[0]):
        end = (p + 1) * group
        a0, a1, a2 = rows.dtype.type(0.0), rows.dtype.type(0.0), rows.dtype.type(0.0)
        while i < idx.shape[0] and idx[i] < end:
            a0 += rows[i, 0]
            a1 += rows[i, 1]
            a2 += rows[i, 2]
            i += 1
        out[p, 0], out[p, 1], out[p, 2] = a0, a1, a2

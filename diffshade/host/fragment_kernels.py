"""Compiled forward and backward kernels of the per-fragment geometry and interpolation.

raster.py and interpolate.py wrap these in JAX primitives (hostop.py, through the host
callback of hostcall.py), nvdiffrast-style: the per-fragment work and its hand-written
gradient run as one numba loop each, and JAX differentiates only the cheap per-face
setup around them (edge coefficients, screen positions, the gather of vertex attributes to
face corners). On XLA CPU, JAX's derivative of the same per-fragment expressions runs
several times slower than these loops (docs/soft-rasterization.md, "How it works").

Conventions: P pixels (row-major, H x W; the geometry kernels take whole rows, P = R * W),
K slots per pixel, F faces. `ids` [P, K] int32 face ids (-1 = empty). Empty slots produce
zeros and receive no gradient. The geometry kernels compute in float64 (the pixel
coordinates are float64 and float32 inputs are widened exactly) and return the inputs'
dtype; the interpolation kernels compute in the inputs' dtype. The geometry forward also
returns each fragment's nearest edge (int8), which its backward takes back: the backward
recomputes the distance's gradient from that one edge instead of measuring all three
again, and the barycentrics only where their cotangent is not 0 (a fragment of weight 0
still counts in the coverage, through its distance). Kernels split the pixels
into `chunks` parts run in parallel (`chunks()`); backward kernels accumulate per-face
gradients in one buffer per part (no races), summed at the end.

Every division is `safe_div` semantics (numerics.py): num / den where |den| > tiny,
0 (and zero gradient) elsewhere. The geometry kernels multiply by reciprocals instead of
dividing (`_inv`): one per fragment (the soft forward needs only the sign of its first
sum, _soft_bary), and per face those of the corners' W and of the edges' squared
lengths, because a division costs many times a multiplication and a fragment would
otherwise need a dozen or more. What they read of a face sits in one
float64 row (`_face_table`, built once per call), and the pixel coordinates come from
per-row and per-column tables (`_pixel_coords`).
"""

import numba
import numpy as np
from llvmlite import ir
from numba import prange, types
from numba.core import cgutils
from numba.extending import intrinsic

from diffshade.host import numba_cache  # noqa: F401 (numba's cache saves, locked)
from diffshade.host.intrinsics import ROW_LANES, Rows, splat


def chunks() -> int:
    """How many parts the pixels are split into: one per numba thread."""
    return numba.get_num_threads()


@numba.njit(cache=True, nogil=True, inline="always")
def _inv(den, tiny):
    """1 / den where |den| > tiny, else 0: x * _inv(d) is safe_div(x, d)."""
    return 1.0 / den if abs(den) > tiny else 0.0


#: a row of _face_table: the edge coefficients [3, 3] (row-major) at _COEFFS, the corners'
#: clip W [3] at _CW and their reciprocals [3] at _INV_W, the corners' eye-space depth [3]
#: at _CZ; then the edges (edge i from corner i to corner i+1 mod 3) lane by lane, so that
#: _edge_dist2 reads each quantity of the three as one vector of 4 doubles: from _EDGES,
#: _LANES values (lane i = edge i, the last lane 0) of each of _EDGE_FIELDS: the edges'
#: start x, start y, vector x, vector y (e = b - a) and e / |e|^2 (x, y). Values 18 and 19
#: are 0, padding: the edges start 160 bytes into a row of 44 doubles (352 bytes, a
#: multiple of 32), so where the table starts on a 32-byte boundary (numba allocates it
#: so) no vector read crosses a cache line
_COEFFS, _CW, _INV_W, _CZ, _EDGES, _LANES, _EDGE_FIELDS, _TABLE_WIDTH = (0, 9, 12, 15, 20, 4,
                                                                         6, 44)


@numba.njit(cache=True, nogil=True)
def _face_table(corner_w, corner_z, coeffs, scr, tiny):
    """Per face, what the kernels read of it, in one float64 row (see _TABLE_WIDTH): [F,
    _TABLE_WIDTH]. Reciprocals by _inv; (ex, ey) computed in the dtype of scr, as the
    kernels once did per fragment. A fragment reads one row instead of four arrays, with
    no conversion from float32 nor subtraction left to do."""
    nfaces = corner_w.shape[0]
    table = np.empty((nfaces, _TABLE_WIDTH), np.float64)
    for f in range(nfaces):
        for i in range(3):
            for j in range(3):
                table[f, _COEFFS + 3 * i + j] = coeffs[f, i, j]
            table[f, _CW + i] = corner_w[f, i]
            table[f, _CZ + i] = corner_z[f, i]
            table[f, _INV_W + i] = _inv(corner_w[f, i], tiny)
            j = (i + 1) % 3
            ex, ey = scr[f, j, 0] - scr[f, i, 0], scr[f, j, 1] - scr[f, i, 1]
            inv = _inv(ex * ex + ey * ey, tiny)
            table[f, _EDGES + i] = scr[f, i, 0]
            table[f, _EDGES + _LANES + i] = scr[f, i, 1]
            table[f, _EDGES + 2 * _LANES + i] = ex
            table[f, _EDGES + 3 * _LANES + i] = ey
            table[f, _EDGES + 4 * _LANES + i] = ex * inv
            table[f, _EDGES + 5 * _LANES + i] = ey * inv
        table[f, _CZ + 3:_EDGES] = 0.0
        for field in range(_EDGE_FIELDS):
            table[f, _EDGES + field * _LANES + 3] = 0.0
    return table


@numba.njit(cache=True, nogil=True)
def _pixel_coords(width, height):
    """Per column (NDC x [W], pixel-centre px [W]) and per row (NDC y [H], py [H]): once
    per call, not a division and a modulo per pixel."""
    cols, rows = np.arange(width), np.arange(height)
    return ((2.0 * cols + 1.0) / width - 1.0, cols + 0.5, 1.0 - (2.0 * rows + 1.0) / height,
            rows + 0.5)


@numba.njit(cache=True, nogil=True, inline="always")
def _face(table, f, x, y):
    """Edge functions e_i = coeffs[f, i] . (x, y, 1) and the corners' clip W (the
    constant term added first: two FMAs per edge where a kernel fuses them)."""
    e0 = table[f, _COEFFS] * x + (table[f, _COEFFS + 1] * y + table[f, _COEFFS + 2])
    e1 = table[f, _COEFFS + 3] * x + (table[f, _COEFFS + 4] * y + table[f, _COEFFS + 5])
    e2 = table[f, _COEFFS + 6] * x + (table[f, _COEFFS + 7] * y + table[f, _COEFFS + 8])
    return e0, e1, e2, table[f, _CW], table[f, _CW + 1], table[f, _CW + 2]


@numba.njit(cache=True, nogil=True, inline="always")
def _hard_bary(e0, e1, e2, tiny):
    """Hard mode's (perspective-correct) barycentrics b = e / sum(e), and 1 / sum(e)."""
    inv = _inv(e0 + e1 + e2, tiny)
    return e0 * inv, e1 * inv, e2 * inv, inv


@numba.njit(cache=True, nogil=True, inline="always")
def _soft_bary(e0, e1, e2, w0, w1, w2, table, f, tiny):
    """Soft mode's barycentrics: screen-space s = e w / sum(e w) clamped to >= 0, then
    corrected for perspective, b = (c / w) / sum(c / w), with one division: b is
    unchanged when s is scaled by |sum(e w)| (q below, scaled alike), so s takes only the
    sign of 1 / sum(e w) (0 where _inv gives 0), and 1 / sum(q) is 0 where the unscaled
    sum(q) <= tiny, as _inv. Returns (s / |1 / sum(e w)|, b), each as 3 scalars: s has
    the signs of the screen-space barycentrics."""
    ew0, ew1, ew2 = e0 * w0, e1 * w1, e2 * w2
    den = ew0 + ew1 + ew2
    sign = 1.0 if den > tiny else -1.0 if den < -tiny else 0.0
    s0, s1, s2 = ew0 * sign, ew1 * sign, ew2 * sign
    q0 = max(s0, 0.0) * table[f, _INV_W + 0]
    q1 = max(s1, 0.0) * table[f, _INV_W + 1]
    q2 = max(s2, 0.0) * table[f, _INV_W + 2]
    sum_q = q0 + q1 + q2
    inv_q = 1.0 / sum_q if abs(sum_q) > tiny * abs(den) else 0.0
    return s0, s1, s2, q0 * inv_q, q1 * inv_q, q2 * inv_q


@numba.njit(cache=True, nogil=True, inline="always")
def _segment(px, py, table, f, i):
    """(squared distance, t, dx, dy) from p to edge i of face f (_face_table):
    d = p - a - t e."""
    ax, ay = table[f, _EDGES + i], table[f, _EDGES + _LANES + i]
    ex, ey = table[f, _EDGES + 2 * _LANES + i], table[f, _EDGES + 3 * _LANES + i]
    t = min(max((px - ax) * table[f, _EDGES + 4 * _LANES + i]
                + (py - ay) * table[f, _EDGES + 5 * _LANES + i], 0.0), 1.0)
    dx, dy = px - ax - t * ex, py - ay - t * ey
    return dx * dx + dy * dy, t, dx, dy


@intrinsic
def _edge_dist2(typingctx, table, f, px, py):
    """The squared distances (d0, d1, d2) from p to the three edges of face f, each as
    _segment computes it (the same operations in the same order, so the same numbers), the
    three side by side in one vector of 4 doubles (_face_table's edge lanes): one vector
    operation where there were three scalar ones. t = min(max(v, 0), 1) as selects that
    keep a NaN, as numba's min and max do."""
    if not (isinstance(table, types.Array) and table.dtype == types.float64
            and table.ndim == 2 and table.layout == "C" and px == py == types.float64):
        return None

    def codegen(context, builder, signature, args):
        table, f, px, py = args
        i32, i64, vector = ir.IntType(32), ir.IntType(64), ir.VectorType(ir.DoubleType(), 4)
        f = context.cast(builder, f, signature.args[1], types.int64)
        data = context.make_array(signature.args[0])(context, builder, table).data
        row = builder.gep(data, [builder.mul(f, ir.Constant(i64, _TABLE_WIDTH))])

        def field(number):
            at = builder.gep(row, [ir.Constant(i64, _EDGES + number * _LANES)])
            return builder.load(builder.bitcast(at, ir.PointerType(vector)), align=8)

        # fastmath "contract", as the kernel's own arithmetic (_FUSED)
        mul = lambda a, b: builder.fmul(a, b, flags=("contract",))
        add = lambda a, b: builder.fadd(a, b, flags=("contract",))
        sub = lambda a, b: builder.fsub(a, b, flags=("contract",))
        ax, ay, ex, ey, ix, iy = (field(number) for number in range(_EDGE_FIELDS))
        rx, ry = sub(splat(builder, px, 4), ax), sub(splat(builder, py, 4), ay)
        t = add(mul(rx, ix), mul(ry, iy))
        zero, one = ir.Constant(vector, [0.0] * 4), ir.Constant(vector, [1.0] * 4)
        t = builder.select(builder.fcmp_ordered("<", t, zero), zero, t)
        t = builder.select(builder.fcmp_ordered(">", t, one), one, t)
        dx, dy = sub(rx, mul(t, ex)), sub(ry, mul(t, ey))
        d = add(mul(dx, dx), mul(dy, dy))
        return context.make_tuple(builder, signature.return_type, [
            builder.extract_element(d, ir.Constant(i32, lane)) for lane in range(3)])
    return types.UniTuple(types.float64, 3)(table, f, px, py), codegen


@numba.njit(cache=True, nogil=True, inline="always")
def _nearest_edge(px, py, table, f):
    """(edge index i: from corner i to corner i+1 mod 3, squared distance) of the nearest
    edge; ties go to the first (as jnp.where(a <= b, a, b)). Selects, not branches: which
    edge is nearest changes from fragment to fragment, past any branch predictor."""
    d0, d1, d2 = _edge_dist2(table, f, px, py)
    first = d0 <= d1
    i, d = (0, d0) if first else (1, d1)
    last = d2 < d
    return (2 if last else i), (d2 if last else d)


@numba.njit(cache=True, nogil=True)
def _chunk(chunk, chunks, npix):
    """The pixel range [start, stop) of one of `chunks` equal parts."""
    step = (npix + chunks - 1) // chunks
    return chunk * step, min(npix, (chunk + 1) * step)


#: fragments per block where the parts take blocks in turn (_dealt): the compacted active
#: slots are padded at their end, so equal ranges would give the first part the most work
#: (interpolate_backward; interpolate_at gained nothing from it and keeps equal ranges)
_DEALT = 1024


@numba.njit(cache=True, nogil=True, inline="always")
def _dealt(block, n):
    """The range [start, stop) of block number `block` of n fragments; part c of `chunks`
    takes blocks c, c + chunks, c + 2 chunks, ..."""
    return block * _DEALT, min(n, (block + 1) * _DEALT)


def geometry_forward(ids, corner_w, corner_z, coeffs, scr, width, height, soft, tiny, chunks):
    """bary [P, K, 3], depth [P, K] = bary . corner_z, the signed squared pixel distance
    [P, K] (soft; zeros in hard mode) and the nearest edge [P, K] int8 (soft; zeros in hard
    mode and empty slots), which the backward reads instead of searching the three edges
    again: its index i (the edge from corner i to corner i+1 mod 3), plus OUTSIDE where
    the distance was negated.

    corner_w: [F, 3] clip W per corner; corner_z: [F, 3] eye-space depth per corner;
    coeffs: [F, 3, 3]; scr: [F, 3, 2] pixel positions. Hard: b = e / sum(e). Soft: see
    _soft_bary; the distance is positive inside (all screen-space barycentrics >= 0).
    """
    npix, k = ids.shape
    dtype = coeffs.dtype
    # np.empty, every element written: zeroing first would write every output twice
    bary = np.empty((npix, k, 3), dtype)
    depth = np.empty((npix, k), dtype)
    dist = np.empty((npix, k), dtype)
    edge = np.empty((npix, k), np.int8)
    geometry_forward_into(ids, corner_w, corner_z, coeffs, scr, width, height, soft, tiny,
                          chunks, bary, depth, dist, edge)
    return bary, depth, dist, edge


#: geometry_forward's edge code of a pixel outside its triangle (added to the edge index)
OUTSIDE = 4


#: the forward's arithmetic may fuse a multiplication and an addition into one FMA (one
#: rounding, not two; in float64, before the results round to their dtype)
_FUSED = {"contract"}


@numba.njit(cache=True, nogil=True, parallel=True, error_model="numpy", fastmath=_FUSED)
def geometry_forward_into(ids, corner_w, corner_z, coeffs, scr, width, height, soft, tiny,
                          chunks, bary, depth, dist, edge):
    """geometry_forward writing every element of bary, depth, dist and edge (as XLA's
    buffers given by an FFI call, ffi.py)."""
    npix, k = ids.shape
    table = _face_table(corner_w, corner_z, coeffs, scr, tiny)
    xs, pxs, ys, pys = _pixel_coords(width, height)
    for chunk in prange(chunks):
        start, stop = _chunk(chunk, chunks, npix // width)  # whole rows
        # a batch of B images arrives as one of B * height rows (hostop.py)
        row, col = start % height, -1
        for pixel in range(start * width, stop * width):
            col += 1
            if col == width:
                row, col = (row + 1) % height, 0
            x, y, px, py = xs[col], ys[row], pxs[col], pys[row]
            for slot in range(k):
                f = ids[pixel, slot]
                if f < 0:
                    bary[pixel, slot, 0] = bary[pixel, slot, 1] = bary[pixel, slot, 2] = 0.0
                    depth[pixel, slot] = dist[pixel, slot] = 0.0
                    edge[pixel, slot] = 0
                    continue
                e0, e1, e2, w0, w1, w2 = _face(table, f, x, y)
                if not soft:
                    dist[pixel, slot] = 0.0
                    edge[pixel, slot] = 0
                    b0, b1, b2, _ = _hard_bary(e0, e1, e2, tiny)
                else:
                    s0, s1, s2, b0, b1, b2 = _soft_bary(e0, e1, e2, w0, w1, w2, table, f,
                                                        tiny)
                    i, d2 = _nearest_edge(px, py, table, f)
                    inside = (s0 >= 0.0) & (s1 >= 0.0) & (s2 >= 0.0)
                    dist[pixel, slot] = d2 if inside else -d2
                    edge[pixel, slot] = i if inside else i + OUTSIDE
                bary[pixel, slot, 0], bary[pixel, slot, 1], bary[pixel, slot, 2] = b0, b1, b2
                depth[pixel, slot] = (b0 * table[f, _CZ] + b1 * table[f, _CZ + 1]
                                      + b2 * table[f, _CZ + 2])


#: geometry_backward's per-face accumulator row: the gradients of corner_w [3] at _W,
#: corner_z [3] at _Z, coeffs [3, 3] at _C (row-major), scr [3, 2] at _S
_W, _Z, _C, _S, _ACC_WIDTH = 0, 3, 6, 15, 21


@numba.njit(cache=True, nogil=True, inline="always")
def _dist_grad(acc, chunk, f, px, py, table, g_m, code):
    """Accumulate the gradient g_m of the signed squared distance (geometry_forward's
    `dist`, of nearest edge `code`) into the corners' screen positions:
    d |d|^2 = -2 d . ((1 - t) da + t db); t drops out (it minimizes |d|^2 inside [0, 1] and
    is constant where clamped)."""
    i = code % OUTSIDE
    _, t, dx, dy = _segment(px, py, table, f, i)
    j = (i + 1) % 3
    g_m = -2.0 * g_m if code < OUTSIDE else 2.0 * g_m
    acc[chunk, f, _S + 2 * i] += g_m * (1.0 - t) * dx
    acc[chunk, f, _S + 1 + 2 * i] += g_m * (1.0 - t) * dy
    acc[chunk, f, _S + 2 * j] += g_m * t * dx
    acc[chunk, f, _S + 1 + 2 * j] += g_m * t * dy


def geometry_backward(ids, corner_w, corner_z, coeffs, scr, width, height, soft, tiny, chunks,
                      edge, g_bary, g_depth, g_dist):
    """Gradients of geometry_forward: (g_w [F, 3], g_z [F, 3], g_coeffs [F, 3, 3],
    g_scr [F, 3, 2]); edge: geometry_forward's nearest edges [P, K] (read in soft mode)."""
    nfaces, dtype = coeffs.shape[0], coeffs.dtype
    out_w, out_z = np.empty((nfaces, 3), dtype), np.empty((nfaces, 3), dtype)
    out_coeffs, out_scr = np.empty((nfaces, 3, 3), dtype), np.empty((nfaces, 3, 2), dtype)
    geometry_backward_into(ids, corner_w, corner_z, coeffs, scr, width, height, soft, tiny,
                           chunks, edge, g_bary, g_depth, g_dist, out_w, out_z, out_coeffs,
                           out_scr)
    return out_w, out_z, out_coeffs, out_scr


#: geometry_backward gathers the fragments whose barycentrics (or depth) have a cotangent
#: into blocks of up to _BLOCK, and computes their gradients in one loop over the block
#: (_bary_block), which LLVM vectorizes: several fragments per instruction, where one
#: fragment at a time is a chain of dependent operations (two divisions among them). A
#: block's rows (_ROWS of them, float64) take 22 KB: they stay in a 32 KB L1 data cache
#: (blocks of 512 ran a third slower than 128 or 256 on a 48 KB one)
_BLOCK = 128
#: the rows of a block, each _BLOCK long, in one flat float64 buffer (so that their
#: offsets are constants, which LLVM tells apart without run-time overlap checks): per
#: fragment the edge functions e [3] at _E, the corners' clip W [3] at _BW and their
#: reciprocals [3] at _BINV_W, the barycentrics' cotangent (the depth's added) [3] at _GB,
#: the depth's cotangent at _GZ; _bary_block writes the gradients of W [3] at _GW, of the
#: corners' depth [3] at _GZS and of e [3] at _GE
_E, _BW, _BINV_W, _GB, _GZ, _GW, _GZS, _GE, _ROWS = 0, 3, 6, 9, 12, 13, 16, 19, 22


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _bary_block(n, block, soft, tiny):
    """The barycentrics' (and depth's) gradients of the first n fragments of a block (see
    _ROWS), as geometry_forward computes them: b = e / sum(e) (hard), or _soft_bary. A loop
    without calls or early exits, one per mode, so that it vectorizes (divisions as
    _inv: the guard is a select)."""
    if not soft:
        for i in range(n):
            e0, e1, e2 = block[_E * _BLOCK + i], block[(_E + 1) * _BLOCK + i], block[
                (_E + 2) * _BLOCK + i]
            gb0, gb1, gb2 = block[_GB * _BLOCK + i], block[(_GB + 1) * _BLOCK + i], block[
                (_GB + 2) * _BLOCK + i]
            g_z = block[_GZ * _BLOCK + i]
            den = e0 + e1 + e2
            inv_e = 1.0 / den if abs(den) > tiny else 0.0
            b0, b1, b2 = e0 * inv_e, e1 * inv_e, e2 * inv_e
            dot = gb0 * b0 + gb1 * b1 + gb2 * b2
            block[_GW * _BLOCK + i] = 0.0
            block[(_GW + 1) * _BLOCK + i] = 0.0
            block[(_GW + 2) * _BLOCK + i] = 0.0
            block[_GZS * _BLOCK + i] = b0 * g_z
            block[(_GZS + 1) * _BLOCK + i] = b1 * g_z
            block[(_GZS + 2) * _BLOCK + i] = b2 * g_z
            block[_GE * _BLOCK + i] = (gb0 - dot) * inv_e
            block[(_GE + 1) * _BLOCK + i] = (gb1 - dot) * inv_e
            block[(_GE + 2) * _BLOCK + i] = (gb2 - dot) * inv_e
        return
    for i in range(n):
        e0, e1, e2 = block[_E * _BLOCK + i], block[(_E + 1) * _BLOCK + i], block[
            (_E + 2) * _BLOCK + i]
        w0, w1, w2 = block[_BW * _BLOCK + i], block[(_BW + 1) * _BLOCK + i], block[
            (_BW + 2) * _BLOCK + i]
        iw0, iw1, iw2 = block[_BINV_W * _BLOCK + i], block[(_BINV_W + 1) * _BLOCK + i], block[
            (_BINV_W + 2) * _BLOCK + i]
        gb0, gb1, gb2 = block[_GB * _BLOCK + i], block[(_GB + 1) * _BLOCK + i], block[
            (_GB + 2) * _BLOCK + i]
        g_z = block[_GZ * _BLOCK + i]
        # _soft_bary: s = e w / sum(e w); q = max(s, 0) / w; b = q / sum(q)
        den = e0 * w0 + e1 * w1 + e2 * w2
        inv_s = 1.0 / den if abs(den) > tiny else 0.0
        s0, s1, s2 = e0 * w0 * inv_s, e1 * w1 * inv_s, e2 * w2 * inv_s
        q0, q1, q2 = max(s0, 0.0) * iw0, max(s1, 0.0) * iw1, max(s2, 0.0) * iw2
        den = q0 + q1 + q2
        inv_q = 1.0 / den if abs(den) > tiny else 0.0
        b0, b1, b2 = q0 * inv_q, q1 * inv_q, q2 * inv_q
        # _softmax_like_grad through b = q / sum(q), then through s = e w / sum(e w),
        # where s > 0 (no gradient through the clamp)
        dot = gb0 * b0 + gb1 * b1 + gb2 * b2
        gs0, gs1, gs2 = (gb0 - dot) * inv_q * iw0, (gb1 - dot) * inv_q * iw1, (
            gb2 - dot) * inv_q * iw2
        h0 = gs0 if s0 > 0.0 else 0.0
        h1 = gs1 if s1 > 0.0 else 0.0
        h2 = gs2 if s2 > 0.0 else 0.0
        dot = h0 * s0 + h1 * s1 + h2 * s2
        gt0, gt1, gt2 = (h0 - dot) * inv_s, (h1 - dot) * inv_s, (h2 - dot) * inv_s
        # w enters through q (q_i = max(s_i, 0) / w_i) and through e w
        block[_GW * _BLOCK + i] = gt0 * e0 - gs0 * q0
        block[(_GW + 1) * _BLOCK + i] = gt1 * e1 - gs1 * q1
        block[(_GW + 2) * _BLOCK + i] = gt2 * e2 - gs2 * q2
        block[_GZS * _BLOCK + i] = b0 * g_z
        block[(_GZS + 1) * _BLOCK + i] = b1 * g_z
        block[(_GZS + 2) * _BLOCK + i] = b2 * g_z
        block[_GE * _BLOCK + i] = gt0 * w0
        block[(_GE + 1) * _BLOCK + i] = gt1 * w1
        block[(_GE + 2) * _BLOCK + i] = gt2 * w2


@numba.njit(cache=True, nogil=True, inline="always")
def _gather(block, n, table, f, x, y, gb0, gb1, gb2, g_z):
    """Fragment n of a block (_ROWS): its face's edge functions at (x, y), corners' W and
    reciprocals, and the barycentrics' cotangent with the depth's added (depth = b . z)."""
    e0, e1, e2, w0, w1, w2 = _face(table, f, x, y)
    block[_E * _BLOCK + n] = e0
    block[(_E + 1) * _BLOCK + n] = e1
    block[(_E + 2) * _BLOCK + n] = e2
    block[_BW * _BLOCK + n] = w0
    block[(_BW + 1) * _BLOCK + n] = w1
    block[(_BW + 2) * _BLOCK + n] = w2
    block[_BINV_W * _BLOCK + n] = table[f, _INV_W]
    block[(_BINV_W + 1) * _BLOCK + n] = table[f, _INV_W + 1]
    block[(_BINV_W + 2) * _BLOCK + n] = table[f, _INV_W + 2]
    block[_GB * _BLOCK + n] = gb0 + g_z * table[f, _CZ]
    block[(_GB + 1) * _BLOCK + n] = gb1 + g_z * table[f, _CZ + 1]
    block[(_GB + 2) * _BLOCK + n] = gb2 + g_z * table[f, _CZ + 2]
    block[_GZ * _BLOCK + n] = g_z


@numba.njit(cache=True, nogil=True)
def _accumulate(acc, block, n, faces, points):
    """Add the gradients _bary_block wrote for the first n fragments of a block (faces [n],
    points [n, 2]: NDC x, y) into the faces' rows of acc [F, _ACC_WIDTH] (e = coeffs .
    (x, y, 1): coeffs' gradient is e's times (x, y, 1))."""
    for i in range(n):
        f, x, y = faces[i], points[i, 0], points[i, 1]
        for j in range(3):
            acc[f, _W + j] += block[(_GW + j) * _BLOCK + i]
        for j in range(3):
            acc[f, _Z + j] += block[(_GZS + j) * _BLOCK + i]
        for j in range(3):
            ge = block[(_GE + j) * _BLOCK + i]
            acc[f, _C + 3 * j] += ge * x
            acc[f, _C + 3 * j + 1] += ge * y
            acc[f, _C + 3 * j + 2] += ge


@numba.njit(cache=True, nogil=True, parallel=True)
def geometry_backward_into(ids, corner_w, corner_z, coeffs, scr, width, height, soft, tiny,
                           chunks, edge, g_bary, g_depth, g_dist, out_w, out_z, out_coeffs,
                           out_scr):
    """geometry_backward writing its gradients into out_w, out_z, out_coeffs and out_scr."""
    npix, k = ids.shape
    nfaces = coeffs.shape[0]
    table = _face_table(corner_w, corner_z, coeffs, scr, tiny)
    # float64 accumulators: more accurate, and no conversion per fragment; a face's sums
    # side by side in one row (_ACC_WIDTH), not in four arrays: a fragment's accumulation
    # writes one contiguous row
    acc = np.zeros((chunks, nfaces, _ACC_WIDTH), np.float64)
    xs, pxs, ys, pys = _pixel_coords(width, height)
    for chunk in prange(chunks):
        start, stop = _chunk(chunk, chunks, npix // width)  # whole rows
        block = np.empty(_ROWS * _BLOCK)
        faces, points = np.empty(_BLOCK, np.int32), np.empty((_BLOCK, 2))
        n = 0
        # a batch of B images arrives as one of B * height rows (hostop.py)
        row, col = start % height, -1
        for pixel in range(start * width, stop * width):
            col += 1
            if col == width:
                row, col = (row + 1) % height, 0
            x, y, px, py = xs[col], ys[row], pxs[col], pys[row]
            for slot in range(k):
                f = ids[pixel, slot]
                if f < 0:
                    continue
                g_z, g_d = g_depth[pixel, slot], g_dist[pixel, slot]
                if soft and g_d != 0.0:
                    # the distance's gradient needs only the edge the forward found
                    _dist_grad(acc, chunk, f, px, py, table, g_d, edge[pixel, slot])
                gb0, gb1, gb2 = g_bary[pixel, slot, 0], g_bary[pixel, slot, 1], g_bary[
                    pixel, slot, 2]
                if gb0 == 0.0 and gb1 == 0.0 and gb2 == 0.0 and g_z == 0.0:
                    continue  # e.g. a fragment whose blend weight underflows to 0
                _gather(block, n, table, f, x, y, gb0, gb1, gb2, g_z)
                faces[n], points[n, 0], points[n, 1] = f, x, y
                n += 1
                if n == _BLOCK:
                    _bary_block(n, block, soft, tiny)
                    _accumulate(acc[chunk], block, n, faces, points)
                    n = 0
        _bary_block(n, block, soft, tiny)
        _accumulate(acc[chunk], block, n, faces, points)
    total = acc.sum(0)
    for f in range(nfaces):
        for i in range(3):
            out_w[f, i] = total[f, _W + i]
            out_z[f, i] = total[f, _Z + i]
            for j in range(3):
                out_coeffs[f, i, j] = total[f, _C + 3 * i + j]
            for j in range(2):
                out_scr[f, i, j] = total[f, _S + 2 * i + j]


def interpolate_forward(ids, bary, corners, chunks):
    """sum_i bary_i * corners[f, i]: [P, K, C] for corners [F, 3, C]."""
    npix, k = ids.shape
    out = np.empty((npix, k, corners.shape[2]), corners.dtype)
    interpolate_forward_into(ids, bary, corners, chunks, out)
    return out


@numba.njit(cache=True, nogil=True, parallel=True)
def interpolate_forward_into(ids, bary, corners, chunks, out):
    """interpolate_forward writing every element of out [P, K, C]."""
    npix, k = ids.shape
    nc = corners.shape[2]
    for chunk in prange(chunks):
        start, stop = _chunk(chunk, chunks, npix)
        for pixel in range(start, stop):
            for slot in range(k):
                f = ids[pixel, slot]
                if f < 0:
                    for ch in range(nc):
                        out[pixel, slot, ch] = 0.0
                    continue
                b0, b1, b2 = bary[pixel, slot, 0], bary[pixel, slot, 1], bary[pixel, slot, 2]
                if nc <= ROW_LANES:
                    _weighted_corners(corners, f, b0, b1, b2, out, (pixel * k + slot) * nc)
                    continue
                for ch in range(nc):
                    out[pixel, slot, ch] = (b0 * corners[f, 0, ch] + b1 * corners[f, 1, ch]
                                            + b2 * corners[f, 2, ch])
    return out


def interpolate_at(rows, ids, bary, corners, chunks):
    """interpolate_forward at some fragments only: out[i] = sum_j bary[r, j] *
    corners[ids[r], j] with r = rows[i]: [M, C] for rows [M] int32, ids [N] int32 and
    bary [N, 3] (the fragments, flat), corners [F, 3, C]; zeros where r is outside [0, N)
    or ids[r] < 0."""
    out = np.empty((rows.shape[0], corners.shape[2]), corners.dtype)
    interpolate_at_into(rows, ids, bary, corners, chunks, out)
    return out


@numba.njit(cache=True, nogil=True, parallel=True)
def interpolate_at_into(rows, ids, bary, corners, chunks, out):
    """interpolate_at writing every element of out [M, C]: the gather of the fragments'
    face ids and barycentrics is this loop's read, not an array of its own."""
    nfrags, nc = ids.shape[0], corners.shape[2]
    for chunk in prange(chunks):
        start, stop = _chunk(chunk, chunks, rows.shape[0])
        for i in range(start, stop):
            r = rows[i]
            f = ids[r] if 0 <= r < nfrags else -1
            if f < 0:
                for ch in range(nc):
                    out[i, ch] = 0.0
            elif nc <= ROW_LANES:
                _weighted_corners(corners, f, bary[r, 0], bary[r, 1], bary[r, 2], out, i * nc)
            else:
                b0, b1, b2 = bary[r, 0], bary[r, 1], bary[r, 2]
                for ch in range(nc):
                    out[i, ch] = (b0 * corners[f, 0, ch] + b1 * corners[f, 1, ch]
                                  + b2 * corners[f, 2, ch])


@intrinsic
def _weighted_corners(typingctx, corners, f, b0, b1, b2, out, at):
    """The C <= ROW_LANES channels b0 * corners[f, 0] + b1 * corners[f, 1] +
    b2 * corners[f, 2] (corners [F, 3, C], C-contiguous) written to out's elements at..at +
    C - 1 (out C-contiguous), each row as one vector (intrinsics.Rows: masked loads and a
    masked store). The same operations in the same order as the loop over channels (no
    FMA: the kernel contracts none), so the same numbers; LLVM kept that loop scalar, a
    load and a multiply or add per channel and corner."""
    if not (isinstance(corners, types.Array) and isinstance(out, types.Array)
            and corners.dtype in (types.float32, types.float64) and out.dtype == corners.dtype
            and corners.ndim == 3 and corners.layout == out.layout == "C"
            and b0 == b1 == b2):
        return None

    def codegen(context, builder, signature, args):
        corners, f, b0, b1, b2, out, at = args
        corners_type, f_type, b_type, _, _, out_type, at_type = signature.args
        array = context.make_array(corners_type)(context, builder, corners)
        channels = cgutils.unpack_tuple(builder, array.shape, 3)[2]
        rows = Rows(context, builder, corners_type.dtype, channels)
        first = builder.mul(context.cast(builder, f, f_type, types.int64),
                            builder.mul(channels, ir.Constant(ir.IntType(64), 3)))
        corner = lambda j: rows.load(array.data, builder.add(
            first, builder.mul(channels, ir.Constant(ir.IntType(64), j))))
        weight = lambda b: rows.weight(b, b_type)
        total = builder.fadd(builder.fadd(builder.fmul(weight(b0), corner(0)),
                                          builder.fmul(weight(b1), corner(1))),
                             builder.fmul(weight(b2), corner(2)))
        rows.store(total, context.make_array(out_type)(context, builder, out).data,
                   context.cast(builder, at, at_type, types.int64))
        return context.get_dummy_value()
    return types.none(corners, f, b0, b1, b2, out, at), codegen


def interpolate_backward(ids, bary, corners, g_out, chunks):
    """Gradients of interpolate_forward: (g_bary [P, K, 3], g_corners [F, 3, C])."""
    npix, k = ids.shape
    g_bary = np.empty((npix, k, 3), corners.dtype)
    g_corners = np.empty(corners.shape, corners.dtype)
    interpolate_backward_into(ids, bary, corners, g_out, chunks, g_bary, g_corners)
    return g_bary, g_corners


@numba.njit(cache=True, nogil=True, parallel=True)
def interpolate_backward_into(ids, bary, corners, g_out, chunks, g_bary, g_corners):
    """interpolate_backward writing every element of g_bary and g_corners."""
    npix, k = ids.shape
    nfaces, _, nc = corners.shape
    dtype = corners.dtype
    # one loop over the fragments, not one over pixels and one over their slots: the
    # compacted active slots arrive as pixels of one slot each (shading.compact), padded at
    # the end, so the parts take blocks of fragments in turn (_dealt)
    count = npix * k
    fids, b, g = ids.reshape(count), bary.reshape(count, 3), g_out.reshape(count, nc)
    g_b = g_bary.reshape(count, 3)
    acc = np.zeros((chunks, nfaces, 3, nc), dtype)
    for chunk in prange(chunks):
        part = acc[chunk]
        for block in range(chunk, (count + _DEALT - 1) // _DEALT, chunks):
            start, stop = _dealt(block, count)
            for i in range(start, stop):
                f = fids[i]
                if f < 0:
                    g_b[i, 0] = g_b[i, 1] = g_b[i, 2] = 0.0
                    continue
                b0, b1, b2 = b[i, 0], b[i, 1], b[i, 2]
                t0 = t1 = t2 = 0.0
                for ch in range(nc):
                    v = g[i, ch]
                    t0 += v * corners[f, 0, ch]
                    t1 += v * corners[f, 1, ch]
                    t2 += v * corners[f, 2, ch]
                    part[f, 0, ch] += b0 * v
                    part[f, 1, ch] += b1 * v
                    part[f, 2, ch] += b2 * v
                g_b[i, 0], g_b[i, 1], g_b[i, 2] = t0, t1, t2
    g_corners[:] = acc.sum(0)

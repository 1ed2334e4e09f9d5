"""Candidate search: which faces reach which pixel, nearest first (non-differentiable).

Runs on the host (called through a host callback, hostcall.py, by raster.py) as a
numba-compiled loop over tiles of the faces' screen footprints, so its cost grows with the
number of (pixel, nearby face) pairs, never with pixels x faces. Hard mode sets each face
up once and loops over the faces per band of rows. Soft mode sets each face up once, bins
the faces into tiles of TILE_W x TILE_H pixels and searches the tiles in parallel (each
thread claims the next tile as it comes free, costliest first): a tile's lists stay in
the L1 cache, and a face's pixels in a tile are evaluated without
branches, TILE_W at a time, those in reach gathered a row at a time by vector compresses.

Coverage uses 2D homogeneous rasterization (Olano & Greer 1997): with v_i = (X, Y, W)
of the clip-space vertices and p = (x_ndc, y_ndc, 1), the edge functions
e_i = (v_j x v_k) . p give the perspective-correct barycentrics e_i / sum(e) directly, and
a pixel is covered when all barycentrics are >= 0, the point is in front of the eye
(det / sum(e) > 0) and its NDC depth lies in [-1, 1]; a pixel centre exactly on an edge
belongs to one face only, by the top-left tie rule (_owns_edge), so the two faces of a
shared edge never both cover it (a transparent surface composites once). This is exactly
OpenGL's clipping against the near and far planes, done per pixel: faces that cross the
near plane are clipped, not culled, and no new triangles are made.

Soft mode (SoftRas) grows each face's footprint by `radius_px` pixels: a pixel outside
the projected triangle is a candidate when its squared distance to the triangle is at most
radius_px^2, with the depth taken at the clamped barycentrics. Faces that cross the near
plane are culled in soft mode (their screen-space triangle is not defined).

Each pixel keeps its k best faces in a small list: hard mode nearest first by NDC depth,
depths within DEPTH_TIE tied and ordered by face id (_depth_after); soft mode sorted by
(blend weight key, face id). Every candidate fragment that does not fit is counted in
`dropped`. The soft key is a float64 sum whose log1p(exp(-|x|)) is the search's own
polynomial (_softplus_neg, within 5e-16 of libm's: LLVM vectorizes it, where numba calls
libm one value at a time), so all keys are computed in one vectorized loop. A soft
fragment that cannot beat its pixel's full list (by a lower bound of its key: its face's
nearest corner, _face_key_bound) is dropped before its key is computed.

The parallel kernels hold nothing but their prange loops: under parallel=True numba turns
np.zeros, reductions and array expressions into parallel loops of their own, each one more
start and join of the threads (costly where a thread waits for one the system paused).
"""

import numba
import numpy as np
from llvmlite import ir
from numba import prange, types
from numba.core import cgutils
from numba.extending import intrinsic

from diffshade.host import numba_cache  # noqa: F401 (numba's cache saves, locked)
from diffshade.host.intrinsics import claim, compress, popcount

EDGES = ((1, 2), (2, 0), (0, 1))


@numba.njit(cache=True, nogil=True, inline="always")
def _pixel_index(v, size):
    """A pixel coordinate v (float, whole) as an int in [-1, size]: v clamped first, so that
    the coordinate of a vertex far outside the image (a field of view of 1e-18 degrees puts
    it at ~1e20 pixels) never overflows int64 (whose conversion is undefined: loops over
    garbage ranges, reads outside the arrays); -1 where v is NaN."""
    if not v == v:
        return -1
    return int(min(max(v, -1.0), float(size)))


@numba.njit(cache=True, nogil=True, inline="always")
def _corners_exist(faces, f, vertices):
    """Whether face f's three vertex indices lie in [0, vertices): render refuses a mesh
    whose do not (pipeline.rendering.check_arguments), but a mesh traced under a caller's
    jit reaches the kernels unchecked, and a face that does not is skipped here rather
    than read outside clip."""
    return ((0 <= faces[f, 0] < vertices) & (0 <= faces[f, 1] < vertices)
            & (0 <= faces[f, 2] < vertices))


@numba.njit(cache=True, nogil=True)
def _face_setup(clip, faces, f, tri, coeffs):
    """Fill tri [3, 4] and coeffs [3, 3] (rows v_j x v_k of [X Y W]); return det."""
    for i in range(3):
        tri[i] = clip[faces[f, i]]
    for i in range(3):
        j, k = (i + 1) % 3, (i + 2) % 3
        coeffs[i, 0] = tri[j, 1] * tri[k, 3] - tri[j, 3] * tri[k, 1]
        coeffs[i, 1] = tri[j, 3] * tri[k, 0] - tri[j, 0] * tri[k, 3]
        coeffs[i, 2] = tri[j, 0] * tri[k, 1] - tri[j, 1] * tri[k, 0]
    return coeffs[0, 0] * tri[0, 0] + coeffs[0, 1] * tri[0, 1] + coeffs[0, 2] * tri[0, 3]


@numba.njit(cache=True, nogil=True)
def _near_clipped_bbox(tri, box):
    """NDC box [xmin, xmax, ymin, ymax] of the face clipped to Z + W >= 0; False if empty."""
    box[0], box[1], box[2], box[3] = np.inf, -np.inf, np.inf, -np.inf
    for i in range(3):
        j = (i + 1) % 3
        di, dj = tri[i, 2] + tri[i, 3], tri[j, 2] + tri[j, 3]
        for t in (0.0, di / (di - dj) if di * dj < 0.0 else -1.0):
            if t < 0.0 or (t == 0.0 and di < 0.0):
                continue
            w = tri[i, 3] + t * (tri[j, 3] - tri[i, 3])
            if not w > 0.0:
                continue
            x = (tri[i, 0] + t * (tri[j, 0] - tri[i, 0])) / w
            y = (tri[i, 1] + t * (tri[j, 1] - tri[i, 1])) / w
            box[0], box[1] = min(box[0], x), max(box[1], x)
            box[2], box[3] = min(box[2], y), max(box[3], y)
    return box[0] <= box[1] and box[2] <= box[3]


@numba.njit(cache=True, nogil=True)
def _pixel_range(lo, hi, size, radius_px, flip):
    """Inclusive range of pixel indices whose centres lie in [lo, hi] (NDC) grown by radius."""
    if flip:
        lo, hi = -hi, -lo
    a = np.ceil((lo + 1.0) * size / 2.0 - 0.5 - radius_px)
    b = np.floor((hi + 1.0) * size / 2.0 - 0.5 + radius_px)
    return max(_pixel_index(a, size), 0), min(_pixel_index(b, size), size - 1)


@numba.njit(cache=True, nogil=True)
def _ranks_after(key, face, other_key, other_face):
    """Whether (key, face) comes after (other_key, other_face) in a pixel's list."""
    return key > other_key or (key == other_key and face > other_face)


@numba.njit(cache=True, nogil=True)
def _insert(ids, keys, filled, pixel, face, key):
    """Insert (face, key) into pixel's list of filled[pixel] entries, ascending by key and,
    among equal keys, by face (so the lists do not depend on the order faces are inserted
    in); returns 1 if a fragment fell off. filled[pixel] counts the entries, so an
    append into a list that is not full costs one comparison."""
    k = ids.shape[1]
    slot = filled[pixel]
    if slot == k:
        if _ranks_after(key, face, keys[pixel, k - 1], ids[pixel, k - 1]):
            return 1
        slot, fell = k - 1, 1
    else:
        filled[pixel] = slot + 1
        fell = 0
    while slot > 0 and _ranks_after(keys[pixel, slot - 1], ids[pixel, slot - 1], key, face):
        ids[pixel, slot] = ids[pixel, slot - 1]
        keys[pixel, slot] = keys[pixel, slot - 1]
        slot -= 1
    ids[pixel, slot] = face
    keys[pixel, slot] = key
    return fell


#: the depth test's tie width, in NDC depth: hard raster orders covering fragments nearest
#: first, and two whose NDC depths differ by at most DEPTH_TIE are equally near, the lower
#: face index first (docs/rendering.md#coplanar-faces). Coplanar faces of two objects (a
#: box resting on a table) differ in depth by the rounding of their projections, a few
#: float32 ulps, which is not the same on every path (the fitting cache's programs,
#: render's, float32 or float64, the host or the JAX search): the tie width makes their
#: order the same on all of them. 2^-18 is 64 float32 ulps just below 1 and 32 steps of a
#: 24-bit depth buffer; for a perspective camera it is an eye-space gap of about
#: DEPTH_TIE * depth^2 / (2 near).
DEPTH_TIE = 2.0 ** -18


@numba.njit(cache=True, nogil=True, inline="always")
def _depth_after(depth, face, other_depth, other_face):
    """Whether the fragment (depth, face) comes after (other_depth, other_face) in hard
    raster's order: farther by more than DEPTH_TIE, or a tie (within DEPTH_TIE) and a
    higher face index. Exactly one of two fragments of distinct faces comes after the
    other."""
    return depth > other_depth + DEPTH_TIE or (depth >= other_depth - DEPTH_TIE
                                               and face > other_face)


@numba.njit(cache=True, nogil=True)
def _insert_nearest(ids, keys, filled, pixel, face, depth):
    """_insert by hard raster's order (_depth_after) instead of (key, face): the faces come
    in ascending index order (_search_hard), and search_tiles repeats these steps."""
    k = ids.shape[1]
    slot = filled[pixel]
    if slot == k:
        if _depth_after(depth, face, keys[pixel, k - 1], ids[pixel, k - 1]):
            return 1
        slot, fell = k - 1, 1
    else:
        filled[pixel] = slot + 1
        fell = 0
    while slot > 0 and _depth_after(keys[pixel, slot - 1], ids[pixel, slot - 1], depth, face):
        ids[pixel, slot] = ids[pixel, slot - 1]
        keys[pixel, slot] = keys[pixel, slot - 1]
        slot -= 1
    ids[pixel, slot] = face
    keys[pixel, slot] = depth
    return fell


@numba.njit(cache=True, nogil=True)
def _sort_list(ids, keys, pixel, count, scratch_ids, scratch_keys):
    """Sort the first `count` entries of pixel's list by (key, face), as _insert orders
    them, without branches: each entry goes to its rank (the number of entries before it;
    a pixel's faces are distinct, so the ranks are a permutation)."""
    for i in range(count):
        scratch_ids[i], scratch_keys[i] = ids[pixel, i], keys[pixel, i]
    for i in range(count):
        key, face, rank = scratch_keys[i], scratch_ids[i], 0
        for j in range(count):  # _ranks_after(key, face, ...), with & and | (no branch)
            rank += (key > scratch_keys[j]) | ((key == scratch_keys[j])
                                               & (face > scratch_ids[j]))
        ids[pixel, rank], keys[pixel, rank] = face, key


@numba.njit(cache=True, nogil=True, inline="always")
def _owns_edge(e, a, b, s):
    """The tie rule for a pixel centre exactly on edge i (e = e_i == 0): the face owns it
    when the edge is a top or left one, i.e. the face's inward normal sign(s) (a, b) (NDC,
    y up) points right, or straight down. A neighbour across a shared edge has exactly
    the negated coefficients, so exactly one of the two owns the pixel."""
    if e != 0.0:
        return True
    if s < 0.0:
        a, b = -a, -b
    return a > 0.0 or (a == 0.0 and b < 0.0)


@numba.njit(cache=True, nogil=True, inline="always")
def _covered_depth(e0, e1, e2, a0, b0, a1, b1, a2, b2, w0, w1, w2, z0, z1, z2):
    """NDC depth of the pixel whose edge functions are e0, e1, e2 (the face's edge
    coefficients a_i x + b_i y + c_i there; corner clip W w_i and Z z_i), or +inf when the
    face does not cover it."""
    s = e0 + e1 + e2
    if s == 0.0 or e0 * s < 0.0 or e1 * s < 0.0 or e2 * s < 0.0:
        return np.inf
    if not (_owns_edge(e0, a0, b0, s) and _owns_edge(e1, a1, b1, s)
            and _owns_edge(e2, a2, b2, s)):
        return np.inf
    w = e0 * w0 + e1 * w1 + e2 * w2
    if w * s <= 0.0:
        return np.inf
    z = (e0 * z0 + e1 * z1 + e2 * z2) / w
    return z if -1.0 <= z <= 1.0 else np.inf


@numba.njit(cache=True, nogil=True)
def _raster_face(ids, keys, filled, coeffs, tri, f, c0, c1, r0, r1, xs, height):
    """Insert face f (_insert_nearest) into every pixel of rows r0..r1, columns c0..c1
    that it covers (_covered_depth); returns the fragments that fell off the lists. The
    face's coefficients are read once into registers, the pixels' NDC x come from xs [W]
    and each row's b_i y is formed once: the same arithmetic, in the same order, as
    evaluating c[i, 0] x + c[i, 1] y + c[i, 2] per pixel."""
    a0, b0, d0 = coeffs[f, 0, 0], coeffs[f, 0, 1], coeffs[f, 0, 2]
    a1, b1, d1 = coeffs[f, 1, 0], coeffs[f, 1, 1], coeffs[f, 1, 2]
    a2, b2, d2 = coeffs[f, 2, 0], coeffs[f, 2, 1], coeffs[f, 2, 2]
    w0, w1, w2 = tri[f, 0, 3], tri[f, 1, 3], tri[f, 2, 3]
    z0, z1, z2 = tri[f, 0, 2], tri[f, 1, 2], tri[f, 2, 2]
    width, fell = xs.shape[0], 0
    for row in range(r0, r1 + 1):
        y = 1.0 - (2.0 * row + 1.0) / height
        by0, by1, by2 = b0 * y, b1 * y, b2 * y
        for col in range(c0, c1 + 1):
            x = xs[col]
            z = _covered_depth(a0 * x + by0 + d0, a1 * x + by1 + d1, a2 * x + by2 + d2,
                               a0, b0, a1, b1, a2, b2, w0, w1, w2, z0, z1, z2)
            if z < np.inf:
                fell += _insert_nearest(ids, keys, filled, row * width + col, f, z)
    return fell


#: faces per item of the setups' parallel loops (_hard_setup, _soft_setup)
SETUP_CHUNK = 512


@numba.njit(cache=True, nogil=True, parallel=True)
def _hard_setup(clips, faces, width, height, cull_backfaces):
    """Per view and face, once (not once per band): tri [B, F, 3, 4], coeffs [B, F, 3, 3],
    the pixel box [B, F, 4] = (first column, last column, first row, last row) of the face
    clipped to the near plane, and reach [B, F] (False: culled, degenerate or behind); in
    parallel over chunks of SETUP_CHUNK faces of every view."""
    views, count = clips.shape[0], faces.shape[0]
    tri, coeffs = np.empty((views, count, 3, 4)), np.empty((views, count, 3, 3))
    pixels, reach = np.empty((views, count, 4), np.int64), np.empty((views, count), np.bool_)
    chunks = (count + SETUP_CHUNK - 1) // SETUP_CHUNK
    for item in prange(views * chunks):
        view, chunk = item // chunks, item % chunks
        box = np.empty(4)
        for f in range(chunk * SETUP_CHUNK, min(count, (chunk + 1) * SETUP_CHUNK)):
            reach[view, f] = False
            if not _corners_exist(faces, f, clips.shape[1]):
                continue
            det = _face_setup(clips[view], faces, f, tri[view, f], coeffs[view, f])
            if not np.isfinite(det) or det == 0.0 or (cull_backfaces and det < 0.0):
                continue
            if not _near_clipped_bbox(tri[view, f], box):
                continue
            pixels[view, f, 0], pixels[view, f, 1] = _pixel_range(box[0], box[1], width, 0.0,
                                                                  False)
            pixels[view, f, 2], pixels[view, f, 3] = _pixel_range(box[2], box[3], height, 0.0,
                                                                  True)
            reach[view, f] = True
    return tri, coeffs, pixels, reach


@numba.njit(cache=True, nogil=True)
def _centres_x(width):
    """The pixel centres' NDC x [W]."""
    return (2.0 * np.arange(width) + 1.0) / width - 1.0


@numba.njit(cache=True, nogil=True, parallel=True)
def _search_hard(clips, faces, width, height, k, cull_backfaces, bands):
    """(ids [views, H * W, k] int32, dropped [views]) of the hard search: per view and
    pixel the k nearest covering faces (-1: none), and the count of covering fragments
    beyond them."""
    views, n_pixels = clips.shape[0], width * height
    all_ids = np.empty((views, n_pixels, k), np.int32)
    all_keys = np.empty((views, n_pixels, k))
    all_filled = np.empty((views, n_pixels), np.int32)
    all_dropped = np.empty((views, bands), np.int64)
    tri, coeffs, pixels, reach = _hard_setup(clips, faces, width, height, cull_backfaces)
    xs = _centres_x(width)
    # one item per (view, band): the views of a batch share one parallel loop
    for item in prange(views * bands):
        view, band = item // bands, item % bands
        ids, keys, filled = all_ids[view], all_keys[view], all_filled[view]
        dropped = all_dropped[view]
        dropped[band] = 0
        view_tri, view_coeffs = tri[view], coeffs[view]
        band_r0, band_r1 = _band_rows(band, bands, height)
        # the band's lists start empty (filled here, in parallel, not before the loop)
        ids[band_r0 * width:(band_r1 + 1) * width] = -1
        keys[band_r0 * width:(band_r1 + 1) * width] = np.inf
        filled[band_r0 * width:(band_r1 + 1) * width] = 0
        for f in range(faces.shape[0]):
            if not reach[view, f]:
                continue
            c0, c1, r0, r1 = pixels[view, f]
            dropped[band] += _raster_face(ids, keys, filled, view_coeffs, view_tri, f, c0, c1,
                                          max(r0, band_r0), min(r1, band_r1), xs, height)
    return all_ids, all_dropped.sum(1)


@numba.njit(cache=True, nogil=True)
def _band_rows(band, bands, height):
    """Inclusive row range of one of `bands` horizontal bands (searched in parallel: a
    band's pixels are written by its own thread only)."""
    step = (height + bands - 1) // bands
    return band * step, min(height, (band + 1) * step) - 1


@numba.njit(cache=True, nogil=True)
def _segment_dist2(px, py, ax, ay, ex, ey, inv_len2):
    """Squared distance from point p to the segment from a along e (all in pixels);
    inv_len2 = 1 / |e|^2 (0 for a point)."""
    rx, ry = px - ax, py - ay
    t = min(max((rx * ex + ry * ey) * inv_len2, 0.0), 1.0)
    dx, dy = rx - t * ex, ry - t * ey
    return dx * dx + dy * dy


@intrinsic
def _fma(typingctx, a, b, c):
    """a * b + c with one rounding (LLVM's fma: an instruction where the CPU has one)."""
    if not (a == b == c == types.float64):
        return None

    def codegen(context, builder, signature, args):
        return builder.fma(*args)
    return types.float64(a, b, c), codegen


@numba.njit(cache=True, nogil=True)
def _depth_logit(z_ndc, soft):
    """zt / gamma of soft_blend from NDC depth: the depth part of a fragment's blend logit.

    soft = (sigma, gamma, near, far, perspective).
    """
    sigma, gamma, near, far, perspective = soft
    if perspective:
        inv_depth = ((far + near) - z_ndc * (far - near)) / (2.0 * far * near)
    else:
        inv_depth = 2.0 / (z_ndc * (far - near) + (far + near))
    return min(max((inv_depth - 1.0 / far) / (1.0 / near - 1.0 / far), 0.0), 1.0) / gamma


@intrinsic
def _two_pow_neg(typingctx, k):
    """2^-k for an int64 k in 0..52 (_softplus_neg's range reduction), exactly: the float64
    of biased exponent 1023 - k, made from its bits (no table lookup: LLVM keeps the
    vectorized loop free of gathers)."""
    if k != types.int64:
        return None

    def codegen(context, builder, signature, args):
        bits = builder.shl(builder.sub(ir.Constant(ir.IntType(64), 1023), args[0]),
                           ir.Constant(ir.IntType(64), 52))
        return builder.bitcast(bits, ir.DoubleType())
    return types.float64(k), codegen


@numba.njit(cache=True, nogil=True, inline="always")
def _softplus_neg(a):
    """log1p(exp(-a)) for a >= 0 without libm (LLVM vectorizes it), never negative, within
    5e-16 of libm's (tests/test_tile_search.py): exp(-a) = 2^-k exp(-r), |r| <= ln2 / 2, by
    its Taylor polynomial of degree 13 (truncation < 5e-18 relative); log(z) for z = 1 + exp(-a)
    in [1, 2], halved above sqrt(2), as 2 atanh(s), s = (z - 1) / (z + 1), |s| <= 0.172,
    by the series to s^19 (truncation < 1e-17). a is clamped to 36 (log1p(exp(-36)) <
    2.4e-16). Both polynomials by Estrin's scheme with FMAs: a chain of 4 or 5 steps
    instead of Horner's 13 and 10, whose latency (not the arithmetic) bounded the keys'
    loop."""
    a = min(a, 36.0)
    k = np.floor(a * 1.4426950408889634 + 0.5)
    r = (a - k * 6.93147180369123816490e-01) - k * 1.90821492927058770002e-10
    m = -r
    m2 = m * m
    m4 = m2 * m2
    # the terms up to m^5 (low) and, over m^6, those from m^6 (high)
    low = _fma(_fma(m, 1.0 / 120.0, 1.0 / 24.0), m2, _fma(m, 1.0 / 6.0, 0.5))
    low = _fma(low, m2, _fma(m, 1.0, 1.0))
    high = _fma(_fma(m, 1.0 / 362880.0, 1.0 / 40320.0), m2,
                _fma(m, 1.0 / 5040.0, 1.0 / 720.0))
    high = _fma(_fma(_fma(m, 1.0 / 6227020800.0, 1.0 / 479001600.0), m2,
                     _fma(m, 1.0 / 39916800.0, 1.0 / 3628800.0)), m4, high)
    p = _fma(high, m4 * m2, low)
    z = _fma(p, _two_pow_neg(int(k)), 1.0)
    big = z > 1.4142135623730951
    z = z * 0.5 if big else z
    t = (z - 1.0) / (z + 1.0)
    t2 = t * t
    t4 = t2 * t2
    # the series' terms from t^8, over t^8, then those below
    q = _fma(_fma(_fma(t2, 1.0 / 19.0, 1.0 / 17.0), t4,
                  _fma(t2, 1.0 / 15.0, 1.0 / 13.0)), t4,
             _fma(t2, 1.0 / 11.0, 1.0 / 9.0))
    q = _fma(q, t4 * t4, _fma(_fma(t2, 1.0 / 7.0, 1.0 / 5.0), t4,
                              _fma(t2, 1.0 / 3.0, 1.0)))
    return max(_fma(2.0 * t, q, 0.6931471805599453 if big else 0.0), 0.0)


@numba.njit(cache=True, nogil=True, inline="always")
def _fragment_key(depth, signed_d2, sigma):
    """The ranking key -(log D + zt / gamma) of a fragment from its depth part
    depth = -_depth_logit(z) and its signed squared distance: log D = log_sigmoid(x),
    x = signed_d2 / sigma, is -u inside (x >= 0) and x - u outside, with
    u = log1p(exp(-|x|)) by _softplus_neg. The key is at least depth (u >= 0), and
    outside at least depth - x (rounding is monotonic): _face_key_bound relies on it."""
    x = signed_d2 / sigma
    u = _softplus_neg(abs(x))
    return depth - (-u) if x >= 0.0 else depth - (x - u)


#: the soft search's tiles, in pixels: a row of a tile is one AVX-512 vector of float64
#: (_soft_block), and a tile's sorted lists (256 pixels x k keys and ids, 24 KiB for
#: k = 8) stay in the L1 cache while its faces are tested
TILE_W, TILE_H = 8, 32


@numba.njit(cache=True, nogil=True)
def _soft_face(clip, faces, f, width, height, cull_backfaces, radius_px, scr, edge, inv_len,
               zndc, box):
    """Screen-space setup of face f for the soft search: fills scr [3, 2] (vertex pixel
    coordinates), edge [3, 2] (scr[i + 1] - scr[i]), inv_len [3] (1 / edge lengths, 0 for
    a point), zndc [3] and box = (first row, last row, first column, last column) of the
    pixels its footprint may reach (rows in [-1, height]); False when it reaches none. The
    corners are read from clip once, as rows (_face_setup's det, only its first row of
    coefficients, in the same order: the soft search needs no others)."""
    if not _corners_exist(faces, f, clip.shape[0]):
        return False
    v0, v1, v2 = clip[faces[f, 0]], clip[faces[f, 1]], clip[faces[f, 2]]
    det = ((v1[1] * v2[3] - v1[3] * v2[1]) * v0[0] + (v1[3] * v2[0] - v1[0] * v2[3]) * v0[1]
           + (v1[0] * v2[1] - v1[1] * v2[0]) * v0[3])
    if not np.isfinite(det) or det == 0.0 or (cull_backfaces and det < 0.0):
        return False
    if min(v0[2] + v0[3], v1[2] + v1[3], v2[2] + v2[3]) < 0.0:
        return False
    for i, v in enumerate((v0, v1, v2)):
        scr[i, 0] = (v[0] / v[3] + 1.0) * width / 2.0
        scr[i, 1] = (1.0 - v[1] / v[3]) * height / 2.0
        zndc[i] = v[2] / v[3]
    # rows in [-1, height] (_pixel_index), so that every later int() of them is exact
    box[0] = _pixel_index(np.ceil(min(scr[0, 1], scr[1, 1], scr[2, 1]) - 0.5 - radius_px),
                          height)
    box[1] = _pixel_index(np.floor(max(scr[0, 1], scr[1, 1], scr[2, 1]) - 0.5 + radius_px),
                          height)
    if not max(box[0], 0.0) <= min(box[1], height - 1.0):
        return False
    area2 = ((scr[1, 0] - scr[0, 0]) * (scr[2, 1] - scr[0, 1])
             - (scr[2, 0] - scr[0, 0]) * (scr[1, 1] - scr[0, 1]))
    if area2 == 0.0:
        return False
    for i in range(3):
        j = (i + 1) % 3
        edge[i, 0], edge[i, 1] = scr[j, 0] - scr[i, 0], scr[j, 1] - scr[i, 1]
        # the root of the sum of squares, not libm's hypot (its three calls a face were a
        # quarter of the search's setup): the squares overflow only past ~1e154 pixels,
        # where the edge functions' products (_soft_block) overflow anyway; an edge below
        # ~1e-154 pixels becomes a point (length 0), as it nearly is
        length = np.sqrt(edge[i, 0] * edge[i, 0] + edge[i, 1] * edge[i, 1])
        inv_len[i] = 1.0 / length if length > 0.0 else 0.0
    box[2] = max(_pixel_index(np.ceil(min(scr[0, 0], scr[1, 0], scr[2, 0]) - 0.5 - radius_px),
                              width), 0)
    box[3] = min(_pixel_index(np.floor(max(scr[0, 0], scr[1, 0], scr[2, 0]) - 0.5 + radius_px),
                              width), width - 1)
    return box[2] <= box[3]


@numba.njit(cache=True, nogil=True, parallel=True)
def _soft_setup(clips, faces, width, height, cull_backfaces, radii, params, perspective):
    """_soft_face for every face of every view: scr [B, F, 3, 2], edge [B, F, 3, 2],
    inv_len [B, F, 3], zndc [B, F, 3], box [B, F, 4] and reach [B, F] (False: the face
    reaches no pixel), and the face's _face_key_bound lowest [B, F] (params [B, 4] = sigma,
    gamma, near, far; where reach), in parallel over chunks of SETUP_CHUNK faces of every
    view."""
    views, count = clips.shape[0], faces.shape[0]
    scr, edge = np.empty((views, count, 3, 2)), np.empty((views, count, 3, 2))
    inv_len, zndc = np.empty((views, count, 3)), np.empty((views, count, 3))
    box, reach = np.empty((views, count, 4)), np.empty((views, count), np.bool_)
    lowest = np.empty((views, count))
    chunks = (count + SETUP_CHUNK - 1) // SETUP_CHUNK
    for item in prange(views * chunks):
        view, chunk = item // chunks, item % chunks
        soft = (params[view, 0], params[view, 1], params[view, 2], params[view, 3], perspective)
        for f in range(chunk * SETUP_CHUNK, min(count, (chunk + 1) * SETUP_CHUNK)):
            reach[view, f] = _soft_face(clips[view], faces, f, width, height, cull_backfaces,
                                        radii[view], scr[view, f], edge[view, f],
                                        inv_len[view, f], zndc[view, f], box[view, f])
            if reach[view, f]:
                lowest[view, f] = _face_key_bound(zndc[view, f], soft)
    return scr, edge, inv_len, zndc, box, reach, lowest


@numba.njit(cache=True, nogil=True)
def _face_tiles(box, height):
    """Inclusive tile rows and columns (ty0, ty1, tx0, tx1) that a face's pixel box
    (_soft_face's box) touches."""
    r0, r1 = int(max(box[0], 0.0)), int(min(box[1], height - 1.0))
    return r0 // TILE_H, r1 // TILE_H, int(box[2]) // TILE_W, int(box[3]) // TILE_W


#: depth classes of _depth_order (faces of one class keep their index order)
DEPTH_BUCKETS = 4096


@numba.njit(cache=True, nogil=True)
def _depth_order(zndc, reach):
    """The faces roughly front to back: by a counting sort of the sum of their vertices'
    NDC depths (zndc [F, 3]) into DEPTH_BUCKETS equal classes between the nearest and the
    farthest face in reach, index order within a class; then the faces out of reach (and
    any of a depth that is not finite). O(F) where an argsort is O(F log F), and it runs
    before the parallel loops: the order only decides how soon the lists fill with their
    best fragments, never what they hold (_search_soft_into)."""
    count = zndc.shape[0]
    depth = np.empty(count)
    lo, hi = np.inf, -np.inf
    for f in range(count):
        depth[f] = zndc[f, 0] + zndc[f, 1] + zndc[f, 2]
        if reach[f] and np.isfinite(depth[f]):
            lo, hi = min(lo, depth[f]), max(hi, depth[f])
    scale = (DEPTH_BUCKETS - 1) / (hi - lo) if hi > lo else 0.0
    bucket = np.empty(count, np.int64)
    start = np.zeros(DEPTH_BUCKETS + 2, np.int64)
    for f in range(count):
        x = (depth[f] - lo) * scale
        # class DEPTH_BUCKETS: out of reach, or a depth (or scaled depth) not finite
        bucket[f] = int(x) if reach[f] and 0.0 <= x < DEPTH_BUCKETS else DEPTH_BUCKETS
        start[bucket[f] + 1] += 1
    for b in range(DEPTH_BUCKETS + 1):
        start[b + 1] += start[b]
    order = np.empty(count, np.int64)
    for f in range(count):
        order[start[bucket[f]]] = f
        start[bucket[f]] += 1
    return order


@numba.njit(cache=True, nogil=True)
def _count_view(box, reach, order, height, tiles_x, start):
    """_bin_faces' starts of one view: start [T + 1] (filled here) = 0, then the running sum
    of the number of faces whose box touches each tile."""
    start[:] = 0
    for f in order:
        if reach[f]:
            ty0, ty1, tx0, tx1 = _face_tiles(box[f], height)
            for ty in range(ty0, ty1 + 1):
                for tx in range(tx0, tx1 + 1):
                    start[ty * tiles_x + tx + 1] += 1
    for t in range(start.shape[0] - 1):
        start[t + 1] += start[t]


@numba.njit(cache=True, nogil=True)
def _fill_view(box, reach, order, height, tiles_x, start, binned):
    """_bin_faces' lists of one view: tile t's faces into binned[start[t]:start[t + 1]], in
    `order`."""
    fill = start[:-1].copy()
    for f in order:
        if reach[f]:
            ty0, ty1, tx0, tx1 = _face_tiles(box[f], height)
            for ty in range(ty0, ty1 + 1):
                for tx in range(tx0, tx1 + 1):
                    binned[fill[ty * tiles_x + tx]] = f
                    fill[ty * tiles_x + tx] += 1


@numba.njit(cache=True, nogil=True, parallel=True)
def _bin_faces(box, reach, zndc, width, height):
    """Per view, the faces whose box touches each tile, roughly front to back
    (_depth_order): (start [B, T + 1], binned [B, N]) with tile t's faces
    binned[v, start[v, t]:start[v, t + 1]]. The views are binned in parallel, a single view
    without a parallel loop (one more start and join of the threads, for nothing); their
    depth orders are made one after another (inside the parallel loop, numba compiles this
    function much more slowly the first time)."""
    views, count = reach.shape
    tiles_x, tiles_y = (width + TILE_W - 1) // TILE_W, (height + TILE_H - 1) // TILE_H
    start = np.empty((views, tiles_x * tiles_y + 1), np.int64)
    order = np.empty((views, count), np.int64)
    for view in range(views):
        order[view] = _depth_order(zndc[view], reach[view])
    if views == 1:
        _count_view(box[0], reach[0], order[0], height, tiles_x, start[0])
    else:
        for view in prange(views):
            _count_view(box[view], reach[view], order[view], height, tiles_x, start[view])
    largest = 0
    for view in range(views):
        largest = max(largest, start[view, -1])
    binned = np.empty((views, largest), np.int64)
    if views == 1:
        _fill_view(box[0], reach[0], order[0], height, tiles_x, start[0], binned[0])
    else:
        for view in prange(views):
            _fill_view(box[view], reach[view], order[view], height, tiles_x, start[view],
                       binned[view])
    return start, binned


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _soft_block(face, tile_c0, r0, c0, c1, radius_px, out, lanes, lowest, worst):
    """The fragments of one face at the pixels of `lanes` // TILE_W rows from row r0,
    TILE_W columns from tile_c0 each, without branches (LLVM vectorizes the loop): per
    pixel out[0] = the NDC depth z (+inf where the pixel is out of reach, the depth outside
    [-1, 1] or the column outside c0..c1) and out[1] = the signed squared distance to the
    triangle in pixels^2 (positive inside; -0.0 at a point outside on an edge, so its sign
    bit tells inside from outside). _soft_keys turns the lanes in reach into keys.
    lowest: _face_key_bound of the face; worst [lanes]: the last key of each pixel's list
    (+inf until it is full). A fragment in reach whose pixel's list already holds k better
    ones (lowest > worst) is dropped here, before its key is computed: out[0] is +inf
    there too, and the count of those is returned (lists only get better, so it would fall
    off when inserted).

    face: _soft_face's scr, edge, inv_len and zndc as 18 scalars (so no load in the loop
    may alias out). Inside, depth is taken at the barycentrics (NDC z is affine in screen
    space); outside, at the clamped ones. The signed distances to the edge lines are the
    cheap test the search once used to skip the segment distances; kept so that the
    pixels in reach stay exactly the same."""
    (s00, s01, s10, s11, s20, s21, e00, e01, e10, e11, e20, e21,
     inv0, inv1, inv2, z0, z1, z2) = face
    inv0_2, inv1_2, inv2_2 = inv0 ** 2, inv1 ** 2, inv2 ** 2
    dropped = 0
    for lane in range(lanes):
        col = tile_c0 + lane % TILE_W
        px, py = col + 0.5, r0 + lane // TILE_W + 0.5
        b0 = (s10 - px) * (s21 - py) - (s20 - px) * (s11 - py)
        b1 = (s20 - px) * (s01 - py) - (s00 - px) * (s21 - py)
        b2 = (s00 - px) * (s11 - py) - (s10 - px) * (s01 - py)
        sign = 1.0 if b0 + b1 + b2 > 0.0 else -1.0
        near = not min(b0 * inv1, b1 * inv2, b2 * inv0) * sign < -radius_px
        d2 = min(_segment_dist2(px, py, s00, s01, e00, e01, inv0_2),
                 _segment_dist2(px, py, s10, s11, e10, e11, inv1_2),
                 _segment_dist2(px, py, s20, s21, e20, e21, inv2_2))
        inside = (b0 * sign >= 0.0) & (b1 * sign >= 0.0) & (b2 * sign >= 0.0)
        w0, w1, w2 = max(b0 * sign, 0.0), max(b1 * sign, 0.0), max(b2 * sign, 0.0)
        z = (w0 * z0 + w1 * z1 + w2 * z2) / (w0 + w1 + w2)
        reach = ((col >= c0) & (col <= c1) & near & (inside | (not d2 > radius_px * radius_px))
                 & (-1.0 <= z) & (z <= 1.0))
        beaten = lowest > worst[lane]
        out[0, lane] = z if reach & (not beaten) else np.inf
        out[1, lane] = d2 if inside else -d2
        dropped += reach & beaten
    return dropped


#: how far below its corners' least NDC depth _face_key_bound places a face's fragments:
#: far above the rounding of _soft_block's depth, a convex combination of the corners'
#: depths in [-1, 1] (a few 1e-16)
DEPTH_MARGIN = 1e-9


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _face_key_bound(zndc, soft):
    """A lower bound of the ranking key of every fragment of a face (zndc [3]: its
    corners' NDC depths): the key is at least its depth part -_depth_logit(z) (log D <= 0,
    and rounding is monotonic), which grows with z, and a fragment's z (at clamped
    barycentrics, in [-1, 1] where in reach) is at least the corners' least, less the
    margin for rounding. NaN (no bound) where a depth is not a number."""
    lowest = min(zndc[0], zndc[1], zndc[2]) - DEPTH_MARGIN
    if not lowest == lowest:
        return np.nan
    return -_depth_logit(max(lowest, -1.0), soft)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _soft_keys(depth, signed_d2, count, soft):
    """For `count` fragments in reach (gathered from _soft_block's out), without branches
    (LLVM vectorizes the loop; numpy's error model lets it divide by sigma, which Python's
    checks for zero): depth[i] (NDC z on entry) becomes the ranking key (_fragment_key of
    its depth part -_depth_logit and signed_d2[i])."""
    for i in range(count):
        depth[i] = _fragment_key(-_depth_logit(depth[i], soft), signed_d2[i], soft[0])


#: the margin by which _strip_rows grows a footprint: ROW_MARGIN pixels plus
#: ROW_MARGIN_REL times the triangle's largest screen coordinate, far above the rounding of
#: _soft_block's and _strip_rows' own sums and products (a few 1e-16 times that coordinate)
ROW_MARGIN, ROW_MARGIN_REL = 1e-6, 1e-12


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _strip_rows(scr, c0, c1, radius_px, height):
    """The rows (first, last; first > last: none) in which a face's footprint may reach a
    pixel of columns c0..c1: the footprint is the points within radius_px of the triangle
    scr, so such a pixel lies within radius_px (in y) of a point of the triangle inside the
    strip of x within radius_px of the columns' centres, and the triangle meets that strip
    in a convex polygon whose y extent comes from the vertices inside the strip and the
    edges' crossings of its two sides (all grown by the margin above). The face's rows
    then cover every pixel _soft_block finds in reach of these columns; rows 0..height - 1
    where a coordinate is not finite."""
    largest = max(abs(scr[0, 0]), abs(scr[0, 1]), abs(scr[1, 0]), abs(scr[1, 1]),
                  abs(scr[2, 0]), abs(scr[2, 1]))
    if not largest < np.inf:
        return 0, height - 1
    reach = radius_px + ROW_MARGIN + ROW_MARGIN_REL * largest
    x_lo, x_hi = c0 + 0.5 - reach, c1 + 0.5 + reach
    y_lo, y_hi = np.inf, -np.inf
    # selects, not branches (whether a vertex lies in the strip and an edge crosses its
    # sides changes from face to face): every crossing is computed, and kept only where
    # the edge crosses (a crossing's x values differ, so its division is by a nonzero)
    for i in range(3):
        j = (i + 1) % 3
        xi, yi, xj, yj = scr[i, 0], scr[i, 1], scr[j, 0], scr[j, 1]
        within = (x_lo <= xi) & (xi <= x_hi)
        y_lo, y_hi = _select(within & (yi < y_lo), yi, y_lo), _select(within & (yi > y_hi),
                                                                      yi, y_hi)
        for side in (x_lo, x_hi):
            y = yi + (side - xi) / (xj - xi) * (yj - yi)
            crosses = (xi - side) * (xj - side) < 0.0
            y_lo, y_hi = _select(crosses & (y < y_lo), y, y_lo), _select(crosses & (y > y_hi),
                                                                         y, y_hi)
    if not y_lo <= y_hi:
        return 0, -1
    first = np.ceil(y_lo - 0.5 - reach)
    last = np.floor(y_hi - 0.5 + reach)
    return max(_pixel_index(first, height), 0), min(_pixel_index(last, height), height - 1)


@numba.njit(cache=True, nogil=True)
def _face_scalars(scr, edge, inv_len, zndc):
    """_soft_block's face tuple."""
    return (scr[0, 0], scr[0, 1], scr[1, 0], scr[1, 1], scr[2, 0], scr[2, 1],
            edge[0, 0], edge[0, 1], edge[1, 0], edge[1, 1], edge[2, 0], edge[2, 1],
            inv_len[0], inv_len[1], inv_len[2], zndc[0], zndc[1], zndc[2])


@intrinsic
def _gather_reached(typingctx, out, lane, first, fragments, depth, signed_d2, count):
    """Append the fragments in reach (out[0] < inf) among lanes lane..lane + 7 (one row
    of a tile, TILE_W = 8) of _soft_block's out [2, L] to fragments (first + lane), depth
    (out[0]) and signed_d2 (out[1]) from index count, in lane order, as vector operations
    without branches; returns the new count. It writes 8 entries from count whatever the
    number in reach (those past the new count are overwritten by the next rows)."""
    vectors = ((out, types.float64, 2), (fragments, types.int64, 1),
               (depth, types.float64, 1), (signed_d2, types.float64, 1))
    if not all(isinstance(a, types.Array) and a.dtype == dtype and a.ndim == ndim
               and a.layout == "C" for a, dtype, ndim in vectors) or TILE_W != 8:
        return None

    def codegen(context, builder, signature, args):
        out_type, _, _, fragments_type, depth_type, signed_d2_type, _ = signature.args
        out, lane, first, fragments, depth, signed_d2, count = args
        double, i64 = ir.DoubleType(), ir.IntType(64)
        lane = context.cast(builder, lane, signature.args[1], types.int64)
        first = context.cast(builder, first, signature.args[2], types.int64)
        count = context.cast(builder, count, signature.args[6], types.int64)
        out_array = context.make_array(out_type)(context, builder, out)
        length = cgutils.unpack_tuple(builder, out_array.shape, 2)[1]

        def vector_at(data, index, element):
            pointer = builder.gep(data, [index])
            return builder.bitcast(pointer, ir.PointerType(ir.VectorType(element, 8)))
        z = builder.load(vector_at(out_array.data, lane, double), align=8)
        d2 = builder.load(vector_at(out_array.data, builder.add(length, lane), double),
                          align=8)
        reached = builder.fcmp_ordered("<", z, ir.Constant(z.type, [np.inf] * 8))
        splat = builder.shuffle_vector(
            builder.insert_element(ir.Constant(ir.VectorType(i64, 8), None),
                                   builder.add(first, lane), ir.Constant(ir.IntType(32), 0)),
            ir.Constant(ir.VectorType(i64, 8), None),
            ir.Constant(ir.VectorType(ir.IntType(32), 8), [0] * 8))
        index = builder.add(splat, ir.Constant(splat.type, list(range(8))))
        for array_type, array, vector, element in (
                (fragments_type, fragments, index, i64), (depth_type, depth, z, double),
                (signed_d2_type, signed_d2, d2, double)):
            data = context.make_array(array_type)(context, builder, array).data
            builder.store(compress(builder, vector, reached), vector_at(data, count, element),
                          align=8)
        return builder.add(count, popcount(builder, reached))
    return types.int64(out, lane, first, fragments, depth, signed_d2, count), codegen


#: a soft search tile's fragments in reach are gathered over its faces until there are at
#: least this many, then keyed (_soft_keys) and inserted (_insert_group): the keys' loop
#: runs over a thousand lanes, not the ~30 of one face, whose scalar remainder dominated
GROUP = 1024


@numba.njit(cache=True, nogil=True)
def _insert_group8(ids, keys, worst_key, fragments, key, count):
    """_insert_group for lists of 8 (the soft search's default), without branches: every
    fragment goes through _insert8, whose lists are always sorted (so neither the counts
    of filled entries nor a sort at the end are needed); returns how many fragments were
    dropped."""
    dropped = 0
    for i in range(count):
        pixel, f = fragments[i] % (TILE_H * TILE_W), fragments[i] // (TILE_H * TILE_W)
        dropped += _insert8(keys, ids, pixel, key[i], f)
    for pixel in range(keys.shape[0]):
        worst_key[pixel] = keys[pixel, 7]
    return dropped


@numba.njit(cache=True, nogil=True)
def _insert_group(ids, keys, filled, worst_key, worst_id, fragments, key, count, scratch_ids,
                  scratch_keys):
    """Insert `count` gathered fragments (fragments[i] = face * TILE_H * TILE_W + pixel;
    key[i]: _soft_keys' key) in order; returns how many were dropped. A full list whose
    last entry (worst_key, worst_id: copies, so one cache line holds those of 8 pixels)
    ranks before the fragment rejects it. A list is appended to unsorted until full, then
    sorted once (_sort_full) and kept sorted by _insert; the others are sorted at the end
    of the tile."""
    k = ids.shape[1]
    if k == 8:
        return _insert_group8(ids, keys, worst_key, fragments, key, count)
    dropped = 0
    for i in range(count):
        pixel, f = fragments[i] % (TILE_H * TILE_W), fragments[i] // (TILE_H * TILE_W)
        if filled[pixel] == k and _ranks_after(key[i], f, worst_key[pixel], worst_id[pixel]):
            dropped += 1
            continue
        if filled[pixel] < k:  # appended unsorted; sorted once full
            ids[pixel, filled[pixel]], keys[pixel, filled[pixel]] = f, key[i]
            filled[pixel] += 1
            if filled[pixel] < k:
                continue
            _sort_full(ids, keys, pixel, scratch_ids, scratch_keys)
        else:
            dropped += _insert(ids, keys, filled, pixel, f, key[i])
        worst_key[pixel], worst_id[pixel] = keys[pixel, k - 1], ids[pixel, k - 1]
    return dropped


@intrinsic
def _select(typingctx, condition, if_true, if_false):
    """`if_true if condition else if_false` as one LLVM select (a conditional move, no
    branch: numba's conditional expression becomes a branch that LLVM keeps)."""
    if not (isinstance(condition, types.Boolean) and if_true == if_false):
        return None

    def codegen(context, builder, signature, args):
        return builder.select(args[0], args[1], args[2])
    return if_true(condition, if_true, if_false), codegen


def _vector_list(context, builder, array_type, array, pixel, element):
    """A pointer to pixel's row of a C-contiguous [P, 8] array as one <8 x element>."""
    data = context.make_array(array_type)(context, builder, array).data
    row = builder.gep(data, [builder.mul(pixel, ir.Constant(pixel.type, 8))])
    return builder.bitcast(row, ir.PointerType(ir.VectorType(element, 8)))


@intrinsic
def _insert8(typingctx, keys, ids, pixel, key, face):
    """Insert (key, face) into pixel's list of 8 (keys [P, 8] float64 and ids [P, 8] int32,
    C-contiguous, sorted by (key, face), empty entries (+inf, -1) last) as vector
    operations, without branches: each entry that ranks after the new one moves down one
    slot, the last falling off. Returns 1 when the list was full (one fragment, the new or
    the last, fell off), else 0. The lists hold distinct faces and finite keys."""
    if not (isinstance(keys, types.Array) and keys.dtype == types.float64 and keys.ndim == 2
            and keys.layout == "C" and isinstance(ids, types.Array)
            and ids.dtype == types.int32 and ids.ndim == 2 and ids.layout == "C"):
        return None

    def codegen(context, builder, signature, args):
        keys_type, ids_type = signature.args[:2]
        keys, ids, pixel, key, face = args
        pixel = context.cast(builder, pixel, signature.args[2], types.int64)
        key = context.cast(builder, key, signature.args[3], types.float64)
        face = context.cast(builder, face, signature.args[4], types.int32)
        key_ptr = _vector_list(context, builder, keys_type, keys, pixel, ir.DoubleType())
        id_ptr = _vector_list(context, builder, ids_type, ids, pixel, ir.IntType(32))
        listed_keys, listed_ids = builder.load(key_ptr, align=8), builder.load(id_ptr, align=4)
        splat = ir.Constant(ir.VectorType(ir.IntType(32), 8), [0] * 8)
        new_key = builder.shuffle_vector(
            builder.insert_element(ir.Constant(listed_keys.type, None), key,
                                   ir.Constant(ir.IntType(32), 0)),
            ir.Constant(listed_keys.type, None), splat)
        new_id = builder.shuffle_vector(
            builder.insert_element(ir.Constant(listed_ids.type, None), face,
                                   ir.Constant(ir.IntType(32), 0)),
            ir.Constant(listed_ids.type, None), splat)
        # before[j]: the new entry ranks before entry j (not _ranks_after(entry j, new))
        before = builder.or_(
            builder.fcmp_ordered("<", new_key, listed_keys),
            builder.and_(builder.fcmp_ordered("==", new_key, listed_keys),
                         builder.icmp_signed("<", new_id, listed_ids)))
        down = ir.Constant(ir.VectorType(ir.IntType(32), 8), [8, 0, 1, 2, 3, 4, 5, 6])
        before_previous = builder.shuffle_vector(
            before, ir.Constant(before.type, [0] * 8), down)
        shift = ir.Constant(ir.VectorType(ir.IntType(32), 8), [0, 0, 1, 2, 3, 4, 5, 6])
        builder.store(builder.select(
            before_previous, builder.shuffle_vector(listed_keys, listed_keys, shift),
            builder.select(before, new_key, listed_keys)), key_ptr, align=8)
        builder.store(builder.select(
            before_previous, builder.shuffle_vector(listed_ids, listed_ids, shift),
            builder.select(before, new_id, listed_ids)), id_ptr, align=4)
        last = builder.extract_element(listed_ids, ir.Constant(ir.IntType(32), 7))
        full = builder.icmp_signed(">=", last, ir.Constant(ir.IntType(32), 0))
        return builder.zext(full, ir.IntType(64))
    return types.int64(keys, ids, pixel, key, face), codegen


@numba.njit(cache=True, nogil=True, inline="always")
def _exchange(key_a, id_a, key_b, id_b):
    """A compare-exchange: the two entries in (key, face) order, without branches."""
    swap = (key_a > key_b) | ((key_a == key_b) & (id_a > id_b))  # _ranks_after, no branch
    return (_select(swap, key_b, key_a), _select(swap, id_b, id_a),
            _select(swap, key_a, key_b), _select(swap, id_a, id_b))


@numba.njit(cache=True, nogil=True)
def _sort_full(ids, keys, pixel, scratch_ids, scratch_keys):
    """Sort pixel's full list by (key, face) as _sort_list does: for 8 entries (the soft
    search's default), by Batcher's odd-even merge network of 19 compare-exchanges in
    registers, without branches."""
    if ids.shape[1] != 8:
        _sort_list(ids, keys, pixel, ids.shape[1], scratch_ids, scratch_keys)
        return
    k0, k1, k2, k3 = keys[pixel, 0], keys[pixel, 1], keys[pixel, 2], keys[pixel, 3]
    k4, k5, k6, k7 = keys[pixel, 4], keys[pixel, 5], keys[pixel, 6], keys[pixel, 7]
    i0, i1, i2, i3 = ids[pixel, 0], ids[pixel, 1], ids[pixel, 2], ids[pixel, 3]
    i4, i5, i6, i7 = ids[pixel, 4], ids[pixel, 5], ids[pixel, 6], ids[pixel, 7]
    k0, i0, k1, i1 = _exchange(k0, i0, k1, i1)
    k2, i2, k3, i3 = _exchange(k2, i2, k3, i3)
    k4, i4, k5, i5 = _exchange(k4, i4, k5, i5)
    k6, i6, k7, i7 = _exchange(k6, i6, k7, i7)
    k0, i0, k2, i2 = _exchange(k0, i0, k2, i2)
    k1, i1, k3, i3 = _exchange(k1, i1, k3, i3)
    k4, i4, k6, i6 = _exchange(k4, i4, k6, i6)
    k5, i5, k7, i7 = _exchange(k5, i5, k7, i7)
    k1, i1, k2, i2 = _exchange(k1, i1, k2, i2)
    k5, i5, k6, i6 = _exchange(k5, i5, k6, i6)
    k0, i0, k4, i4 = _exchange(k0, i0, k4, i4)
    k1, i1, k5, i5 = _exchange(k1, i1, k5, i5)
    k2, i2, k6, i6 = _exchange(k2, i2, k6, i6)
    k3, i3, k7, i7 = _exchange(k3, i3, k7, i7)
    k2, i2, k4, i4 = _exchange(k2, i2, k4, i4)
    k3, i3, k5, i5 = _exchange(k3, i3, k5, i5)
    k1, i1, k2, i2 = _exchange(k1, i1, k2, i2)
    k3, i3, k4, i4 = _exchange(k3, i3, k4, i4)
    k5, i5, k6, i6 = _exchange(k5, i5, k6, i6)
    keys[pixel, 0], keys[pixel, 1], keys[pixel, 2], keys[pixel, 3] = k0, k1, k2, k3
    keys[pixel, 4], keys[pixel, 5], keys[pixel, 6], keys[pixel, 7] = k4, k5, k6, k7
    ids[pixel, 0], ids[pixel, 1], ids[pixel, 2], ids[pixel, 3] = i0, i1, i2, i3
    ids[pixel, 4], ids[pixel, 5], ids[pixel, 6], ids[pixel, 7] = i4, i5, i6, i7


def _search_soft(clips, faces, width, height, k, cull_backfaces, radii, params, perspective,
                 threads):
    """(ids [views, H * W, k] int32, dropped [views]): _search_soft_into's results in new
    arrays."""
    all_ids = np.empty((clips.shape[0], width * height, k), np.int32)
    dropped = _search_soft_into(clips, faces, width, height, k, cull_backfaces, radii, params,
                                perspective, all_ids, threads)
    return all_ids, dropped


@numba.njit(cache=True, nogil=True)
def _tile_order(start):
    """The (view, tile) items (view * tiles + tile) of a soft search, those with the most
    binned faces first (start [B, T + 1]: _bin_faces'), so that the threads claiming them
    one at a time end together: the last items are the cheapest."""
    views, tiles = start.shape[0], start.shape[1] - 1
    work = np.empty(views * tiles, np.int64)
    for item in range(views * tiles):
        view, t = item // tiles, item % tiles
        work[item] = start[view, t] - start[view, t + 1]  # negated: the most first
    return np.argsort(work, kind="mergesort")


@numba.njit(cache=True, nogil=True)
def _tile_scratch(k):
    """A thread's arrays for _search_tile, allocated once per search and reused tile after
    tile (fresh arrays per tile cost thousands of mallocs a search)."""
    capacity = GROUP + TILE_H * TILE_W
    return (np.empty((TILE_H * TILE_W, k), np.int32), np.empty((TILE_H * TILE_W, k)),
            np.empty(TILE_H * TILE_W, np.int32), np.empty(TILE_H * TILE_W),
            np.empty(TILE_H * TILE_W, np.int64), np.empty((2, TILE_H * TILE_W)),
            np.empty(capacity, np.int64), np.empty(capacity), np.empty(capacity),
            np.empty(k, np.int32), np.empty(k))


@numba.njit(cache=True, nogil=True)
def _search_tile(setup, binned, first_slot, last_slot, tile_r0, tile_c0, width, height, k,
                 radius_px, soft, ids_out, scratch):
    """Search one tile of one view: its lists from its faces binned[first_slot:last_slot]
    (setup: one view's scr, edge, inv_len, zndc, box and lowest_key of _soft_setup), copied
    into ids_out [H * W, k]; returns the fragments dropped. A tile's pixel (row, col) is
    (row - tile_r0) * TILE_W + col - tile_c0 (TILE_W columns even where the image ends).
    Per face: its rows in reach of the tile's columns (_strip_rows), evaluated without
    branches (_soft_block), the pixels in reach gathered (_gather_reached); per GROUP of
    those, keys and insertions."""
    scr, edge, inv_len, zndc, box, lowest_key = setup
    tile_r1, tile_c1 = min(tile_r0 + TILE_H, height) - 1, min(tile_c0 + TILE_W, width) - 1
    tile_w = tile_c1 - tile_c0 + 1
    if first_slot == last_slot:  # no face reaches the tile: no lists
        for row in range(tile_r0, tile_r1 + 1):
            ids_out[row * width + tile_c0:row * width + tile_c1 + 1] = -1
        return 0
    (ids, keys, filled, worst_key, worst_id, out, fragments, depth, signed_d2, scratch_ids,
     scratch_keys) = scratch
    ids[:] = -1
    keys[:] = np.inf
    filled[:] = 0
    worst_key[:] = np.inf
    worst_id[:] = -1
    dropped, count = 0, 0
    for slot in range(first_slot, last_slot):
        f = binned[slot]
        fb = box[f]
        c0, c1 = max(int(fb[2]), tile_c0), min(int(fb[3]), tile_c1)
        r0, r1 = _strip_rows(scr[f], c0, c1, radius_px, height)
        r0, r1 = max(r0, int(max(fb[0], tile_r0))), min(r1, int(min(fb[1], tile_r1)))
        if r0 <= r1:
            face = _face_scalars(scr[f], edge[f], inv_len[f], zndc[f])
            lane0 = (r0 - tile_r0) * TILE_W
            dropped += _soft_block(face, tile_c0, r0, c0, c1, radius_px, out,
                                   (r1 - r0 + 1) * TILE_W, lowest_key[f], worst_key[lane0:])
            first = f * (TILE_H * TILE_W) + lane0
            for lane in range(0, (r1 - r0 + 1) * TILE_W, TILE_W):  # the pixels in reach
                count = _gather_reached(out, lane, first, fragments, depth, signed_d2, count)
        if count >= GROUP or (slot == last_slot - 1 and count > 0):
            _soft_keys(depth, signed_d2, count, soft)
            dropped += _insert_group(ids, keys, filled, worst_key, worst_id, fragments, depth,
                                     count, scratch_ids, scratch_keys)
            count = 0
    for pixel in range(ids.shape[0] if k != 8 else 0):  # lists of 8 stay sorted
        if filled[pixel] < k:
            _sort_list(ids, keys, pixel, filled[pixel], scratch_ids, scratch_keys)
    for row in range(tile_r0, tile_r1 + 1):
        ids_out[row * width + tile_c0:row * width + tile_c1 + 1] = \
            ids[(row - tile_r0) * TILE_W:(row - tile_r0) * TILE_W + tile_w]
    return dropped


@numba.njit(cache=True, nogil=True, parallel=True)
def _search_soft_into(clips, faces, width, height, k, cull_backfaces, radii, params,
                      perspective, all_ids, threads):
    """The soft search of every view into all_ids [views, H * W, k] (XLA's buffer, ffi.py)
    by `threads` threads (numba's thread count: numba.get_num_threads here would keep numba
    from caching the kernel); returns dropped [views]."""
    views = clips.shape[0]
    scr, edge, inv_len, zndc, box, reach, lowest_key = _soft_setup(
        clips, faces, width, height, cull_backfaces, radii, params, perspective)
    # faces front to back: the lists fill with the best fragments first, and the bound
    # then rejects most of the rest without the logarithm (the lists are ordered by
    # (key, face), so the result does not depend on this order)
    start, binned = _bin_faces(box, reach, zndc, width, height)
    tiles_x, tiles_y = (width + TILE_W - 1) // TILE_W, (height + TILE_H - 1) // TILE_H
    tiles = tiles_x * tiles_y
    all_dropped = np.empty((views, tiles), np.int64)  # each item writes its own
    # the (view, tile) items (the views of a batch share one parallel loop; a tile's lists
    # are its own until they are copied out), claimed one at a time by each thread, the
    # costliest first: the threads stay busy until the last few cheap items, whatever the
    # tiles' costs (a face-dense tile costs a hundred sparse ones) and however the threads
    # are scheduled (a static split waits for a thread the system has paused)
    order, counter = _tile_order(start), np.empty(1, np.int64)
    counter[0] = 0
    for _ in prange(max(1, min(threads, views * tiles))):
        scratch = _tile_scratch(k)
        item = claim(counter)
        while item < views * tiles:
            view, t = order[item] // tiles, order[item] % tiles
            setup = (scr[view], edge[view], inv_len[view], zndc[view], box[view],
                     lowest_key[view])
            soft = (params[view, 0], params[view, 1], params[view, 2], params[view, 3],
                    perspective)
            all_dropped[view, t] = _search_tile(
                setup, binned[view], start[view, t], start[view, t + 1], t // tiles_x * TILE_H,
                t % tiles_x * TILE_W, width, height, k, radii[view], soft, all_ids[view],
                scratch)
            item = claim(counter)
    return all_dropped.sum(1)


def find_candidates(clip, faces, near=0.1, far=100.0, *, width, height, k,
                    cull_backfaces=False, radius_px=0.0, sigma=1.0, gamma=1e-4,
                    perspective=True):
    """Per pixel, the ids of the k faces that reach it, best first.

    clip: [V, 4] float clip coordinates; faces: [F, 3] int. Hard mode (radius_px = 0):
    covering faces, nearest first. Soft mode (radius_px > 0, the footprint radius in
    pixels): faces within reach, ranked by their weight in soft_blend,
    log D + zt / gamma (sigma, gamma, near, far and the projection give D and the
    normalized inverse depth zt): for small gamma this is nearest first, and among
    fragments at nearly the same depth the one that covers the pixel outranks neighbours
    that only graze it. Returns (face_ids [H, W, k] int32, -1 where fewer faces reach the
    pixel; dropped: [] int32, fragments beyond the k kept).

    A batch of B views of one mesh: clip [B, V, 4], and near, far, radius_px, sigma and
    gamma each a scalar or [B]; returns face_ids [B, H, W, k] and dropped [B]. The views
    are searched in one parallel loop (over views x bands of rows), not one after another.
    """
    clip = np.asarray(clip, np.float64)
    batched = clip.ndim == 3
    clips = np.ascontiguousarray(clip if batched else clip[None])
    views = clips.shape[0]
    per_view = lambda x: np.ascontiguousarray(np.broadcast_to(np.asarray(x, np.float64), views))
    radii = per_view(radius_px)
    faces = np.ascontiguousarray(faces, np.int64)
    if np.any(radii > 0.0):
        params = np.stack([per_view(sigma), per_view(gamma), per_view(near), per_view(far)], 1)
        ids, dropped = _search_soft(clips, faces, width, height, k, cull_backfaces, radii,
                                    params, bool(perspective), numba.get_num_threads())
    else:
        bands = min(height, 2 * numba.get_num_threads())
        ids, dropped = _search_hard(clips, faces, width, height, k, cull_backfaces, bands)
    ids, dropped = ids.reshape(views, height, width, k), dropped.astype(np.int32)
    return (ids, dropped) if batched else (ids[0], dropped[0])

"""Candidate search in pure JAX by tile binning: the device counterpart of candidates.py.

`search_tiles` answers the same question as `candidates.find_candidates` (which faces
reach which pixel, best first; discrete, no gradient) with the same coverage tests, depth,
ranking keys and tie order, but as ordinary JAX ops: it runs under `jit`, `vmap` and
inside `grad` on any backend, so an accelerator never calls back to the host.

Two steps, both with static shapes, repeated in passes:
1. Binning. The image is cut into tiles of `tile` x `tile` pixels. Each face's pixel box
   (the host's: near-clipped screen box in hard mode, the box grown by radius_px in soft
   mode) is tested against every tile: cost tiles x faces, chunked with `lax.map` so its
   memory stays bounded. Pass p gives each tile the faces ranked p * capacity to
   (p + 1) * capacity - 1 among those that touch it, lowest face ids first.
2. Evaluation. Each pixel tests only its tile's list (cost pixels x capacity, never
   pixels x faces) and merges the keys with the best k of the earlier passes. Soft mode
   merges by `lax.top_k`, which puts equal keys in list order: lower face id first
   (earlier passes hold lower ids), as the host's stable insertion does. Hard mode inserts
   the faces one at a time in ascending id order (a loop), as the host does: its
   depth test's ties (depths within candidates.DEPTH_TIE) are not a sort by key.
There are as many passes as the most crowded tile needs (a `lax.while_loop`; one where
no tile holds more than `capacity` faces), so no face is ever left untested: a dense mesh
in a small image costs more passes, not wrong pixels.

Compiled size: the program holds one copy of each step. The first pass is the loop's
first iteration (it also counts the passes), not a copy of the loop body before it, and
the tile count is padded to a multiple of each `lax.map`'s batch (tiles outside the image,
which no face touches), so that `lax.map` compiles no second body for a remainder. This
halves the search's compile time, which a fresh install's first render waits for.

Bit-exactness: the arithmetic mirrors candidates.py operation by operation, and every
product that feeds an addition goes through `_rounded`, because XLA's CPU backend would
otherwise fuse it into an FMA (one rounding instead of two) and move coverage decisions
and near-tied keys by an ulp. With float64 input the face ids then equal the host's; the
soft key's log1p(exp(-|x|)) is XLA's here and a polynomial of the host's own there
(candidates._softplus_neg, within 5e-16), so two soft keys within an ulp or so of each
other can still rank differently. float32 input is computed in float32 (the host
always computes in float64), so there pixels on edges and near-tied faces may differ.

`dropped` counts, in one number, reaching fragments beyond the k kept, as the host does.
"""

import jax
import jax.numpy as jnp
from jax import lax

from diffshade.host.candidates import DEPTH_TIE

NEXT = (1, 2, 0)   # vertex i's edge runs to NEXT[i]
PREV = (2, 0, 1)
TILE_ELEMENTS = 1 << 20   # (pixel, candidate) pairs evaluated per lax.map step
BIN_ELEMENTS = 1 << 21    # (tile, face) pairs tested per lax.map step


def _rounded(product):
    """The product, rounded before any addition it feeds: the select hides it from LLVM's
    mul-add fusion, so results match the host kernel bit for bit (NaN stays NaN)."""
    return jnp.where(product == product, product, jnp.nan)


def _mul_sub(a, b, c, d):
    """a * b - c * d with each product rounded (no FMA)."""
    return _rounded(a * b) - _rounded(c * d)


def _dot3(a0, a1, a2, b0, b1, b2):
    """(a0 b0 + a1 b1) + a2 b2 in the host's order, without FMA."""
    return (_rounded(a0 * b0) + _rounded(a1 * b1)) + _rounded(a2 * b2)


def _edge_coefficients(tri):
    """Rows v_j x v_k of (X, Y, W) for tri [F, 3, 4]: [F, 3, 3]; and det [F]."""
    rows = []
    for i in range(3):
        vj, vk = tri[:, NEXT[i]], tri[:, PREV[i]]
        rows.append(jnp.stack([_mul_sub(vj[:, 1], vk[:, 3], vj[:, 3], vk[:, 1]),
                               _mul_sub(vj[:, 3], vk[:, 0], vj[:, 0], vk[:, 3]),
                               _mul_sub(vj[:, 0], vk[:, 1], vj[:, 1], vk[:, 0])], -1))
    coeffs = jnp.stack(rows, 1)
    det = _dot3(*coeffs[:, 0].T, tri[:, 0, 0], tri[:, 0, 1], tri[:, 0, 3])
    return coeffs, det


def _face_ok(det, cull_backfaces):
    """[F] bool: a usable face (finite, non-zero det; front-facing if culling)."""
    ok = jnp.isfinite(det) & (det != 0.0)
    return ok & (det > 0.0) if cull_backfaces else ok


def _near_clipped_box(tri):
    """NDC box [F, 4] (xmin, xmax, ymin, ymax) of each face clipped to Z + W >= 0, from
    its corners in front and its edges' crossings (candidates._near_clipped_bbox)."""
    xs, ys, keep = [], [], []
    for i in range(3):
        vi, vj = tri[:, i], tri[:, NEXT[i]]
        di, dj = vi[:, 2] + vi[:, 3], vj[:, 2] + vj[:, 3]
        crossing = jnp.where(_rounded(di * dj) < 0.0, di / (di - dj), -1.0)
        for t in (jnp.zeros_like(di), crossing):
            w = vi[:, 3] + _rounded(t * (vj[:, 3] - vi[:, 3]))
            keep.append(~((t < 0.0) | ((t == 0.0) & (di < 0.0))) & (w > 0.0))
            xs.append((vi[:, 0] + _rounded(t * (vj[:, 0] - vi[:, 0]))) / w)
            ys.append((vi[:, 1] + _rounded(t * (vj[:, 1] - vi[:, 1]))) / w)
    keep, xs, ys = jnp.stack(keep), jnp.stack(xs), jnp.stack(ys)
    inf = jnp.inf
    return jnp.stack([jnp.where(keep, xs, inf).min(0), jnp.where(keep, xs, -inf).max(0),
                      jnp.where(keep, ys, inf).min(0), jnp.where(keep, ys, -inf).max(0)], -1)


def _index_range(first, last, size):
    """Inclusive pixel index range [F] int32 x 2 from float bounds, clipped to the image
    (empty when first > last)."""
    first = jnp.clip(jnp.ceil(first), 0.0, size).astype(jnp.int32)
    last = jnp.clip(jnp.floor(last), -1.0, size - 1.0).astype(jnp.int32)
    return first, last


def _ndc_pixel_range(lo, hi, size):
    """Pixels whose centres lie in the NDC interval [lo, hi] (candidates._pixel_range)."""
    return _index_range(_rounded((lo + 1.0) * size) / 2.0 - 0.5,
                        _rounded((hi + 1.0) * size) / 2.0 - 0.5, size)


def _hard_faces(clip, faces, width, height, cull_backfaces):
    """Per-face data of the hard test, (coeffs [F, 3, 3], W [F, 3], Z [F, 3]), and the
    pixel box [F, 4] int32 (c0, c1, r0, r1), empty for faces the host skips."""
    tri = clip[faces]
    coeffs, det = _edge_coefficients(tri)
    box = _near_clipped_box(tri)
    ok = _face_ok(det, cull_backfaces) & (box[:, 0] <= box[:, 1]) & (box[:, 2] <= box[:, 3])
    c0, c1 = _ndc_pixel_range(box[:, 0], box[:, 1], width)
    r0, r1 = _ndc_pixel_range(-box[:, 3], -box[:, 2], height)
    return (coeffs, tri[..., 3], tri[..., 2]), _mask_box(jnp.stack([c0, c1, r0, r1], -1), ok)


def _mask_box(box, ok):
    """Empty the pixel box [F, 4] of faces that are not ok [F]."""
    return jnp.where(ok[:, None], box, jnp.array([0, -1, 0, -1], jnp.int32))


def _soft_faces(clip, faces, width, height, cull_backfaces, radius_px):
    """Per-face data of the soft test, (scr [F, 3, 2] pixel corners, edge [F, 3, 2],
    inv_len [F, 3], zndc [F, 3]), and the pixel box [F, 4] grown by radius_px; faces with
    a corner behind the near plane or no screen area are skipped, as by the host."""
    tri = clip[faces]
    _, det = _edge_coefficients(tri)
    scr = jnp.stack([(tri[..., 0] / tri[..., 3] + 1.0) * width / 2.0,
                     (1.0 - tri[..., 1] / tri[..., 3]) * height / 2.0], -1)
    edge = scr[:, NEXT] - scr
    length = jnp.hypot(edge[..., 0], edge[..., 1])
    inv_len = jnp.where(length > 0.0, 1.0 / jnp.where(length > 0.0, length, 1.0), 0.0)
    area2 = _mul_sub(scr[:, 1, 0] - scr[:, 0, 0], scr[:, 2, 1] - scr[:, 0, 1],
                     scr[:, 2, 0] - scr[:, 0, 0], scr[:, 1, 1] - scr[:, 0, 1])
    in_front = jnp.min(tri[..., 2] + tri[..., 3], axis=1) >= 0.0
    ok = _face_ok(det, cull_backfaces) & in_front & (area2 != 0.0)
    lo, hi = scr.min(1) - 0.5 - radius_px, scr.max(1) - 0.5 + radius_px
    c0, c1 = _index_range(lo[:, 0], hi[:, 0], width)
    r0, r1 = _index_range(lo[:, 1], hi[:, 1], height)
    data = (scr, edge, inv_len, tri[..., 2] / tri[..., 3])
    return data, _mask_box(jnp.stack([c0, c1, r0, r1], -1), ok)


def _bin_faces(box, tiles, tiles_x, tile, capacity, first):
    """Per tile, the faces ranked first .. first + capacity - 1 (ascending ids) among those
    whose pixel box [F, 4] touches it: [T, capacity] int32 (-1 = empty), T = tiles (the
    image's tiles in row-major order, tiles_x a row, then padding tiles below the image,
    which no face touches); and how many faces touch each tile: [T] int32. Cost T x F, in
    chunks of tiles (_bin_batch)."""
    ty, tx = jnp.divmod(jnp.arange(tiles, dtype=jnp.int32), tiles_x)

    def one_tile(origin):
        row, col = origin
        hit = ((box[:, 0] < col + tile) & (box[:, 1] >= col) & (box[:, 0] <= box[:, 1])
               & (box[:, 2] < row + tile) & (box[:, 3] >= row) & (box[:, 2] <= box[:, 3]))
        rank = jnp.cumsum(hit, dtype=jnp.int32) - 1
        ids = jnp.nonzero(hit & (rank >= first), size=capacity, fill_value=-1)[0]
        return ids.astype(jnp.int32), hit.sum(dtype=jnp.int32)

    return lax.map(one_tile, (ty * tile, tx * tile), batch_size=_bin_batch(tiles, box))


def _tile_batches(tiles, most):
    """(padded tile count, tiles per lax.map step): at most `most` tiles a step, in as few
    steps as that allows, the count padded to a whole number of steps (fewer than one
    padding tile per step)."""
    steps = -(-tiles // max(1, min(tiles, most)))
    batch = -(-tiles // steps)
    return steps * batch, batch


def _bin_batch(tiles, box):
    """Tiles binned per lax.map step: at most BIN_ELEMENTS (tile, face) pairs, and a
    divisor of `tiles`, so that lax.map has no remainder to compile a second body for."""
    batch = max(1, min(tiles, BIN_ELEMENTS // max(box.shape[0], 1)))
    while tiles % batch:
        batch -= 1
    return batch


def _owns_edge(e, a, b, s):
    """The top-left tie rule of a pixel centre exactly on an edge (candidates._owns_edge):
    [P, C] bool."""
    a, b = jnp.where(s < 0.0, -a, a), jnp.where(s < 0.0, -b, b)
    return (e != 0.0) | (a > 0.0) | ((a == 0.0) & (b < 0.0))


def _hard_keys(data, x, y):
    """NDC depth of each (pixel, face) pair, +inf where the face does not cover the pixel
    (candidates._covered_depth). data: per-face arrays gathered to [C, ...]; x, y: [P, 1]
    NDC pixel centres. -> [P, C]."""
    coeffs, corner_w, corner_z = data
    e = [_rounded(coeffs[:, i, 0] * x) + _rounded(coeffs[:, i, 1] * y) + coeffs[:, i, 2]
         for i in range(3)]
    s = (e[0] + e[1]) + e[2]
    inside = (s != 0.0) & ~((e[0] * s < 0.0) | (e[1] * s < 0.0) | (e[2] * s < 0.0))
    for i in range(3):
        inside &= _owns_edge(e[i], coeffs[:, i, 0], coeffs[:, i, 1], s)
    w = _dot3(*e, *corner_w.T)
    z = _dot3(*e, *corner_z.T) / w
    covered = inside & ~(w * s <= 0.0) & (z >= -1.0) & (z <= 1.0)
    return jnp.where(covered, z, jnp.inf)


def _segment_dist2(px, py, a, e, inv_len2):
    """Squared distance from pixel (px, py) to the segment from a [C, 2] along e [C, 2]
    (candidates._segment_dist2)."""
    rx, ry = px - a[:, 0], py - a[:, 1]
    t = jnp.clip((_rounded(rx * e[:, 0]) + _rounded(ry * e[:, 1])) * inv_len2, 0.0, 1.0)
    dx, dy = rx - _rounded(t * e[:, 0]), ry - _rounded(t * e[:, 1])
    return _rounded(dx * dx) + _rounded(dy * dy)


def _soft_fragment(data, px, py, radius_px):
    """(NDC depth [P, C], +inf out of reach; signed squared distance [P, C], positive
    inside) of each (pixel, face) pair (candidates._soft_block); px, py: [P, 1]."""
    scr, edge, inv_len, zndc = data
    sx, sy = scr[..., 0], scr[..., 1]
    b = [_mul_sub(sx[:, j] - px, sy[:, k] - py, sx[:, k] - px, sy[:, j] - py)
         for j, k in zip(NEXT, PREV, strict=True)]
    sign = jnp.where((b[0] + b[1]) + b[2] > 0.0, 1.0, -1.0)
    line = jnp.minimum(jnp.minimum(b[0] * inv_len[:, 1], b[1] * inv_len[:, 2]),
                       b[2] * inv_len[:, 0])
    d2 = jnp.minimum(jnp.minimum(
        _segment_dist2(px, py, scr[:, 0], edge[:, 0], inv_len[:, 0] ** 2),
        _segment_dist2(px, py, scr[:, 1], edge[:, 1], inv_len[:, 1] ** 2)),
        _segment_dist2(px, py, scr[:, 2], edge[:, 2], inv_len[:, 2] ** 2))
    inside = (b[0] * sign >= 0.0) & (b[1] * sign >= 0.0) & (b[2] * sign >= 0.0)
    w = [jnp.maximum(bi * sign, 0.0) for bi in b]
    z = _dot3(*w, *zndc.T) / ((w[0] + w[1]) + w[2])
    reach = ~(line * sign < -radius_px) & (inside | ~(d2 > radius_px * radius_px))
    reach &= (z >= -1.0) & (z <= 1.0)
    return jnp.where(reach, z, jnp.inf), jnp.where(inside, d2, -d2)


def _depth_logit(z_ndc, near, far, gamma, perspective):
    """zt / gamma of soft_blend from NDC depth (candidates._depth_logit)."""
    if perspective:
        inv_depth = ((far + near) - _rounded(z_ndc * (far - near))) / (2.0 * far * near)
    else:
        inv_depth = 2.0 / (_rounded(z_ndc * (far - near)) + (far + near))
    zt = (inv_depth - 1.0 / far) / (1.0 / near - 1.0 / far)
    return jnp.clip(zt, 0.0, 1.0) / gamma


def _coverage_logit(signed_d2, sigma):
    """log_sigmoid(d2 / sigma), in the host's two branches (candidates._fragment_key)."""
    x = signed_d2 / sigma
    return jnp.where(x >= 0.0, -jnp.log1p(jnp.exp(-jnp.abs(x))),
                     x - jnp.log1p(jnp.exp(jnp.minimum(x, 0.0))))


def _soft_keys(data, px, py, radius_px, sigma, gamma, near, far, perspective):
    """Ranking key -(log D + zt / gamma) of each (pixel, face) pair, +inf out of reach:
    [P, C]."""
    z, signed_d2 = _soft_fragment(data, px, py, radius_px)
    key = -_depth_logit(z, near, far, gamma, perspective) - _coverage_logit(signed_d2, sigma)
    return jnp.where(z < jnp.inf, key, jnp.inf)


def _merge(keys, ids, best_keys, best_ids):
    """The k = best_keys.shape[-1] smallest of a pass's keys [P, C] (faces ids [C]) and
    the earlier passes' best (best_keys, best_ids [P, k]), equal keys in list order
    (the earlier passes' first, then ascending ids): (keys, ids) [P, k]."""
    keys = jnp.where(keys == 0.0, 0.0, keys)   # -0.0 and 0.0 tie, as in the host
    keys = jnp.concatenate([best_keys, keys], -1)
    ids = jnp.concatenate([best_ids, jnp.broadcast_to(ids, keys.shape[:1] + ids.shape)], -1)
    _, slot = lax.top_k(-keys, best_keys.shape[-1])
    return jnp.take_along_axis(keys, slot, -1), jnp.take_along_axis(ids, slot, -1)


def _depth_after(depth, face, other_depth, other_face):
    """candidates._depth_after elementwise: (depth, face) comes after (other_depth,
    other_face) in hard raster's order (farther by more than DEPTH_TIE, or tied and of a
    higher face index)."""
    return ((depth > other_depth + DEPTH_TIE)
            | ((depth >= other_depth - DEPTH_TIE) & (face > other_face)))


def _insert_nearest(best, fragment):
    """candidates._insert_nearest for every pixel at once: the fragment (depth [P], +inf
    where it does not cover the pixel; face [P]) inserted into the lists best = (depths,
    ids) [P, k] (entries first, +inf after), each in hard raster's order."""
    depths, ids = best
    depth, face = fragment[0], fragment[1][:, None]
    k = depths.shape[-1]
    slots = jnp.arange(k)
    full = depths[:, -1] < jnp.inf
    start = jnp.where(full, k - 1, jnp.sum(depths < jnp.inf, -1))  # where the host starts
    rejected = (depth == jnp.inf) | (full & _depth_after(depth, face[:, 0], depths[:, -1],
                                                          ids[:, -1]))
    # the host moves the fragment forward past every entry after it, from `start` on
    stays = (slots < start[:, None]) & ~_depth_after(depths, ids, depth[:, None], face)
    slot = jnp.max(jnp.where(stays, slots + 1, 0), -1)[:, None]
    moved = (slots > slot) & (slots <= start[:, None])
    shift = lambda a: jnp.concatenate([a[:, :1], a[:, :-1]], -1)  # entry j - 1 at j
    new = [jnp.where(slots == slot, value, jnp.where(moved, shift(a), a))
           for a, value in ((depths, depth[:, None]), (ids, face))]
    return tuple(jnp.where(rejected[:, None], a, b) for a, b in zip(best, new, strict=True))


def _insert_pass(keys, ids, best_keys, best_ids):
    """A pass's depths [P, C] (faces ids [C], ascending) inserted one face at a time into
    the earlier passes' lists (best_keys, best_ids [P, k]), as the host inserts them: (keys,
    ids) [P, k]. Hard raster's order has ties within DEPTH_TIE, which no sort by key
    (top_k) can express, and inserting in the host's order gives the host's lists even
    where ties chain. Each pixel's covering faces are first packed to the front, in id
    order, so the loop runs as many steps as the most covered pixel has faces, not C."""
    covers = keys < jnp.inf
    rank = jnp.where(covers, jnp.cumsum(covers, -1) - 1, keys.shape[-1])  # out: dropped
    rows = jnp.arange(keys.shape[0])[:, None]
    packed_keys = jnp.full_like(keys, jnp.inf).at[rows, rank].set(keys, mode="drop")
    packed_ids = jnp.full(keys.shape, -1, ids.dtype).at[rows, rank].set(
        jnp.broadcast_to(ids, keys.shape), mode="drop")
    step = lambda i, best: _insert_nearest(best, (packed_keys[:, i], packed_ids[:, i]))
    return lax.fori_loop(0, covers.sum(-1).max(), step, (best_keys, best_ids))


def _tile_pixels(origin, tile, width, height, dtype):
    """Pixel (row, col) [P, 1] int32 of a tile at origin (row0, col0), P = tile^2, with
    the host's NDC centres (x, y) and pixel centres (px, py) [P, 1] in dtype."""
    row0, col0 = origin
    row = (row0 + jnp.arange(tile * tile, dtype=jnp.int32) // tile)[:, None]
    col = (col0 + jnp.arange(tile * tile, dtype=jnp.int32) % tile)[:, None]
    r, c = row.astype(dtype), col.astype(dtype)
    ndc = ((2.0 * c + 1.0) / width - 1.0, 1.0 - (2.0 * r + 1.0) / height)
    return row, col, ndc, (c + 0.5, r + 0.5)


def _in_box(box, row, col):
    """[P, C] bool: the pixel lies in the face's pixel box [C, 4] (as the host loops)."""
    return (box[:, 0] <= col) & (col <= box[:, 1]) & (box[:, 2] <= row) & (row <= box[:, 3])


def search_tiles(clip, faces, near, far, radius_px, sigma, gamma, *, width, height, k,
                 soft, cull_backfaces=False, perspective=True, tile=16, capacity=64):
    """Per pixel, the ids of the k faces that reach it, best first, in pure JAX.

    clip: [V, 4] float clip coordinates (computed in their dtype); faces: [F, 3] int;
    near, far, radius_px, sigma, gamma: [] float, may be traced (radius_px, sigma and
    gamma are used in soft mode only); width, height, k, soft, cull_backfaces,
    perspective, tile, capacity: static. Hard mode (soft=False): covering faces, nearest
    first by NDC depth. Soft mode: faces within radius_px pixels, ranked by their
    soft_blend weight (see candidates.find_candidates, whose results this reproduces;
    unlike it, the mode is chosen by `soft`, not by radius_px > 0).
    Returns (face_ids [height, width, k] int32, -1 = empty; dropped [] int32: reaching
    fragments beyond the k kept). capacity: faces per tile and pass (module docstring).
    """
    clip, near, far, radius_px, sigma, gamma = lax.stop_gradient(
        (clip, near, far, radius_px, sigma, gamma))
    dtype = clip.dtype if jnp.issubdtype(clip.dtype, jnp.floating) else jnp.float32
    clip = clip.astype(dtype)
    near, far, radius_px, sigma, gamma = (jnp.asarray(v, dtype)
                                          for v in (near, far, radius_px, sigma, gamma))
    faces = jnp.asarray(faces, jnp.int32)
    if soft:
        data, box = _soft_faces(clip, faces, width, height, cull_backfaces, radius_px)
    else:
        data, box = _hard_faces(clip, faces, width, height, cull_backfaces)
    tiles_x, tiles_y = -(-width // tile), -(-height // tile)
    tiles, batch = _tile_batches(tiles_x * tiles_y, TILE_ELEMENTS // (tile * tile * capacity))
    origins = jnp.divmod(jnp.arange(tiles, dtype=jnp.int32), tiles_x)
    origins = (origins[0] * tile, origins[1] * tile)

    def one_tile(args):
        ids, origin, best_keys, best_ids, reached = args
        row, col, ndc, centre = _tile_pixels(origin, tile, width, height, dtype)
        face_data = jax.tree.map(lambda a: a[jnp.maximum(ids, 0)], data)
        if soft:
            keys = _soft_keys(face_data, *centre, radius_px, sigma, gamma, near, far,
                              perspective)
        else:
            keys = _hard_keys(face_data, *ndc)
        tested = _in_box(box[jnp.maximum(ids, 0)], row, col) & (ids >= 0)
        keys = jnp.where(tested, keys, jnp.inf)
        reached = reached + (keys < jnp.inf).sum(-1, dtype=jnp.int32)
        merge = _merge if soft else _insert_pass
        return (*merge(keys, ids, best_keys, best_ids), reached)

    def search_pass(state):
        # pass p: the faces ranked p * capacity ... in each tile; the first pass also
        # says how many passes the most crowded tile needs
        p, passes, *best = state
        tile_faces, touching = _bin_faces(box, tiles, tiles_x, tile, capacity, p * capacity)
        passes = jnp.where(p == 0, (touching.max() + capacity - 1) // capacity, passes)
        best = lax.map(one_tile, (tile_faces, origins, *best), batch_size=batch)
        return (p + 1, passes, *best)

    pixels = (tiles, tile * tile)
    empty = (jnp.full(pixels + (k,), jnp.inf, dtype), jnp.full(pixels + (k,), -1, jnp.int32),
             jnp.zeros(pixels, jnp.int32))
    _, _, best_keys, ids, reached = lax.while_loop(lambda state: state[0] < state[1],
                                                   search_pass,
                                                   (jnp.int32(0), jnp.int32(1), *empty))
    image_tiles = tiles_x * tiles_y
    best_keys, ids, reached = best_keys[:image_tiles], ids[:image_tiles], reached[:image_tiles]
    ids = jnp.where(best_keys < jnp.inf, ids, -1)
    ids = ids.reshape(tiles_y, tiles_x, tile, tile, k).transpose(0, 2, 1, 3, 4)
    ids = ids.reshape(tiles_y * tile, tiles_x * tile, k)[:height, :width]
    return ids, jnp.maximum(reached - k, 0).sum()

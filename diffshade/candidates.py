"""Candidate search: which faces reach which pixel, nearest first (non-differentiable).

Runs on the host (called through `jax.pure_callback` by raster.py) as a numba-compiled
loop over each face's screen bounding box, so its cost grows with the number of
(pixel, nearby face) pairs, never with pixels x faces, and it allocates only the output.

Coverage uses 2D homogeneous rasterization (Olano & Greer 1997): with v_i = (X, Y, W)
of the clip-space vertices and p = (x_ndc, y_ndc, 1), the edge functions
e_i = (v_j x v_k) . p give the perspective-correct barycentrics e_i / sum(e) directly, and
a pixel is covered when all barycentrics are >= 0, the point is in front of the eye
(det / sum(e) > 0) and its NDC depth lies in [-1, 1]. This is exactly OpenGL's clipping
against the near and far planes, done per pixel: faces that cross the near plane are
clipped, not culled, and no new triangles are made.

Soft mode (SoftRas) grows each face's footprint by `radius_px` pixels: a pixel outside
the projected triangle is a candidate when its squared distance to the triangle is at most
radius_px^2, with the depth taken at the clamped barycentrics. Faces that cross the near
plane are culled in soft mode (their screen-space triangle is not defined).

Each pixel keeps its k nearest faces (by NDC depth) in a small sorted list; every candidate
fragment that does not fit is counted in `dropped`.
"""

import numba
import numpy as np
from numba import prange

EDGES = ((1, 2), (2, 0), (0, 1))


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
    return int(max(a, 0.0)), int(min(b, size - 1.0))


@numba.njit(cache=True, nogil=True)
def _insert(ids, keys, pixel, face, key):
    """Insert (face, key) into pixel's ascending list; returns 1 if a fragment fell off."""
    k = ids.shape[1]
    if ids[pixel, k - 1] >= 0 and key >= keys[pixel, k - 1]:
        return 1
    fell = 1 if ids[pixel, k - 1] >= 0 else 0
    slot = k - 1
    while slot > 0 and (ids[pixel, slot - 1] < 0 or keys[pixel, slot - 1] > key):
        ids[pixel, slot] = ids[pixel, slot - 1]
        keys[pixel, slot] = keys[pixel, slot - 1]
        slot -= 1
    while slot > 0 and ids[pixel, slot - 1] < 0:
        slot -= 1
    ids[pixel, slot] = face
    keys[pixel, slot] = key
    return fell


@numba.njit(cache=True, nogil=True)
def _covered_depth(coeffs, tri, f, x, y):
    """NDC depth of the pixel on face f, or +inf when the face does not cover it."""
    e0 = coeffs[f, 0, 0] * x + coeffs[f, 0, 1] * y + coeffs[f, 0, 2]
    e1 = coeffs[f, 1, 0] * x + coeffs[f, 1, 1] * y + coeffs[f, 1, 2]
    e2 = coeffs[f, 2, 0] * x + coeffs[f, 2, 1] * y + coeffs[f, 2, 2]
    s = e0 + e1 + e2
    if s == 0.0 or e0 * s < 0.0 or e1 * s < 0.0 or e2 * s < 0.0:
        return np.inf
    w = e0 * tri[f, 0, 3] + e1 * tri[f, 1, 3] + e2 * tri[f, 2, 3]
    if w * s <= 0.0:
        return np.inf
    z = (e0 * tri[f, 0, 2] + e1 * tri[f, 1, 2] + e2 * tri[f, 2, 2]) / w
    return z if -1.0 <= z <= 1.0 else np.inf


@numba.njit(cache=True, nogil=True)
def _batch_outputs(views, pixels, k, bands):
    """Per view: the K nearest ids (-1: none) and keys (inf) per pixel, and the count of
    candidates each row band dropped."""
    return (np.full((views, pixels, k), -1, np.int32), np.full((views, pixels, k), np.inf),
            np.zeros((views, bands), np.int64))


@numba.njit(cache=True, nogil=True, parallel=True)
def _search_hard(clips, faces, width, height, k, cull_backfaces, bands):
    views = clips.shape[0]
    all_ids, all_keys, all_dropped = _batch_outputs(views, width * height, k, bands)
    # one item per (view, band): the views of a batch share one parallel loop
    for item in prange(views * bands):
        view, band = item // bands, item % bands
        clip, ids, keys, dropped = clips[view], all_ids[view], all_keys[view], all_dropped[view]
        band_r0, band_r1 = _band_rows(band, bands, height)
        tri, coeffs, box = np.empty((1, 3, 4)), np.empty((1, 3, 3)), np.empty(4)
        for f in range(faces.shape[0]):
            det = _face_setup(clip, faces, f, tri[0], coeffs[0])
            if not np.isfinite(det) or det == 0.0 or (cull_backfaces and det < 0.0):
                continue
            if not _near_clipped_bbox(tri[0], box):
                continue
            c0, c1 = _pixel_range(box[0], box[1], width, 0.0, False)
            r0, r1 = _pixel_range(box[2], box[3], height, 0.0, True)
            for row in range(max(r0, band_r0), min(r1, band_r1) + 1):
                y = 1.0 - (2.0 * row + 1.0) / height
                for col in range(c0, c1 + 1):
                    z = _covered_depth(coeffs, tri, 0, (2.0 * col + 1.0) / width - 1.0, y)
                    if z < np.inf:
                        dropped[band] += _insert(ids, keys, row * width + col, f, z)
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


@numba.njit(cache=True, nogil=True)
def _soft_fragment(scr, edge, inv_len, zndc, px, py, radius_px):
    """(NDC depth, signed squared distance in pixels^2, positive inside) of the fragment of
    a screen triangle at pixel p; depth is +inf when the pixel is out of reach.

    scr: [3, 2] vertex pixel coordinates; edge: [3, 2] scr[i + 1] - scr[i]; inv_len: [3]
    1 / edge lengths; zndc: [3].
    Inside, depth is taken at the barycentrics (NDC z is affine in screen space); outside,
    at the clamped ones.
    """
    b0 = (scr[1, 0] - px) * (scr[2, 1] - py) - (scr[2, 0] - px) * (scr[1, 1] - py)
    b1 = (scr[2, 0] - px) * (scr[0, 1] - py) - (scr[0, 0] - px) * (scr[2, 1] - py)
    b2 = (scr[0, 0] - px) * (scr[1, 1] - py) - (scr[1, 0] - px) * (scr[0, 1] - py)
    sign = 1.0 if b0 + b1 + b2 > 0.0 else -1.0
    # signed distances to the edge lines: a cheap necessary test before the exact one
    if min(b0 * inv_len[1], b1 * inv_len[2], b2 * inv_len[0]) * sign < -radius_px:
        return np.inf, 0.0
    d2 = min(_segment_dist2(px, py, scr[0, 0], scr[0, 1], edge[0, 0], edge[0, 1], inv_len[0] ** 2),
             _segment_dist2(px, py, scr[1, 0], scr[1, 1], edge[1, 0], edge[1, 1], inv_len[1] ** 2),
             _segment_dist2(px, py, scr[2, 0], scr[2, 1], edge[2, 0], edge[2, 1], inv_len[2] ** 2))
    inside = b0 * sign >= 0.0 and b1 * sign >= 0.0 and b2 * sign >= 0.0
    if not inside and d2 > radius_px * radius_px:
        return np.inf, 0.0
    w0, w1, w2 = max(b0 * sign, 0.0), max(b1 * sign, 0.0), max(b2 * sign, 0.0)
    z = (w0 * zndc[0] + w1 * zndc[1] + w2 * zndc[2]) / (w0 + w1 + w2)
    return z, (d2 if inside else -d2)


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


@numba.njit(cache=True, nogil=True)
def _coverage_logit(signed_d2, sigma):
    """log D = log_sigmoid(d2 / sigma) of soft_blend (<= 0)."""
    x = signed_d2 / sigma
    return -np.log1p(np.exp(-x)) if x >= 0.0 else x - np.log1p(np.exp(x))


@numba.njit(cache=True, nogil=True, parallel=True)
def _search_soft(clips, faces, width, height, k, cull_backfaces, radii, params, perspective,
                 bands):
    views = clips.shape[0]
    all_ids, all_keys, all_dropped = _batch_outputs(views, width * height, k, bands)
    # one item per (view, band): the views of a batch share one parallel loop
    for item in prange(views * bands):
        view, band = item // bands, item % bands
        clip, ids, keys, dropped = clips[view], all_ids[view], all_keys[view], all_dropped[view]
        radius_px = radii[view]
        soft = (params[view, 0], params[view, 1], params[view, 2], params[view, 3], perspective)
        band_r0, band_r1 = _band_rows(band, bands, height)
        tri, coeffs = np.empty((3, 4)), np.empty((3, 3))
        scr, edge, zndc, inv_len = np.empty((3, 2)), np.empty((3, 2)), np.empty(3), np.empty(3)
        for f in range(faces.shape[0]):
            det = _face_setup(clip, faces, f, tri, coeffs)
            if not np.isfinite(det) or det == 0.0 or (cull_backfaces and det < 0.0):
                continue
            if min(tri[0, 2] + tri[0, 3], tri[1, 2] + tri[1, 3], tri[2, 2] + tri[2, 3]) < 0.0:
                continue
            for i in range(3):
                scr[i, 0] = (tri[i, 0] / tri[i, 3] + 1.0) * width / 2.0
                scr[i, 1] = (1.0 - tri[i, 1] / tri[i, 3]) * height / 2.0
            r0 = int(max(np.ceil(scr[:, 1].min() - 0.5 - radius_px), band_r0))
            r1 = int(min(np.floor(scr[:, 1].max() - 0.5 + radius_px), band_r1))
            if r0 > r1:
                continue
            area2 = ((scr[1, 0] - scr[0, 0]) * (scr[2, 1] - scr[0, 1])
                     - (scr[2, 0] - scr[0, 0]) * (scr[1, 1] - scr[0, 1]))
            if area2 == 0.0:
                continue
            for i in range(3):
                j = (i + 1) % 3
                zndc[i] = tri[i, 2] / tri[i, 3]
                edge[i, 0], edge[i, 1] = scr[j, 0] - scr[i, 0], scr[j, 1] - scr[i, 1]
                length = np.hypot(edge[i, 0], edge[i, 1])
                inv_len[i] = 1.0 / length if length > 0.0 else 0.0
            c0 = int(max(np.ceil(scr[:, 0].min() - 0.5 - radius_px), 0.0))
            c1 = int(min(np.floor(scr[:, 0].max() - 0.5 + radius_px), width - 1.0))
            for row in range(r0, r1 + 1):
                for col in range(c0, c1 + 1):
                    z, sd2 = _soft_fragment(scr, edge, inv_len, zndc, col + 0.5, row + 0.5,
                                            radius_px)
                    if not (z < np.inf and -1.0 <= z <= 1.0):
                        continue
                    # the key is -(log D + zt / gamma) >= -zt / gamma: a full list whose
                    # last key beats that bound rejects the fragment without the logarithm
                    pixel = row * width + col
                    key = -_depth_logit(z, soft)
                    if ids[pixel, k - 1] >= 0 and key >= keys[pixel, k - 1]:
                        dropped[band] += 1
                        continue
                    key -= _coverage_logit(sd2, soft[0])
                    dropped[band] += _insert(ids, keys, pixel, f, key)
    return all_ids, all_dropped.sum(1)


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
    bands = min(height, 2 * numba.get_num_threads())
    faces = np.ascontiguousarray(faces, np.int64)
    if np.any(radii > 0.0):
        params = np.stack([per_view(sigma), per_view(gamma), per_view(near), per_view(far)], 1)
        ids, dropped = _search_soft(clips, faces, width, height, k, cull_backfaces, radii,
                                    params, bool(perspective), bands)
    else:
        ids, dropped = _search_hard(clips, faces, width, height, k, cull_backfaces, bands)
    ids, dropped = ids.reshape(views, height, width, k), dropped.astype(np.int32)
    return (ids, dropped) if batched else (ids[0], dropped[0])

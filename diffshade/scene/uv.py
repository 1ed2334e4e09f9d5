"""Texture coordinates of meshes: seams, welding, and the built-in shapes' UV maps (NumPy).

A vertex has one UV, so where a surface's UV map is cut (a seam: the sphere's date line,
the torus's two closing rings) the vertices on the cut are split, one copy per UV, and
the faces on either side use their own copy. `split_by_corner_uv` does that from one UV
per face corner. The copies share a position, so normals computed over the split mesh
would show the cut; `weld` finds the vertices that share a position, over which
diffshade.scene.mesh computes normals instead.

UVs: u across, v up the image (v = 0 its bottom row: OBJ / OpenGL).
"""

import numpy as np

__all__ = ["sphere_corner_uv", "split_by_corner_uv", "torus_corner_uv", "weld"]


def weld(vertices):
    """(ids [V] int: the welded vertex of each vertex, count of welded vertices) for
    vertices [V, 3]: vertices at the same position share one id."""
    _, ids = np.unique(np.asarray(vertices), axis=0, return_inverse=True)
    ids = ids.reshape(-1)
    return ids, int(ids.max()) + 1


def split_by_corner_uv(faces, corner_uv):
    """(source [V'] int: the original vertex of each new vertex, faces [F, 3] int32 over
    the new vertices, uv [V', 2] float64) for faces [F, 3] int and one UV per corner
    corner_uv [F, 3, 2]: a vertex whose corners carry different UVs is split, one copy
    per UV."""
    keys = np.column_stack([faces.reshape(-1).astype(np.float64), corner_uv.reshape(-1, 2)])
    unique, inverse = np.unique(keys, axis=0, return_inverse=True)
    return (unique[:, 0].astype(np.int64), inverse.reshape(faces.shape).astype(np.int32),
            unique[:, 1:])


def _unwrap(corner_uv, reference):
    """corner_uv [F, 3, 2] moved by whole periods to within half a period of
    reference [F, 1, 2] (so a face across a seam does not span the whole map)."""
    # a whole number added: the UVs of faces that do not cross a seam stay bit-exact,
    # so the copies of a vertex that differ only by rounding are not split
    return corner_uv + np.round(reference - corner_uv)


def _longitude(points):
    """u in [0, 1) of points [..., 3] around the y axis; u = 0.5 faces +z."""
    return (0.5 + np.arctan2(points[..., 0], points[..., 2]) / (2 * np.pi)) % 1.0


def sphere_corner_uv(vertices, faces):
    """Longitude / latitude UV [F, 3, 2] of each corner of unit-sphere faces: u around the
    y axis (0.5 facing +z, the seam at -z), v = 0.5 + asin(y) / pi (1 at the north pole,
    y up). Faces across the seam get u continuing past 1 or below 0 (read as wrapped);
    a pole, where u is undefined, takes the mean u of its face's other corners."""
    corners = vertices[faces]
    latitude = 0.5 + np.arcsin(np.clip(corners[..., 1], -1.0, 1.0)) / np.pi
    u = _longitude(corners)
    centre = _longitude(corners.mean(1))[:, None]
    u = _unwrap(u, centre)
    pole = np.hypot(corners[..., 0], corners[..., 2]) < 1e-9
    others = np.where(pole, 0.0, u).sum(1, keepdims=True) / np.maximum((~pole).sum(1), 1)[:, None]
    u = np.where(pole, others, u)
    return np.stack([u, latitude], -1)


def torus_corner_uv(faces, major_segments, minor_segments):
    """UV [F, 3, 2] of each corner of a torus grid (vertex id = i * minor_segments + j):
    u = i / major_segments around the y axis, v = j / minor_segments around the tube,
    the closing faces reaching u = 1 and v = 1 (so every UV is in [0, 1])."""
    i, j = np.divmod(faces, minor_segments)
    uv = np.stack([i / major_segments, j / minor_segments], -1)
    return _unwrap(uv, uv.max(1, keepdims=True))

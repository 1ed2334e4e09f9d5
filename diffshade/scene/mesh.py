"""Triangle meshes: the `Mesh` pytree, its builders, and differentiable normals.

`Mesh` holds vertices [V, 3] float, faces [F, 3] int32 (counter-clockwise = front) and
unit vertex normals [V, 3] float, and optionally texture coordinates uv [V, 2] float
(OBJ / OpenGL convention: v = 0 at the bottom row of the image; diffshade.scene.uv). Where
a UV map is cut (a seam) the vertices are split, one copy per UV, and normals are
computed over the positions welded back together, so that a seam never shows in the
shading. Its constructor is cheap and unchecked, because JAX
transforms rebuild it from tracers; the public builders, and `check_mesh` for a Mesh
built otherwise, validate their input with one function (`_check_arrays`) and raise
ValueError naming the argument, the value and what was expected. Builders keep float32
input float32 and store everything else (float64 arrays, lists, files, generated shapes)
in the default float dtype: float64 under `jax_enable_x64`, else float32. `face_normals`,
`face_areas`, `vertex_normals` and `transform_mesh` are pure jax.numpy, differentiable and
jit-able, finite in value and gradient on degenerate faces and unused vertices (whose
normals are zero). Crease splitting is numpy work done once, at construction time.
"""

import dataclasses
import itertools
import math
import numbers
import os
import re
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from diffshade import budget
from diffshade.numerics import (
    float_dtype,
    float_dtype_of,
    representable,
    safe_norm,
    safe_normalize,
    tiny,
)
from diffshade.scene.uv import sphere_corner_uv, split_by_corner_uv, torus_corner_uv, weld

__all__ = [
    "Mesh", "box", "check_mesh", "face_areas", "face_normals", "icosphere", "load_mesh",
    "mesh_from_arrays", "mesh_from_trimesh", "model_matrix", "torus", "transform_mesh",
    "vertex_normals",
]  # fmt: skip

WEIGHTINGS = ("angle", "area", "uniform")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Mesh:
    """A triangle mesh; every field is a pytree leaf.

    vertices: [V, 3] float (float32, or float64 under x64) model-space positions.
    faces: [F, 3] int32 vertex indices, counter-clockwise = front.
    normals: [V, 3] float, vertices' dtype, unit vertex normals (zero where undefined).
    uv: [V, 2] float, vertices' dtype, texture coordinates (v = 0 at the image's bottom),
    or None (a mesh without UVs, which no texture can be mapped onto).
    """

    vertices: jax.Array
    faces: jax.Array
    normals: jax.Array
    uv: jax.Array | None = None


def face_normals(vertices, faces):
    """Unit normals [F, 3] float of faces [F, 3] int over vertices [V, 3] float.

    normalize(cross(v1 - v0, v2 - v0)): counter-clockwise corners face the viewer.
    Degenerate faces get a zero normal with a finite gradient.
    """
    tri = vertices[faces]
    return safe_normalize(jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))


def face_areas(vertices, faces):
    """Areas [F] float of faces [F, 3] int over vertices [V, 3] float (0 if degenerate)."""
    tri = vertices[faces]
    return 0.5 * safe_norm(jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))


def _corner_angles(vertices, faces):
    """Interior angle [F, 3] float, in radians, of each face at each of its corners.

    atan2(|e1 x e2|, e1 . e2) keeps its gradient finite near 0 and pi, where arccos of
    a normalized dot product does not. A corner with a zero-length edge gets 0.
    """
    tri = vertices[faces]
    e1 = jnp.roll(tri, -1, axis=1) - tri
    e2 = jnp.roll(tri, -2, axis=1) - tri
    sin_part = safe_norm(jnp.cross(e1, e2))
    cos_part = jnp.sum(e1 * e2, axis=-1)
    ok = sin_part**2 + cos_part**2 > tiny(tri.dtype) ** 2
    angle = jnp.arctan2(jnp.where(ok, sin_part, 0.0), jnp.where(ok, cos_part, 1.0))
    return jnp.where(ok, angle, 0.0)


def _corner_weights(vertices, faces, weighting):
    """Weight [F, 3] float of each face corner in its vertex normal (see vertex_normals)."""
    _check_weighting(weighting)
    if weighting == "angle":
        return _corner_angles(vertices, faces)
    if weighting == "area":
        return jnp.repeat(face_areas(vertices, faces)[:, None], 3, axis=1)
    return jnp.ones(faces.shape, vertices.dtype)


def vertex_normals(vertices, faces, weighting="angle"):
    """Unit vertex normals [V, 3] float for vertices [V, 3] float and faces [F, 3] int.

    Each is the normalized weighted sum of the unit normals of the faces sharing the
    vertex. weighting: "angle" (default) weighs a face by its interior angle at the
    vertex (Thürmer & Wüthrich 1998), the only choice that does not depend on how the
    surface is triangulated: splitting a face leaves the normals of its corners as they
    were. "area" weighs by face area, "uniform" by 1. A vertex used by no face, or whose
    face normals cancel, gets a zero normal; values and gradients stay finite. Under jit,
    make weighting static.
    """
    # the normals do not change when the mesh is scaled: computed on the mesh scaled to
    # a unit box, the cross products' squares cannot overflow (float32 did from ~1e19,
    # giving NaN normals for finite vertices); the scale is a constant to derivatives
    # (zero-degree homogeneity: d n(v / s) / dv at fixed s is d n / dv)
    extent = jax.lax.stop_gradient(jnp.max(jnp.abs(vertices)))
    vertices = vertices / jnp.where(extent > 0.0, extent, 1.0)
    weights = _corner_weights(vertices, faces, weighting)
    weighted = weights[..., None] * face_normals(vertices, faces)[:, None, :]
    summed = jax.ops.segment_sum(
        weighted.reshape(-1, 3), faces.reshape(-1), num_segments=vertices.shape[0]
    )
    return safe_normalize(summed)


def _check_weighting(weighting):
    if weighting not in WEIGHTINGS:
        raise ValueError(f"weighting: {weighting!r}; expected one of {WEIGHTINGS}")


def _is_real(value):
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _as_array(values, name, expected):
    """np.asarray(values), or ValueError naming `name` for a ragged sequence."""
    try:
        return np.asarray(values)
    except ValueError:
        raise ValueError(f"{name}: got a ragged sequence; expected {expected}") from None


def _check_points(values, name, dtype):
    """values as an [N, 3] float64 numpy array, finite once stored as `dtype`, or
    ValueError naming `name`."""
    arr = _as_array(values, name, "[N, 3] real numbers")
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name}: shape {arr.shape}; expected [N, 3]")
    if not (np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)):
        raise ValueError(f"{name}: dtype {arr.dtype}; expected real numbers")
    bad = np.flatnonzero(~representable(arr, dtype).all(axis=1))
    if bad.size:
        raise ValueError(f"{name}: row {bad[0]} is {arr[bad[0]].tolist()}; expected finite "
                         f"numbers (in {np.dtype(dtype).name})")
    return arr.astype(np.float64)


def _check_faces(faces, num_vertices, name):
    """faces as an [F, 3] int32 numpy array of indices into num_vertices, F >= 1."""
    arr = _as_array(faces, name, "[F, 3] integer vertex indices")
    if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] == 0:
        raise ValueError(f"{name}: shape {arr.shape}; expected [F, 3] with F >= 1")
    if np.issubdtype(arr.dtype, np.floating):
        bad = np.flatnonzero(~np.isfinite(arr) | (arr != np.floor(arr)))
        if bad.size:
            raise ValueError(f"{name}: value {arr.flat[bad[0]]} is not an integer; "
                             "expected integer vertex indices")
    elif not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{name}: dtype {arr.dtype}; expected integer vertex indices")
    bad = np.flatnonzero((arr < 0) | (arr >= num_vertices))
    if bad.size:
        raise ValueError(
            f"{name}: index {arr.flat[bad[0]]:g} out of range for {num_vertices} vertices; "
            f"expected 0 <= index < {num_vertices}"
        )
    return arr.astype(np.int32)


class _Checked(NamedTuple):
    """Validated mesh data: vertices [V, 3] float64, faces [F, 3] int32, normals [V, 3]
    float64 or None (numpy), dtype, the float dtype the Mesh stores them in, and uv
    [V, 2] float64 or None."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None
    dtype: np.dtype
    uv: np.ndarray | None = None


def _check_uv(uv, count, name, dtype):
    """uv as a [count, 2] float64 numpy array of finite numbers, or ValueError."""
    arr = _as_array(uv, name, "[V, 2] real numbers")
    real = np.issubdtype(arr.dtype, np.floating) or np.issubdtype(arr.dtype, np.integer)
    if arr.shape != (count, 2) or not real:
        raise ValueError(f"{name}: shape {arr.shape} of {arr.dtype}; expected [{count}, 2] "
                         "real numbers, one (u, v) per vertex")
    bad = np.flatnonzero(~representable(arr, dtype).all(axis=1))
    if bad.size:
        raise ValueError(f"{name}: row {bad[0]} is {arr[bad[0]].tolist()}; expected finite "
                         "numbers")
    return arr.astype(np.float64)


def _check_arrays(vertices, faces, normals=None, name=str, uv=None):
    """The one validation of mesh data, shared by every path that builds a Mesh (arrays,
    mesh files, scene files, datasets): finite vertices (and normals) [V, 3], faces [F, 3]
    of exact integers in [0, V), F >= 1. name(field) is what errors call "vertices",
    "faces" and "normals". Raises ValueError naming the field, the value and what was
    expected."""
    dtype = float_dtype_of(vertices)
    verts = _check_points(vertices, name("vertices"), dtype)
    tris = _check_faces(faces, len(verts), name("faces"))
    if normals is not None:
        normals = _check_points(normals, name("normals"), dtype)
        if normals.shape != verts.shape:
            raise ValueError(f"{name('normals')}: shape {normals.shape}; expected "
                             f"{verts.shape} like {name('vertices')}")
    if uv is not None:
        uv = _check_uv(uv, len(verts), name("uv"), dtype)
    return _Checked(verts, tris, normals, dtype, uv)


def check_mesh(mesh, name=lambda field: f"mesh.{field}"):
    """mesh (a Mesh of concrete arrays) after `_check_arrays`, with vertices and normals
    [V, 3] in their float dtype (float32 stays float32, float64 stays float64 under x64)
    and faces [F, 3] int32; values are kept as they are (normals are not renormalized).

    For meshes built without a builder (Mesh(...) directly, a dataset's saved arrays):
    an out-of-range face index would otherwise reach the rasterizer. name(field) names
    the fields in errors ("mesh.vertices" by default).
    """
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh: got {type(mesh).__name__}; expected Mesh")
    checked = _check_arrays(mesh.vertices, mesh.faces, mesh.normals, name, mesh.uv)
    return Mesh(*_jax_arrays(*checked))


def _jax_arrays(verts, tris, normals, dtype, uv=None):
    """(vertices [V, 3] dtype, faces [F, 3] int32, normals [V, 3] dtype, uv [V, 2] dtype
    or None) as jax arrays."""
    return (jnp.asarray(verts, dtype), jnp.asarray(tris, jnp.int32), jnp.asarray(normals, dtype),
            None if uv is None else jnp.asarray(uv, dtype))


def _check_crease(crease_angle):
    if crease_angle is not None and not (_is_real(crease_angle) and 0 <= crease_angle <= 180):
        raise ValueError(f"crease_angle: {crease_angle!r}; expected None or degrees in [0, 180]")


def mesh_from_arrays(vertices, faces, normals=None, *, uv=None, weighting="angle",
                     crease_angle=None):
    """Validated Mesh from vertices [V, 3] real, faces [F, 3] integer (CCW = front).

    uv: optional [V, 2] real texture coordinates (v = 0 at the image's bottom; any
    finite value: the texture's wrap mode says what outside [0, 1] reads). Vertices
    split at a UV seam (same position, other UV) get the normals of the welded surface.

    normals: optional [V, 3] real, normalized here. Without them they are computed by
    `vertex_normals(weighting)`; with crease_angle (degrees) the vertices are first split
    along sharp edges (see `_split_creases`), which changes V. Float faces are accepted
    when they hold exact integers. Vertices and normals are stored as float32 when
    vertices are float32, else in the default float dtype (float64 under x64: float64
    input keeps its precision). Raises ValueError on any bad argument.
    """
    _check_weighting(weighting)
    _check_crease(crease_angle)
    checked = _check_arrays(vertices, faces, normals, uv=uv)
    if normals is not None:
        return _mesh_with_normals(checked, crease_angle)
    if crease_angle is not None:
        return _split_creases(checked, weighting, crease_angle)
    if checked.uv is not None:
        return _welded_normals(checked, weighting)
    vs, fs = jnp.asarray(checked.vertices, checked.dtype), jnp.asarray(checked.faces)
    return Mesh(vs, fs, vertex_normals(vs, fs, weighting))


def _welded_normals(checked, weighting):
    """Mesh with UVs whose normals are those of its positions welded (seams closed)."""
    ids, count = weld(checked.vertices)
    welded = np.zeros((count, 3))
    welded[ids] = checked.vertices
    normals = vertex_normals(jnp.asarray(welded, checked.dtype),
                             jnp.asarray(ids[checked.faces], jnp.int32), weighting)
    return Mesh(jnp.asarray(checked.vertices, checked.dtype), jnp.asarray(checked.faces),
                jnp.take(normals, jnp.asarray(ids), axis=0),
                jnp.asarray(checked.uv, checked.dtype))


def _mesh_with_normals(checked, crease_angle):
    """Mesh from `_check_arrays` output with user normals, normalized here."""
    if crease_angle is not None:
        raise ValueError(f"crease_angle: {crease_angle!r}; expected None when normals are given")
    verts, tris, normals, uv = _jax_arrays(*checked)
    return Mesh(verts, tris, safe_normalize(normals), uv)


def _smooth_corner_links(faces, face_n, cos_limit):
    """Links (a [L] int, b [L] int) between corners (id 3 * face + k) of the same vertex
    whose faces share an edge and have face normals with dot >= cos_limit."""
    flat = faces.ravel().astype(np.int64)
    start = np.arange(flat.size)
    end = start - start % 3 + (start + 1) % 3
    low = np.where(flat[start] <= flat[end], start, end)
    high = start + end - low
    key = flat[low] * (flat.max() + 1) + flat[high]
    order = np.argsort(key, kind="stable")
    # Consecutive records of one edge: its two faces (a chain of them if non-manifold).
    same = key[order[1:]] == key[order[:-1]]
    a, b = order[:-1][same], order[1:][same]
    smooth = np.einsum("ij,ij->i", face_n[a // 3], face_n[b // 3]) >= cos_limit
    a, b = a[smooth], b[smooth]
    return np.concatenate([low[a], high[a]]), np.concatenate([low[b], high[b]])


def _components(num_nodes, a, b):
    """Connected-component label [num_nodes] int (its smallest node) under links a-b."""
    labels = np.arange(num_nodes)
    while True:
        low = np.minimum(labels[a], labels[b])
        new = labels.copy()
        np.minimum.at(new, a, low)
        np.minimum.at(new, b, low)
        if np.array_equal(new, labels):
            return labels
        labels = new


def _split_creases(checked, weighting, crease_angle):
    """Mesh from `_check_arrays` output (no normals), split at creases.

    A crease is an edge whose two face normals differ by more than crease_angle degrees.
    The corners of a vertex joined through smooth edges form one smoothing group and
    share one output vertex, whose normal is the weighted normal of the group's faces;
    every other group gets a copy of the vertex. Splitting at edges, not by comparing
    every face pair around a vertex, keeps a smooth fan whole even when its far sides
    differ by more than crease_angle. Vertices used by no face are dropped. With UVs,
    edges and normals are those of the welded positions (a UV seam is no crease), and a
    vertex keeps one copy per (UV, smoothing group).
    """
    verts, tris, dtype = checked.vertices, checked.faces, checked.dtype
    vs, fs = jnp.asarray(verts, dtype), jnp.asarray(tris)
    face_n = np.asarray(face_normals(vs, fs), np.float64)
    weights = np.asarray(_corner_weights(vs, fs, weighting), np.float64).ravel()
    # float32 normals of coplanar faces differ by ~1e-7: flat regions must stay whole at 0.
    cos_limit = math.cos(math.radians(crease_angle)) - 1e-6
    welded = tris if checked.uv is None else weld(verts)[0][tris]
    group = _components(tris.size, *_smooth_corner_links(welded, face_n, cos_limit))
    _, normal_of = np.unique(welded.ravel().astype(np.int64) * tris.size + group,
                             return_inverse=True)
    summed = np.zeros((normal_of.max() + 1, 3))
    np.add.at(summed, normal_of.ravel(), weights[:, None] * np.repeat(face_n, 3, axis=0))
    corner_vertex = tris.ravel().astype(np.int64)
    _, first, inverse = np.unique(
        corner_vertex * tris.size + group, return_index=True, return_inverse=True
    )
    uv = None if checked.uv is None else jnp.asarray(checked.uv[corner_vertex[first]], dtype)
    return Mesh(
        jnp.asarray(verts[corner_vertex[first]], dtype),
        jnp.asarray(inverse.reshape(-1, 3), jnp.int32),
        safe_normalize(jnp.asarray(summed[normal_of.ravel()[first]], dtype)),
        uv,
    )


def _check_positive(value, name):
    if not (_is_real(value) and representable(value) and value > 0):
        raise ValueError(f"{name}: {value!r}; expected a finite number > 0")


def _check_count(value, name, low, high):
    is_int = isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if not (is_int and low <= value <= high):
        raise ValueError(f"{name}: {value!r}; expected an int in [{low}, {high}]")


def _check_memory(name, value, faces, shape):
    """A built-in shape of `faces` faces must fit the memory budget (diffshade.budget)."""
    budget.check(name, value, budget.mesh_bytes(faces), f"{shape} of {faces} faces",
                 faces * 3)


_PHI = (1.0 + math.sqrt(5.0)) / 2.0
_ICOSAHEDRON_VERTICES = np.array(
    [[-1, _PHI, 0], [1, _PHI, 0], [-1, -_PHI, 0], [1, -_PHI, 0],
     [0, -1, _PHI], [0, 1, _PHI], [0, -1, -_PHI], [0, 1, -_PHI],
     [_PHI, 0, -1], [_PHI, 0, 1], [-_PHI, 0, -1], [-_PHI, 0, 1]]
)  # fmt: skip
_ICOSAHEDRON_FACES = np.array(
    [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
     [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
     [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
     [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
)  # fmt: skip


def _subdivide(verts, tris):
    """One `subSphere` step on unit verts [V, 3] float64 and tris [F, 3] int.

    (v1, v2, v3) -> (v1, v12, v31), (v12, v2, v23), (v31, v12, v23), (v31, v23, v3),
    midpoints pushed onto the unit sphere and shared by the two faces of their edge.
    """
    edges = np.sort(tris[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    unique, inverse = np.unique(edges, axis=0, return_inverse=True)
    mids = verts[unique[:, 0]] + verts[unique[:, 1]]
    mids /= np.linalg.norm(mids, axis=1, keepdims=True)
    v12, v23, v31 = (inverse.reshape(-1, 3) + len(verts)).T
    v1, v2, v3 = tris.T
    new = np.stack([v1, v12, v31, v12, v2, v23, v31, v12, v23, v31, v23, v3], axis=1)
    return np.concatenate([verts, mids]), new.reshape(-1, 3)


def icosphere(subdivisions=3, radius=1.0, uv=False):
    """Watertight sphere Mesh centred at the origin, from the regular icosahedron.

    subdivisions: int in [0, 8]; V = 10 * 4**s + 2, F = 20 * 4**s. Normals are the exact
    sphere normals (unit positions), as `glNormal` in the lecture's `subSphere`.
    uv: give it a longitude / latitude UV map (diffshade.scene.uv.sphere_corner_uv: u
    around the y axis, 0.5 facing +z, the seam at -z; v = 1 at the north pole, y up);
    the vertices on the seam and at the poles are then split, so V grows.
    """
    _check_count(subdivisions, "subdivisions", 0, 8)
    _check_positive(radius, "radius")
    _check_memory("subdivisions", subdivisions, 20 * 4**subdivisions, "an icosphere")
    verts = _ICOSAHEDRON_VERTICES / np.linalg.norm(_ICOSAHEDRON_VERTICES, axis=1)[:, None]
    tris = _ICOSAHEDRON_FACES
    for _ in range(subdivisions):
        verts, tris = _subdivide(verts, tris)
    _check_flag(uv, "uv")
    coords = None
    if uv:
        source, tris, coords = split_by_corner_uv(tris, sphere_corner_uv(verts, tris))
        verts = verts[source]
    unit = jnp.asarray(verts, float_dtype())
    return Mesh(unit * radius, jnp.asarray(tris, jnp.int32), unit,
                None if coords is None else jnp.asarray(coords, float_dtype()))


def _check_flag(value, name):
    if not isinstance(value, bool):
        raise ValueError(f"{name}: {value!r}; expected true or false")


def torus(major_radius=1.0, minor_radius=0.35, major_segments=48, minor_segments=24,
          uv=False):
    """Watertight torus Mesh around the y axis (y up), centred at the origin.

    V = major_segments * minor_segments, F = 2 * V, faces CCW seen from outside, exact
    analytic normals. Needs 0 < minor_radius < major_radius and segments >= 3.
    uv: give it UVs (u around the y axis, v around the tube, each in [0, 1]); the two
    closing rings of vertices are then split, so V = (major + 1) * (minor + 1).
    """
    _check_positive(major_radius, "major_radius")
    _check_positive(minor_radius, "minor_radius")
    if minor_radius >= major_radius:
        raise ValueError(f"minor_radius: {minor_radius!r}; expected < major_radius")
    _check_count(major_segments, "major_segments", 3, 2**16)
    _check_count(minor_segments, "minor_segments", 3, 2**16)
    _check_memory("major_segments, minor_segments", f"{major_segments} x {minor_segments}",
                  2 * major_segments * minor_segments, "a torus")
    u = np.linspace(0.0, 2 * np.pi, major_segments, endpoint=False)[:, None]
    v = np.linspace(0.0, 2 * np.pi, minor_segments, endpoint=False)[None, :]
    cos_u, sin_u, cos_v, sin_v = np.cos(u), np.sin(u), np.cos(v), np.sin(v)
    normals = np.stack(np.broadcast_arrays(cos_v * cos_u, sin_v, cos_v * sin_u), -1)
    ring = np.stack(np.broadcast_arrays(cos_u, 0.0 * v, sin_u), -1) * major_radius
    verts, normals = (ring + minor_radius * normals).reshape(-1, 3), normals.reshape(-1, 3)
    tris = _grid_faces(major_segments, minor_segments)
    _check_flag(uv, "uv")
    if not uv:
        return Mesh(*_jax_arrays(verts, tris, normals, float_dtype()))
    source, tris, coords = split_by_corner_uv(
        tris, torus_corner_uv(tris, major_segments, minor_segments))
    return Mesh(*_jax_arrays(verts[source], tris, normals[source], float_dtype(), coords))


def _grid_faces(rows, cols):
    """Faces [2 * rows * cols, 3] int of a rows x cols vertex grid wrapped in both
    directions (vertex id row * cols + col), two triangles per cell."""
    i, j = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    a, b = i * cols + j, i * cols + (j + 1) % cols
    c, d = (b + cols) % (rows * cols), (a + cols) % (rows * cols)
    # Stepping along a column (around the tube) before a row winds CCW seen from outside.
    return np.stack([a, b, c, a, c, d], axis=-1).reshape(-1, 3)


def _three_numbers(value):
    """value as a float64 [3] array, or None (text, ragged, another shape, or not finite
    in the default float dtype)."""
    if isinstance(value, (str, bytes)):
        return None
    try:
        arr = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        return None
    return arr if arr.shape == (3,) and np.all(representable(arr)) else None


def box(size=(1.0, 1.0, 1.0), uv=False):
    """Axis-aligned box Mesh centred at the origin with side lengths size: 3 floats > 0.

    24 vertices (4 per side, so each side has its own flat normal), 12 faces CCW outward.
    uv: give it UVs: each side shows the whole texture, unmirrored seen from outside (its
    corners at (0, 0), (1, 0), (1, 1), (0, 1)); V stays 24.
    """
    _check_flag(uv, "uv")
    sides = _three_numbers(size)
    if sides is None or not np.all(sides > 0):
        raise ValueError(f"size: {size!r}; expected 3 finite numbers > 0")
    half = sides / 2.0
    square = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    corners, normals = [], []
    for axis, sign in itertools.product(range(3), (1.0, -1.0)):
        side = np.zeros((4, 3))
        side[:, axis] = sign
        # Reversing the square for the negative side keeps it CCW seen from outside.
        side[:, [(axis + 1) % 3, (axis + 2) % 3]] = square if sign > 0 else square[::-1]
        corners.append(side)
        normals.append(np.broadcast_to(np.eye(3)[axis] * sign, (4, 3)))
    tris = (np.arange(6)[:, None, None] * 4 + np.array([[0, 1, 2], [0, 2, 3]])).reshape(-1, 3)
    coords = np.tile((square + 1.0) / 2.0, (6, 1)) if uv else None
    return Mesh(*_jax_arrays(np.concatenate(corners) * half, tris, np.concatenate(normals),
                             float_dtype(), coords))


def mesh_from_trimesh(tm, *, weighting="angle", crease_angle=None):
    """Mesh from a trimesh.Trimesh (a trimesh.Scene is concatenated first).

    Positions, faces and UVs (tm.visual.uv, when the file had them: trimesh has split
    the vertices at UV seams) are taken: normals are our own (`vertex_normals` over the
    welded positions, or crease splitting when crease_angle is given), never trimesh's.
    """
    import trimesh  # here, not at import: it imports scipy (slow) and most runs never need it

    if isinstance(tm, trimesh.Scene):
        tm = trimesh.util.concatenate(tm.dump())
    if not isinstance(tm, trimesh.Trimesh):
        raise TypeError(f"tm: {type(tm).__name__}; expected trimesh.Trimesh or trimesh.Scene")
    verts, faces = np.asarray(tm.vertices), np.asarray(tm.faces)
    uv = getattr(tm.visual, "uv", None)
    uv = None if uv is None or len(uv) != len(verts) else np.asarray(uv)
    return mesh_from_arrays(verts, faces, uv=uv, weighting=weighting, crease_angle=crease_angle)


_READABLE = "a mesh file trimesh reads (OBJ, PLY, STL, GLB, ...)"


def _check_mesh_path(path):
    """path as a str naming an existing file, else FileNotFoundError or ValueError."""
    path = os.fspath(path)
    if os.path.isdir(path):
        raise ValueError(f"path: {path!r} is a directory; expected {_READABLE}")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"mesh file not found: {path!r}")
    return path


def _obj_statements(path):
    """(line number, tokens) of each `v` and `f` statement of an OBJ file, comments cut.
    (trimesh reads no backslash-continued lines, so neither does this.)"""
    with open(path, encoding="utf-8", errors="replace") as file:
        lines = file.read().splitlines()
    for number, line in enumerate(lines, 1):
        tokens = line.split("#", 1)[0].split()
        if tokens and tokens[0] in ("v", "f"):
            yield number, tokens


def _is_number(token):
    try:
        float(token)
    except ValueError:
        return False
    return True


def _obj_vertex_ref(token, seen):
    """The 1-based vertex index of an OBJ face reference "i", "i/t", "i//n" or "i/t/n"
    (negative: relative to the `seen` vertices so far), or None if it is not one."""
    head = token.split("/", 1)[0]
    if not re.fullmatch(r"-?[0-9]+", head) or int(head) == 0 or -int(head) > seen:
        return None
    return int(head) if int(head) > 0 else seen + 1 + int(head)


def _scan_obj(path):
    """ValueError naming the file and line for what trimesh would drop silently or crash
    on: a `v` line without 3 numbers, an `f` line with fewer than 3 vertex references
    (a truncated last line), or a reference to a vertex the file does not have."""
    seen, highest = 0, (0, 0)
    for number, tokens in _obj_statements(path):
        where = f"path: mesh file {path!r}, line {number}: {' '.join(tokens)[:60]!r}"
        if tokens[0] == "v":
            if len(tokens) < 4 or not all(map(_is_number, tokens[1:])):
                raise ValueError(f"{where}; expected a vertex 'v x y z' with 3 numbers")
            seen += 1
            continue
        refs = [_obj_vertex_ref(token, seen) for token in tokens[1:]]
        if len(refs) < 3 or None in refs:
            raise ValueError(f"{where}; expected a face 'f i j k ...' of at least 3 vertex "
                             f"references i (1 <= i, or -{seen} <= i <= -1 relative)")
        highest = max(highest, (max(refs), number))
    if highest[0] > seen:
        raise ValueError(f"path: mesh file {path!r}, line {highest[1]}: a face refers to "
                         f"vertex {highest[0]}; expected at most {seen}, the vertices in the file")


def _read_trimesh(path):
    """trimesh.Trimesh of the file at path, its arrays checked (`_check_arrays`) before
    trimesh's processing (which drops NaN vertices silently) and then processed: merged
    duplicated vertices, as STL stores each triangle alone."""
    import trimesh  # see mesh_from_trimesh

    try:
        tm = trimesh.load(path, force="mesh", process=False)
    # trimesh's loaders raise many exception types; all mean "cannot read this file".
    except Exception as err:
        raise ValueError(f"path: cannot read mesh file {path!r}: {err}; expected "
                         f"{_READABLE}") from err
    if not isinstance(tm, trimesh.Trimesh) or len(tm.faces) == 0:
        raise ValueError(f"path: mesh file {path!r} has no faces; expected triangles")
    _check_arrays(tm.vertices, tm.faces, name=lambda field: f"path: mesh file {path!r}: {field}")
    tm.process()
    return tm


def load_mesh(path, *, weighting="angle", crease_angle=None):
    """Mesh from any file trimesh reads (OBJ, PLY, STL, GLB, ...); see mesh_from_trimesh.

    Duplicated vertices are merged (STL stores each triangle alone) so that they can
    share a normal. Vertices are stored in the default float dtype. Raises
    FileNotFoundError for a missing file and ValueError, naming the file, for a folder,
    a file that cannot be parsed, has no faces, a non-finite vertex or a face index out
    of range; in an OBJ file, also for a truncated `v` or `f` line (named by its line
    number), which trimesh would drop silently.
    """
    path = _check_mesh_path(path)
    _check_weighting(weighting)
    _check_crease(crease_angle)
    if path.lower().endswith(".obj"):
        _scan_obj(path)
    tm = _read_trimesh(path)
    return mesh_from_trimesh(tm, weighting=weighting, crease_angle=crease_angle)


def _inverse_transpose_direction(linear):
    """sign(det) * cofactor matrix [3, 3] of linear [3, 3]: |det| * inv(linear).T.

    Same directions as the inverse transpose once renormalized, but finite (and zero for
    a singular matrix, so normals become zero) where inv would divide by zero.
    """
    r0, r1, r2 = linear
    cofactor = jnp.stack([jnp.cross(r1, r2), jnp.cross(r2, r0), jnp.cross(r0, r1)])
    return jnp.sign(jnp.dot(r0, cofactor[0])) * cofactor


def transform_mesh(mesh, matrix):
    """Mesh moved by the affine model matrix [4, 4] float (last row 0, 0, 0, 1).

    Vertices [V, 3] map by the matrix, normals by the inverse transpose of its
    upper-left 3x3, renormalized, so they stay perpendicular to the transformed surface
    under non-uniform scale. Pure jax: differentiable wrt matrix and mesh.
    """
    matrix = jnp.asarray(matrix, mesh.vertices.dtype)
    if matrix.shape != (4, 4):
        raise ValueError(f"matrix: shape {matrix.shape}; expected [4, 4]")
    linear = matrix[:3, :3]
    vertices = mesh.vertices @ linear.T + matrix[:3, 3]
    normals = safe_normalize(mesh.normals @ _inverse_transpose_direction(linear).T)
    return Mesh(vertices, mesh.faces, normals, mesh.uv)


def _axis_rotation(axis, angle):
    """Right-handed rotation [3, 3] float64 by angle (radians) about coordinate axis 0-2."""
    b, c = (axis + 1) % 3, (axis + 2) % 3
    rot = np.eye(3)
    rot[b, b] = rot[c, c] = np.cos(angle)
    rot[c, b], rot[b, c] = np.sin(angle), -np.sin(angle)
    return rot


def model_matrix(translate=(0.0, 0.0, 0.0), rotate_deg=(0.0, 0.0, 0.0), scale=(1.0, 1.0, 1.0)):
    """Affine model matrix [4, 4] numpy, in the default float dtype, = T @ Rz @ Ry @ Rx @ S.

    Applied to a point: scale first, then rotate about X, then Y, then Z (right-handed
    Euler angles rotate_deg, in degrees), then translate. Each argument is 3 numbers.
    """
    args = {"translate": translate, "rotate_deg": rotate_deg, "scale": scale}
    for name, value in args.items():
        if _three_numbers(value) is None:
            raise ValueError(f"{name}: {value!r}; expected 3 finite numbers")
    rx, ry, rz = np.radians(np.asarray(rotate_deg, np.float64))
    matrix = np.eye(4)
    rotation = _axis_rotation(2, rz) @ _axis_rotation(1, ry) @ _axis_rotation(0, rx)
    matrix[:3, :3] = rotation * np.asarray(scale, np.float64)[None, :]
    matrix[:3, 3] = translate
    return matrix.astype(float_dtype())

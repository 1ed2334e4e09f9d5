"""Shading samples: where each shading mode lights the surface, and how pixels read it.

One definition serves `render` and the fitting cache (fitting/model/cache.py), so a new effect
is added in one place. Per mode (RenderSettings.shading, OpenGL 1.x):
- 'phong': one sample per fragment: the interpolated point and renormalized normal;
- 'gouraud': one per vertex (and side); a fragment reads its face's three corners with
  its barycentric weights, after each vertex colour was clamped;
- 'flat': one per face, at the centroid with the face normal; a fragment reads its face;
- 'flat_last': one per vertex (and side); a fragment reads its face's last vertex.
Two-sided lighting (scene.two_sided) lights back faces with the reversed normal: the
per-vertex modes then have a front and a back sample of every vertex, and a fragment
reads the side its face shows. In a scene of several objects every sample also carries
its object's id (of its face or vertex), which picks its material. A scene whose material
has a texture (and only such a scene) gives every sample its UV: the perspective-correct
interpolated UV (Phong), the vertex's (Gouraud, flat_last) or the mean of the face's
corners' (flat), where diffshade.shading.texturing reads the textures.

`Reader` says how fragments read sample values: row `ids[...]` of `table` lists the
samples (G of them) a fragment combines with `weights[..., G]`; no table means the
samples are the fragments themselves.
"""

import dataclasses

import jax
import jax.numpy as jnp

from diffshade.numerics import safe_normalize
from diffshade.raster.fragments import face_edge_coefficients
from diffshade.raster.interpolation import interpolate_rows
from diffshade.scene.materials import has_textures
from diffshade.shading.compact import interpolate_rows_at


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Samples:
    """points: [..., 3] world space; normals: [..., 3] unit, reversed on back sides under
    two-sided lighting; front: [...] bool, lit with the front material; objects: [...]
    int32 object ids in a scene of several objects, else None; uv: [..., 2] texture
    coordinates where the scene has textures, else None; valid: [...] bool, the samples
    that hold a fragment, where the scene has textures and some samples may hold none
    (Phong's), else None: textures are read only there."""

    points: jax.Array
    normals: jax.Array
    front: jax.Array
    objects: jax.Array | None = None
    uv: jax.Array | None = None
    valid: jax.Array | None = None

    def leaves(self):
        """The arrays, in field order, without the absent ones (objects, uv, valid)."""
        return tuple(a for a in (self.points, self.normals, self.front, self.objects, self.uv,
                                 self.valid) if a is not None)

    def with_leaves(self, leaves):
        """Samples of the same structure holding `leaves` (as `leaves()` lists them)."""
        names = [f.name for f in dataclasses.fields(self) if getattr(self, f.name) is not None]
        return Samples(**dict(zip(names, leaves, strict=True)))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Reader:
    """ids: [...] int32 row of `table` per fragment (-1 = empty); weights: [..., G] or
    None; table: [T, G] int32 sample indices, or None when sample i is fragment i."""

    ids: jax.Array
    weights: jax.Array | None = None
    table: jax.Array | None = None


def uses_uv(scene) -> bool:
    """Whether the scene's samples need UVs: its (front or back) material has a texture."""
    return has_textures(scene.material) or (scene.two_sided and
                                            has_textures(scene.back_material))


def flat_samples(scene, proj):
    """Per face, where flat shading lights it: centroids [F, 3], unit face normals [F, 3]
    and front [F] bool (counter-clockwise on screen)."""
    tri = proj.world[scene.mesh.faces]
    normals = safe_normalize(jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
    _, det = face_edge_coefficients(proj.clip, scene.mesh.faces)
    return tri.mean(1), normals, det > 0


def _oriented(normals, front, two_sided):
    return jnp.where(front[..., None], normals, -normals) if two_sided else normals


def object_ids(scene, per_face, index):
    """The object ids [...] of faces (per_face) or vertices at `index` [...], or None in
    the single-object form; empty slots (-1) read object 0."""
    if scene.objects is None:
        return None
    ids = scene.objects.faces if per_face else scene.objects.vertices
    return jnp.take(ids, jnp.maximum(index, 0), axis=0)


def phong_samples(scene, proj, face_ids, bary, front, host=None, points=True):
    """Phong's samples of fragments given by their face ids [N, K] (-1 = empty),
    barycentrics [N, K, 3] and sides [N, K]: interpolated points and renormalized normals
    (render lights only the fragments that count this way, diffshade.render).

    points=False: for a shading that reads no points (lighting.reads_points, and no local
    viewer) only the normals are interpolated, and the points are NaN, so that a use
    would show in the image; the interpolation forward and backward then carry three
    columns fewer, and the backward no zeros for the points."""
    attrs = _phong_attributes(scene, proj, points)
    values = interpolate_rows(attrs, scene.mesh.faces, face_ids, bary, host)
    return _phong_from(scene, values, face_ids, front, points)


def phong_samples_at(scene, proj, rows, face_ids, bary, front, host=None, points=True):
    """phong_samples of the fragments at rows [M] int32 of face ids [N] and barycentrics
    [N, 3] (flat), with their sides front [M]: [M, ...] samples. The interpolation reads
    the fragments at `rows` itself (compact.interpolate_rows_at)."""
    attrs = _phong_attributes(scene, proj, points)
    values = interpolate_rows_at(attrs, scene.mesh.faces, rows, face_ids, bary, host)
    needs_ids = scene.objects is not None or uses_uv(scene)
    ids = jnp.take(face_ids, rows, mode="fill", fill_value=-1) if needs_ids else None
    return _phong_from(scene, values, ids, front, points)


def _phong_attributes(scene, proj, points):
    """The vertex attributes Phong interpolates: positions (where `points`), normals (and
    UVs)."""
    return (((proj.world,) if points else ()) + (proj.normals,)
            + ((scene.mesh.uv,) if uses_uv(scene) else ()))


def _phong_from(scene, values, face_ids, front, points):
    """Phong's Samples from the interpolated ([points,] normals[, uv]) of fragments of face
    ids face_ids (read only by a scene of several objects, or with textures); NaN points
    where not `points`."""
    if not points:
        values = (jnp.full_like(values[0], jnp.nan),) + tuple(values)
    points, normals, *uv = values
    normals = _oriented(safe_normalize(normals), front, scene.two_sided)
    return Samples(points, normals, front, object_ids(scene, True, face_ids), *uv,
                   valid=face_ids >= 0 if uses_uv(scene) else None)


def _phong(scene, proj, frags, host, points):
    samples = phong_samples(scene, proj, frags.face_ids, frags.bary, frags.front, host, points)
    return samples, Reader(frags.face_ids)


def _per_vertex(scene, proj, frags, corners):
    """Gouraud (corners 0..2) and flat_last (corner 2): samples per vertex and side."""
    faces = scene.mesh.faces[:, corners]
    n_faces, n_vertices = faces.shape[0], proj.world.shape[0]
    weights = frags.bary if len(corners) == 3 else None
    objects = None if scene.objects is None else scene.objects.vertices
    uv = scene.mesh.uv if uses_uv(scene) else None
    if not scene.two_sided:
        front = jnp.ones(n_vertices, bool)
        return (Samples(proj.world, proj.normals, front, objects, uv),
                Reader(frags.face_ids, weights, faces))
    points = jnp.concatenate([proj.world, proj.world])
    normals = jnp.concatenate([proj.normals, -proj.normals])
    front = jnp.arange(2 * n_vertices) < n_vertices
    objects = None if objects is None else jnp.concatenate([objects, objects])
    uv = None if uv is None else jnp.concatenate([uv, uv])
    ids = jnp.where(frags.front | ~frags.valid, frags.face_ids, frags.face_ids + n_faces)
    table = jnp.concatenate([faces, faces + n_vertices])
    return Samples(points, normals, front, objects, uv), Reader(ids, weights, table)


def _flat(scene, proj, frags):
    points, normals, front = flat_samples(scene, proj)
    normals = _oriented(normals, front, scene.two_sided)
    table = jnp.arange(points.shape[0], dtype=jnp.int32)[:, None]
    objects = None if scene.objects is None else scene.objects.faces
    uv = scene.mesh.uv[scene.mesh.faces].mean(1) if uses_uv(scene) else None
    return Samples(points, normals, front, objects, uv), Reader(frags.face_ids, None, table)


def shading_samples(scene, proj, frags, shading, host=None, points=True):
    """(Samples, Reader) of the shading mode for the fragments `frags` of `proj`;
    points=False: Phong's samples carry no points (phong_samples)."""
    if shading == "phong":
        return _phong(scene, proj, frags, host, points)
    if shading == "flat":
        return _flat(scene, proj, frags)
    return _per_vertex(scene, proj, frags, (0, 1, 2) if shading == "gouraud" else (2,))


def read(tree, reader: Reader, host=None):
    """Per-fragment values of a pytree of per-sample values ([S, C_i] leaves) -> [..., C_i]
    leaves (zeros in empty slots)."""
    if reader.table is None:
        return tree
    if reader.weights is None:
        valid = (reader.ids >= 0)[..., None]
        rows = jnp.take(reader.table[:, 0], jnp.maximum(reader.ids, 0), axis=0)
        return jax.tree.map(lambda v: jnp.where(valid, jnp.take(v, rows, axis=0), 0.0), tree)
    return interpolate_rows(tree, reader.table, reader.ids, reader.weights, host)

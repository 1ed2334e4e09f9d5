"""Several objects in one scene, each with its own mesh, transform and material.

`diffshade.scene_object(mesh, material, transform=..., back_material=..., name=...)`
describes one object; `make_scene(objects=[...])` joins several (`join_objects`):
- the meshes are concatenated into one Mesh, each object's vertices moved by its
  transform and its normals by the inverse transpose (diffshade.scene.transform),
  so that projection and rasterization see one mesh;
- `ObjectIds` says which object each face and each vertex belongs to, and holds the
  objects' names (static; None when no object is named);
- the materials are stacked along a leading object axis ([O, 3], shininess [O]); an
  optional field absent from some materials (ks, emission, or any other) is zeros there.
  Textured materials cannot be stacked: textures are for scenes of one object (the
  joined mesh keeps UVs only when every object's mesh has them).
Shading takes each sample's material by its object id (`take_material`). A scene of one
object keeps the single-object form (no ids, an unstacked material, the transform in
`Scene.model`), so it compiles exactly as a scene built from a mesh does.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.scene.materials import Material
from diffshade.scene.mesh import Mesh
from diffshade.scene.transform import transform_normals, transform_points


@dataclasses.dataclass(frozen=True)
class SceneObject:
    """One object: mesh; material and back_material (Material, back_material None: the
    front one serves back faces under two-sided lighting); transform: [4, 4] object-to-
    model matrix; name: a label (str) or None. Built, validated, by `scene_object`."""

    mesh: Mesh
    material: Material
    transform: jax.Array
    back_material: Material | None = None
    name: str | None = None


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ObjectIds:
    """faces: [F] int32, the object of each face; vertices: [V] int32, of each vertex;
    names: a tuple of one str per object (an unnamed one is 'object_<i>'), or None when
    no object is named (static: hashable, not traced)."""

    faces: jax.Array
    vertices: jax.Array
    names: tuple | None = dataclasses.field(default=None, metadata={"static": True})


def _filled(materials):
    """The materials with one structure: a field None in some is zeros shaped like the
    others' (ks 0 adds no specular, emission 0 no light)."""
    def field(mat, name):
        value = getattr(mat, name)
        if value is not None:
            return value
        given = [getattr(m, name) for m in materials if getattr(m, name) is not None]
        return jnp.zeros_like(given[0]) if given else None
    names = [f.name for f in dataclasses.fields(Material)]
    return [dataclasses.replace(m, **{n: field(m, n) for n in names}) for m in materials]


def stack_materials(materials) -> Material:
    """One Material whose leaves have a leading object axis [O, ...] (see `_filled`)."""
    return jax.tree.map(lambda *leaves: jnp.stack(leaves), *_filled(list(materials)))


def unstack_material(material: Material, index: int) -> Material:
    """Object `index`'s Material of a stacked one."""
    return jax.tree.map(lambda leaf: leaf[index], material)


def take_material(material: Material, ids) -> Material:
    """The material of each sample: stacked material [O, ...] leaves, ids [...] int32 ->
    [..., ...] leaves (broadcasting against a sample's [..., 3] values)."""
    return jax.tree.map(lambda leaf: jnp.take(leaf, ids, axis=0, mode="clip"), material)


def _placed(obj: SceneObject):
    """The object's mesh in model space: its transform applied to vertices and normals."""
    mesh = obj.mesh
    return Mesh(transform_points(obj.transform, mesh.vertices).astype(mesh.vertices.dtype),
                mesh.faces,
                transform_normals(obj.transform, mesh.normals).astype(mesh.normals.dtype),
                mesh.uv)


def object_names(objects):
    """The names of SceneObjects (an unnamed one's 'object_<i>'), or None when none is
    named; ValueError when two are the same."""
    if all(o.name is None for o in objects):
        return None
    names = tuple(f"object_{i}" if o.name is None else o.name for i, o in enumerate(objects))
    for i, name in enumerate(names):
        if name in names[:i]:
            raise ValueError(f"objects[{i}].name: got {name!r} again; expected a name unique "
                             "among the objects (an unnamed object i is 'object_<i>')")
    return names


def join_objects(objects):
    """(mesh, ObjectIds, material, back_material) of several SceneObjects: one mesh, the
    objects' ids, the stacked front materials and the stacked back materials (each
    object's front one where it has none), or None when no object has one."""
    meshes = [_placed(o) for o in objects]
    offsets = np.cumsum([0] + [m.vertices.shape[0] for m in meshes])[:-1]
    uv = (None if any(m.uv is None for m in meshes)
          else jnp.concatenate([m.uv for m in meshes]))
    mesh = Mesh(jnp.concatenate([m.vertices for m in meshes]),
                jnp.concatenate([m.faces + off for m, off in zip(meshes, offsets, strict=True)]),
                jnp.concatenate([m.normals for m in meshes]), uv)
    def repeated(counts):
        return jnp.asarray(np.repeat(np.arange(len(meshes)), counts), jnp.int32)
    ids = ObjectIds(repeated([m.faces.shape[0] for m in meshes]),
                    repeated([m.vertices.shape[0] for m in meshes]), object_names(objects))
    fronts = [o.material for o in objects]
    if all(o.back_material is None for o in objects):
        return mesh, ids, stack_materials(fronts), None
    backs = [o.material if o.back_material is None else o.back_material for o in objects]
    both = _filled(fronts + backs)  # front and back share one structure
    return mesh, ids, stack_materials(both[:len(objects)]), stack_materials(both[len(objects):])


def split_mesh(mesh: Mesh, ids: ObjectIds, index: int) -> Mesh:
    """Object `index`'s part of a joined mesh (numpy arrays), its faces renumbered."""
    vertices = np.flatnonzero(np.asarray(ids.vertices) == index)
    faces = np.asarray(mesh.faces)[np.asarray(ids.faces) == index] - vertices[0]
    uv = None if mesh.uv is None else np.asarray(mesh.uv)[vertices]
    return Mesh(np.asarray(mesh.vertices)[vertices], faces, np.asarray(mesh.normals)[vertices],
                uv)

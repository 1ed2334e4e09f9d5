"""Scene: everything that is rendered, as one frozen pytree.

Array leaves (differentiable): the mesh, the material(s), the lights, the camera's
parameters, the model matrix, the global ambient light and the background colour.
Static fields (they choose code paths): `local_viewer` and `two_sided`, as in
`glLightModel`. `make_scene` validates and groups the lights by type.

A scene of several objects (`make_scene(objects=[scene_object(...), ...])`) holds them
joined (diffshade.scene.objects): one mesh, `objects` (the object of every face and vertex) and
materials stacked along a leading object axis. A scene of one object has `objects=None`
and unstacked materials: the single-object form, compiled as it always was.
"""

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.numerics import float_dtype, representable
from diffshade.scene.camera import Camera
from diffshade.scene.lights import LightGroups, group_lights
from diffshade.scene.materials import TEXTURED_FIELDS, Material, has_textures
from diffshade.scene.materials import material as make_material
from diffshade.scene.mesh import Mesh
from diffshade.scene.objects import ObjectIds, SceneObject, join_objects
from diffshade.scene.textures import is_texture


@partial(jax.tree_util.register_dataclass,
         data_fields=["mesh", "material", "lights", "camera", "model", "global_ambient",
                      "background", "back_material", "objects"],
         meta_fields=["local_viewer", "two_sided"])
@dataclasses.dataclass(frozen=True)
class Scene:
    """mesh: Mesh; material: Material; lights: LightGroups; camera: Camera;
    model: [4, 4] model-to-world matrix; global_ambient, background: [3];
    back_material: Material or None (two-sided lighting falls back to `material`);
    objects: ObjectIds of a scene of several objects, whose materials are then stacked
    ([O, 3] leaves, shininess [O]), or None (one object, unstacked materials)."""

    mesh: Mesh
    material: Material
    lights: LightGroups
    camera: Camera
    model: jax.Array
    global_ambient: jax.Array
    background: jax.Array
    back_material: Material | None = None
    objects: ObjectIds | None = None
    local_viewer: bool = False
    two_sided: bool = False


def _floats(value):
    """value as a float64 array, or None when it is not numbers (a string, ragged...)."""
    if isinstance(value, (str, bytes)):
        return None
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None


def _rgb(name, value):
    arr = _floats(value)
    if arr is not None and arr.shape == ():
        arr = np.full(3, float(arr))
    if arr is None or arr.shape != (3,) or not np.all(representable(arr)) or np.any(arr < 0):
        raise ValueError(f"{name}: got {value!r}; expected a non-negative number or 3 of them")
    return jnp.asarray(arr, dtype=float_dtype())


def _model_matrix(value, name="model"):
    """The [4, 4] matrix `value` (None: identity), finite with an invertible upper 3x3
    block, in the default float dtype; ValueError naming `name` otherwise."""
    arr = np.eye(4) if value is None else _floats(value)
    if arr is None:
        raise ValueError(f"{name}: got {value!r}; expected a finite 4x4 matrix")
    if arr.shape != (4, 4) or not np.all(representable(arr)):
        raise ValueError(f"{name}: got an array of shape {arr.shape}; expected a finite 4x4 "
                         "matrix")
    if abs(np.linalg.det(arr[:3, :3])) < 1e-12:
        raise ValueError(f"{name}: the upper 3x3 block is singular; expected an invertible "
                         "transform")
    return jnp.asarray(arr, dtype=float_dtype())


def _check_types(*checks):
    """TypeError naming the first (name, value, kind) whose value is not a kind."""
    for name, value, kind in checks:
        if not isinstance(value, kind):
            expected = kind.__name__ if isinstance(kind, type) else "Material or None"
            raise TypeError(f"{name}: got {type(value).__name__}; expected {expected}")


def _optional_material(name, value):
    return name, value, (Material, type(None))


def scene_object(mesh: Mesh, material: Material | None = None, *, transform=None,
                 back_material: Material | None = None, name: str | None = None
                 ) -> SceneObject:
    """One object of a scene (make_scene's `objects`): its mesh, its material (default
    OpenGL's), its transform (object to model space: a 4x4 matrix with an invertible
    upper 3x3 block, default identity), its back material (default: none, the front
    material serves back faces under two-sided lighting) and its name (a non-empty
    string, unique among the scene's objects; it labels the object's fitted material)."""
    _check_types(("mesh", mesh, Mesh), _optional_material("material", material),
                 _optional_material("back_material", back_material))
    if name is not None and (not isinstance(name, str) or name.split() != [name]):
        raise ValueError(f"name: got {name!r}; expected a non-empty string without "
                         "spaces (it names the object's material in .mtl files) or None")
    return SceneObject(mesh, make_material() if material is None else material,
                       _model_matrix(transform, "transform"), back_material, name)


def _check_objects(objects, mesh, material, back_material):
    """objects as a list of SceneObject, given instead of mesh and the materials."""
    if mesh is not None or material is not None or back_material is not None:
        given = [n for n, v in (("mesh", mesh), ("material", material),
                                ("back_material", back_material)) if v is not None]
        raise ValueError(f"objects: given with {', '.join(given)}; expected either objects "
                         "(each with its mesh and materials) or mesh and material")
    if isinstance(objects, SceneObject) or not isinstance(objects, (list, tuple)) or not objects:
        raise TypeError(f"objects: got {objects!r:.60}; expected a non-empty list of "
                        "SceneObject (diffshade.scene_object)")
    _check_types(*((f"objects[{i}]", o, SceneObject) for i, o in enumerate(objects)))
    return list(objects)


def _textured_field(material):
    return next(name for name in TEXTURED_FIELDS if is_texture(getattr(material, name)))


def _check_textures(mesh, materials, where):
    """ValueError unless a textured material (of `materials`, {name: Material or None})
    is on a mesh with UVs, in a scene of one object (where: its key, or None)."""
    for name, mat in materials.items():
        if not has_textures(mat):
            continue
        field = f"{name}.{_textured_field(mat)}"
        if where is not None:
            raise ValueError(f"{where}.{field}: a texture in a scene of several objects; "
                             "expected textures only in a scene of one object")
        if mesh.uv is None:
            raise ValueError(f"{field}: a texture on a mesh without UVs; expected a mesh "
                             "with texture coordinates (mesh_from_arrays(..., uv=...), an "
                             "OBJ with vt, icosphere/torus/box(uv=True))")


def _geometry(mesh, material, back_material, objects, model):
    """(mesh, material, back_material, ObjectIds or None, model) of make_scene's
    arguments: one object keeps the single-object form, its transform in the model."""
    if objects is None:
        _check_types(("mesh", mesh, Mesh), _optional_material("material", material),
                     _optional_material("back_material", back_material))
        _check_textures(mesh, {"material": material, "back_material": back_material}, None)
        return (mesh, make_material() if material is None else material, back_material,
                None, _model_matrix(model))
    objects = _check_objects(objects, mesh, material, back_material)
    model = _model_matrix(model)
    if len(objects) == 1:
        one = objects[0]
        _check_textures(one.mesh, {"material": one.material,
                                   "back_material": one.back_material}, None)
        return one.mesh, one.material, one.back_material, None, model @ one.transform
    for i, o in enumerate(objects):
        _check_textures(o.mesh, {"material": o.material, "back_material": o.back_material},
                        f"objects[{i}]")
    mesh, ids, front, back = join_objects(objects)
    return mesh, front, back, ids, model


def make_scene(mesh: Mesh | None = None, camera: Camera | None = None, lights=(),
               material: Material | None = None, *, objects=None, model=None,
               global_ambient=0.2, background=0.0, back_material=None, local_viewer=False,
               two_sided=False) -> Scene:
    """Build a validated Scene. Either `mesh` with `material` (and `back_material`), or
    `objects`, a list of `scene_object(...)`, each with its own mesh, transform and
    materials (`model` then moves them all). `lights` is a list of lights or a
    LightGroups; the defaults follow OpenGL (global ambient 0.2, infinite viewer,
    one-sided lighting)."""
    _check_types(("camera", camera, Camera))
    mesh, material, back_material, ids, model = _geometry(mesh, material, back_material,
                                                          objects, model)
    return Scene(
        mesh=mesh, material=material, lights=group_lights(lights), camera=camera,
        model=model, global_ambient=_rgb("global_ambient", global_ambient),
        background=_rgb("background", background), back_material=back_material,
        objects=ids, local_viewer=bool(local_viewer), two_sided=bool(two_sided))


def object_count(scene: Scene) -> int:
    """The number of objects of the scene (1 in the single-object form)."""
    return 1 if scene.objects is None else int(scene.material.ka.shape[0])


def replace(obj, **changes):
    """dataclasses.replace for diffshade's frozen pytrees (scene, material, lights...)."""
    return dataclasses.replace(obj, **changes)


__all__ = ["LightGroups", "Scene", "SceneObject", "make_scene", "object_count", "replace",
           "scene_object"]

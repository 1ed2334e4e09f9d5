"""Scene: everything that is rendered, as one frozen pytree.

Array leaves (differentiable): the mesh, the material(s), the lights, the camera's
parameters, the model matrix, the global ambient light and the background colour.
Static fields (they choose code paths): `local_viewer` and `two_sided`, as in
`glLightModel`. `make_scene` validates and groups the lights by type.
"""

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.camera import Camera
from diffshade.lights import LightGroups, group_lights
from diffshade.material import Material
from diffshade.material import material as make_material
from diffshade.mesh import Mesh
from diffshade.numerics import float_dtype, representable


@partial(jax.tree_util.register_dataclass,
         data_fields=["mesh", "material", "lights", "camera", "model", "global_ambient",
                      "background", "back_material"],
         meta_fields=["local_viewer", "two_sided"])
@dataclasses.dataclass(frozen=True)
class Scene:
    """mesh: Mesh; material: Material; lights: LightGroups; camera: Camera;
    model: [4, 4] model-to-world matrix; global_ambient, background: [3];
    back_material: Material or None (two-sided lighting falls back to `material`)."""

    mesh: Mesh
    material: Material
    lights: LightGroups
    camera: Camera
    model: jax.Array
    global_ambient: jax.Array
    background: jax.Array
    back_material: Material | None = None
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


def _model_matrix(value):
    arr = np.eye(4) if value is None else _floats(value)
    if arr is None:
        raise ValueError(f"model: got {value!r}; expected a finite 4x4 matrix")
    if arr.shape != (4, 4) or not np.all(representable(arr)):
        raise ValueError(f"model: got an array of shape {arr.shape}; expected a finite 4x4 matrix")
    if abs(np.linalg.det(arr[:3, :3])) < 1e-12:
        raise ValueError("model: the upper 3x3 block is singular; expected an invertible transform")
    return jnp.asarray(arr, dtype=float_dtype())


def make_scene(mesh: Mesh, camera: Camera, lights=(), material: Material | None = None, *,
               model=None, global_ambient=0.2, background=0.0, back_material=None,
               local_viewer=False, two_sided=False) -> Scene:
    """Build a validated Scene. `lights` is a list of lights or a LightGroups; the defaults
    follow OpenGL (global ambient 0.2, infinite viewer, one-sided lighting)."""
    for name, value, kind in (("mesh", mesh, Mesh), ("camera", camera, Camera),
                              ("material", material, (Material, type(None))),
                              ("back_material", back_material, (Material, type(None)))):
        if not isinstance(value, kind):
            expected = kind.__name__ if isinstance(kind, type) else "Material or None"
            raise TypeError(f"{name}: got {type(value).__name__}; expected {expected}")
    return Scene(
        mesh=mesh, material=make_material() if material is None else material,
        lights=group_lights(lights), camera=camera, model=_model_matrix(model),
        global_ambient=_rgb("global_ambient", global_ambient),
        background=_rgb("background", background), back_material=back_material,
        local_viewer=bool(local_viewer), two_sided=bool(two_sided))


def replace(obj, **changes):
    """dataclasses.replace for diffshade's frozen pytrees (scene, material, lights...)."""
    return dataclasses.replace(obj, **changes)


__all__ = ["Scene", "make_scene", "replace", "LightGroups"]

"""diffshade: a differentiable Blinn-Phong renderer in JAX for fitting reflectance parameters.

Pipeline: project -> rasterize -> interpolate -> shade -> blend; `render` composes them.
"""

from diffshade import cputune

#: what diffshade.cputune changed in this process (see its docstring; before any import of
#: a module that could start XLA)
CPU_TUNING = cputune.apply()

from diffshade.blend import hard_blend, soft_blend
from diffshade.builtin import BUILTIN_SCENES, builtin_scene
from diffshade.camera import Camera, look_at, projection_matrix, view_matrix
from diffshade.color import COLOR_SPACES, linear_to_srgb, srgb_to_linear
from diffshade.interpolate import gather_faces, interpolate
from diffshade.io import image_transfer, read_image, write_json, write_npy, write_png
from diffshade.lights import (
    AmbientLight,
    DirectionalLight,
    LightGroups,
    PointLight,
    SpotLight,
    ambient_light,
    directional_light,
    group_lights,
    point_light,
    spot_light,
)
from diffshade.material import Material, material
from diffshade.mesh import (
    Mesh,
    box,
    check_mesh,
    face_normals,
    icosphere,
    load_mesh,
    mesh_from_arrays,
    mesh_from_trimesh,
    model_matrix,
    torus,
    transform_mesh,
    vertex_normals,
)
from diffshade.project import Projected, project
from diffshade.raster import Fragments, fragments_from_ids, rasterize
from diffshade.render import (
    rasterize_scene,
    render,
    render_fragments,
    render_parts,
    shade_fragments,
)
from diffshade.scene import Scene, make_scene, replace
from diffshade.scenefile import (
    SceneFileError,
    load_scene,
    save_scene,
    scene_from_dict,
    scene_to_dict,
)
from diffshade.settings import RenderSettings
from diffshade.shading import ShadingParts, shade

__all__ = [
    "BUILTIN_SCENES", "COLOR_SPACES", "SceneFileError", "builtin_scene", "image_transfer",
    "linear_to_srgb", "load_scene", "read_image", "srgb_to_linear",
    "save_scene", "scene_from_dict", "scene_to_dict", "soft_blend", "write_json", "write_npy",
    "write_png",
    "AmbientLight", "Camera", "DirectionalLight", "Fragments", "LightGroups", "Material",
    "Mesh", "PointLight", "Projected", "RenderSettings", "Scene", "ShadingParts", "SpotLight",
    "ambient_light", "box", "check_mesh", "directional_light", "face_normals", "fragments_from_ids",
    "gather_faces", "group_lights", "hard_blend", "icosphere", "interpolate", "load_mesh",
    "look_at", "make_scene", "material", "mesh_from_arrays", "mesh_from_trimesh",
    "model_matrix", "point_light", "project", "projection_matrix", "rasterize",
    "rasterize_scene", "render", "render_fragments", "render_parts", "replace", "shade",
    "shade_fragments", "spot_light", "torus", "transform_mesh", "vertex_normals",
    "view_matrix",
]

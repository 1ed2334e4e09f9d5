"""diffshade: a differentiable Blinn-Phong renderer in JAX for fitting reflectance parameters.

Pipeline: project -> rasterize -> interpolate -> shade -> blend; `render` composes them.
"""

from diffshade.host import cputune

#: what diffshade.host.cputune changed in this process (see its docstring; before any import of
#: a module that could start XLA)
CPU_TUNING = cputune.apply()

from diffshade.io.color import linear_to_srgb, srgb_to_linear
from diffshade.io.images import read_image, write_npy, write_png
from diffshade.io.scenefile import (
    SceneFileError,
    load_scene,
    load_scenes,
    save_scene,
    scene_from_dict,
    scenes_from_dict,
)
from diffshade.pipeline.rendering import (
    blend,
    rasterize_scene,
    render,
    render_fragments,
    render_parts,
    render_views,
    stack_cameras,
)
from diffshade.pipeline.shading_cache import ShadingCache, cache_shading, render_cached
from diffshade.raster.fragments import Fragments, rasterize
from diffshade.raster.interpolation import interpolate
from diffshade.raster.projection import project
from diffshade.scene.area_lights import area_light, sphere_light
from diffshade.scene.builtin import BUILTIN_SCENES, builtin_scene
from diffshade.scene.calibration import camera_from_opencv, camera_to_opencv
from diffshade.scene.camera import Camera, look_at
from diffshade.scene.lights import ambient_light, directional_light, point_light, spot_light
from diffshade.scene.materials import Material, material
from diffshade.scene.mesh import (
    Mesh,
    box,
    icosphere,
    load_mesh,
    mesh_from_arrays,
    mesh_from_trimesh,
    model_matrix,
    torus,
)
from diffshade.scene.scene import Scene, SceneObject, make_scene, replace, scene_object
from diffshade.settings import RenderSettings
from diffshade.shading.lighting import shade

# What users call. Everything else (light classes, blend variants, mesh utilities, the
# scene-file dict writer, io helpers) stays importable from its module.
__all__ = [
    # the types a user holds
    "Camera", "Fragments", "Material", "Mesh", "RenderSettings", "Scene", "SceneFileError",
    "SceneObject", "ShadingCache",
    # building a scene
    "ambient_light", "area_light", "box", "directional_light", "icosphere", "load_mesh",
    "look_at", "camera_from_opencv", "camera_to_opencv",
    "make_scene", "material", "mesh_from_arrays", "mesh_from_trimesh", "model_matrix",
    "point_light", "replace", "scene_object", "sphere_light", "spot_light", "torus",
    "BUILTIN_SCENES", "builtin_scene", "load_scene", "load_scenes", "save_scene",
    "scene_from_dict", "scenes_from_dict",
    # rendering
    "cache_shading", "rasterize_scene", "render", "render_cached", "render_fragments",
    "render_parts", "render_views", "stack_cameras",
    # the pipeline's ops
    "blend", "interpolate", "project", "rasterize", "shade",
    # images
    "linear_to_srgb", "read_image", "srgb_to_linear", "write_npy", "write_png",
]

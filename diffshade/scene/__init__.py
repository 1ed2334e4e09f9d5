"""scene: what is rendered: meshes, cameras, materials, lights, objects, scenes.

The floor's public face, listed in `__all__`: the names other packages (fitting,
data_synth) may use. Modules inside diffshade import each other by full module path, so
this package imports its own modules and nothing above them. `material` here is the
function (the module is diffshade.scene.materials).
"""

from diffshade.scene.area_lights import area_light, sphere_light
from diffshade.scene.builtin import BUILTIN_SCENES, builtin_scene
from diffshade.scene.calibration import (
    camera_from_opencv,
    camera_to_opencv,
    distort,
    opencv_intrinsics,
    opencv_pose,
    with_pose,
)
from diffshade.scene.camera import Camera, look_at
from diffshade.scene.lights import (
    LightGroups,
    ambient_light,
    directional_light,
    group_lights,
    point_light,
    shadow_flags,
    spot_light,
)
from diffshade.scene.materials import Material, material
from diffshade.scene.mesh import (
    Mesh,
    box,
    check_mesh,
    icosphere,
    load_mesh,
    mesh_from_arrays,
    mesh_from_trimesh,
    model_matrix,
    torus,
)
from diffshade.scene.objects import (
    ObjectIds,
    SceneObject,
    stack_materials,
    take_material,
    unstack_material,
)
from diffshade.scene.scene import Scene, make_scene, replace, scene_object
from diffshade.scene.transform import transform_normals, transform_points

__all__ = [
    "area_light", "sphere_light",
    "BUILTIN_SCENES", "builtin_scene",
    "camera_from_opencv", "camera_to_opencv", "distort", "opencv_intrinsics", "opencv_pose",
    "with_pose",
    "Camera", "look_at",
    "LightGroups", "ambient_light", "directional_light", "group_lights", "point_light",
    "shadow_flags", "spot_light",
    "Material", "material",
    "Mesh", "box", "check_mesh", "icosphere", "load_mesh", "mesh_from_arrays",
    "mesh_from_trimesh", "model_matrix", "torus",
    "ObjectIds", "SceneObject", "stack_materials", "take_material", "unstack_material",
    "Scene", "make_scene", "replace", "scene_object",
    "transform_normals", "transform_points",
]

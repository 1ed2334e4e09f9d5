"""io: files in and out: scene files, images, colour encodings, the compilation cache.

The floor's public face, listed in `__all__` (diffshade's own modules import each other
by full module path).
"""

from diffshade.io.colmap import colmap_text, read_colmap
from diffshade.io.color import COLOR_SPACES, decode, encode, linear_to_srgb, srgb_to_linear
from diffshade.io.compile_cache import FAST_COMPILE, LIGHT_COMPILE, store_dir, stored_jit
from diffshade.io.compile_cache import enable as enable_compile_cache
from diffshade.io.image_formats import header as image_header
from diffshade.io.images import (
    check_color_space,
    check_writable,
    read_image,
    write_json,
    write_npy,
    write_png,
    write_text,
)
from diffshade.io.nerf import read_transforms, transforms_dict
from diffshade.io.scenefile import (
    SceneFileError,
    camera_to_dict,
    load_material,
    load_scene,
    load_scenes,
    read_json,
    save_scene,
    save_textures,
    scene_from_dict,
    scene_to_dict,
    scenes_from_dict,
)
from diffshade.io.textures import obj_textures, texture
from diffshade.io.undistort import (
    distort_image,
    pinhole,
    undistort_image,
    undistort_mask,
    undistort_points,
    undistort_rounding,
)
from diffshade.io.xla_cache import await_producer

__all__ = [
    "colmap_text", "read_colmap", "read_transforms", "transforms_dict",
    "COLOR_SPACES", "decode", "encode", "linear_to_srgb", "srgb_to_linear",
    "FAST_COMPILE", "LIGHT_COMPILE", "await_producer", "enable_compile_cache", "store_dir",
    "stored_jit",
    "check_color_space", "check_writable", "image_header", "read_image", "write_json",
    "write_npy", "write_png", "write_text",
    "SceneFileError", "camera_to_dict", "load_material", "load_scene", "load_scenes",
    "read_json", "save_scene", "save_textures", "scene_from_dict", "scene_to_dict",
    "scenes_from_dict",
    "distort_image", "pinhole", "undistort_image", "undistort_mask", "undistort_points",
    "undistort_rounding",
    "obj_textures", "texture",
]

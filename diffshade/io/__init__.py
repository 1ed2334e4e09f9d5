"""io: files in and out: scene files, images, colour encodings, the compilation cache.

The floor's public face, listed in `__all__` (diffshade's own modules import each other
by full module path).
"""

from diffshade.io.color import COLOR_SPACES, decode, encode, linear_to_srgb, srgb_to_linear
from diffshade.io.compile_cache import FAST_COMPILE, LIGHT_COMPILE, stored_jit
from diffshade.io.images import read_image, write_json, write_npy, write_png, write_text
from diffshade.io.scenefile import (
    SceneFileError,
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

__all__ = [
    "COLOR_SPACES", "decode", "encode", "linear_to_srgb", "srgb_to_linear",
    "FAST_COMPILE", "LIGHT_COMPILE", "stored_jit",
    "read_image", "write_json", "write_npy", "write_png", "write_text",
    "SceneFileError", "load_scene", "load_scenes", "read_json", "save_scene", "save_textures",
    "scene_from_dict", "scene_to_dict", "scenes_from_dict",
    "obj_textures", "texture",
]

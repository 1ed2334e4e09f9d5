"""Textures from arrays and image files, and the textures an OBJ file's MTL names.

`texture(source, wrap='repeat')` is what users call (`diffshade.texture`): source is an
array of linear texels [H, W] or [H, W, C], or the path of an image file read with
`read_image` (PNG and JPEG decoded from sRGB to linear like any image, .npy read as
stored, linear). An alpha channel is dropped. Row 0 of the array or image is its top,
v = 1 (diffshade.scene.textures).

`obj_textures(path)` reads the `mtllib` of an OBJ file and, in the first material that
has them, its `map_Kd` and `map_Ks` (relative to the MTL's folder): {'kd': Texture,
'ks': Texture}, either absent when the file names none.
"""

import os

from diffshade.io.images import read_image
from diffshade.scene.textures import make_texture

__all__ = ["obj_textures", "texture"]

#: MTL statements naming a texture, and the material field each maps onto
_MTL_MAPS = {"map_kd": "kd", "map_ks": "ks"}


def _drop_alpha(texels):
    """[H, W, C] without an alpha channel (C = 2: grey + alpha; C = 4: RGB + alpha)."""
    return texels[..., :-1] if texels.shape[-1] in (2, 4) else texels


def texture(source, wrap="repeat"):
    """A Texture (diffshade.scene.textures) of texels or of an image file (module docstring).

    Raises FileNotFoundError for a missing file and ValueError naming the file (or
    `texels`) for one that cannot be read, a NaN, infinite or negative texel, more than
    MAX_TEXELS texels, or a bad `wrap`."""
    if not isinstance(source, (str, os.PathLike)):
        return make_texture(source, wrap)
    path = os.fspath(source)
    return make_texture(_drop_alpha(read_image(path)), wrap, name=f"path: texture {path!r}")


def _statements(path):
    """(keyword lower-cased, rest of the line) of each statement of an OBJ or MTL file."""
    with open(path, encoding="utf-8", errors="replace") as file:
        for line in file:
            tokens = line.split("#", 1)[0].split(None, 1)
            if tokens:
                yield tokens[0].lower(), tokens[1].strip() if len(tokens) > 1 else ""


def _mtl_maps(mtl_path):
    """{field: texture file path} of the first material of an MTL file naming any."""
    found, current = {}, None
    for keyword, rest in _statements(mtl_path):
        if keyword == "newmtl":
            if found:
                break
            current = rest
        elif keyword in _MTL_MAPS and rest and current is not None:
            # options (-s, -o, -bm ...) come first; the file name is the last token
            name = rest.split()[-1]
            found[_MTL_MAPS[keyword]] = os.path.join(os.path.dirname(mtl_path), name)
    return found


def obj_textures(path):
    """{'kd': Texture, 'ks': Texture} named by the OBJ file's MTL (module docstring); {}
    without an MTL file or maps. A named texture file that cannot be read raises as in
    `texture`, naming the MTL file."""
    path = os.fspath(path)
    libraries = [rest for keyword, rest in _statements(path) if keyword == "mtllib" and rest]
    for library in libraries:
        mtl_path = os.path.join(os.path.dirname(path), library)
        if not os.path.isfile(mtl_path):
            continue
        maps = _mtl_maps(mtl_path)
        for field, file in maps.items():
            if not os.path.isfile(file):
                raise ValueError(f"path: MTL file {mtl_path!r}: map_{field.capitalize()} "
                                 f"{file!r} not found; expected an image file beside it")
        if maps:
            return {field: texture(file) for field, file in maps.items()}
    return {}

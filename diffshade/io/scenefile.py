"""JSON scene files: `load_scene`, `save_scene`, `scene_from_dict`, `scene_to_dict`.

A scene file is one JSON object holding everything `make_scene` and `RenderSettings`
take; docs/scene-format.md documents every key. Parsing is strict: each value is
type-checked, unknown keys are errors (a typo must never fall back to a default silently)
and every error is a `SceneFileError` (a ValueError) whose message starts with the key path
of the offending value and says what was expected, e.g.
``lights[1].cutoff: got 120; expected degrees in [0, 90], or 180 (no cone)``;
`load_scene` puts the file name in front. Range checks are the builders' own (look_at,
the light factories, material, the mesh builders, make_scene, RenderSettings): their
ValueErrors are re-raised with the key path put in front of the argument name.

A file may give several cameras (`"cameras": [...]` instead of `"camera"`): one scene per
camera, sharing everything else; `scenes_from_dict` and `load_scenes` return them all,
while `scene_from_dict` and `load_scene` want exactly one.

`scene_to_dict` is the inverse: scene_from_dict(scene_to_dict(scene, settings)) renders
as (scene, settings) do. Key names are the builders' keyword arguments throughout.
"""

import contextlib
import dataclasses
import difflib
import json
import numbers
import os
import re
from typing import NamedTuple

import jax
import numpy as np

from diffshade.io.images import write_json
from diffshade.scene.area_lights import area_light, sphere_light
from diffshade.scene.calibration import camera_from_opencv, camera_to_opencv
from diffshade.scene.camera import PROJECTIONS, look_at
from diffshade.scene.lights import (
    AmbientLight,
    DirectionalLight,
    DiskLight,
    PointLight,
    RectLight,
    SphereLight,
    SpotLight,
    ambient_light,
    directional_light,
    point_light,
    shadow_flags,
    spot_light,
)
from diffshade.scene.materials import material
from diffshade.scene.mesh import (
    WEIGHTINGS,
    box,
    icosphere,
    load_mesh,
    mesh_from_arrays,
    model_matrix,
    torus,
)
from diffshade.scene.objects import object_names, split_mesh, stack_materials, unstack_material
from diffshade.scene.scene import Scene, make_scene, object_count, scene_object
from diffshade.settings import DATA_FIELDS, RenderSettings

__all__ = ["FORMAT_VERSION", "SceneFileError", "camera_to_dict", "load_scene", "load_scenes",
           "read_json",
           "save_scene", "scene_from_dict", "scene_to_dict", "scenes_from_dict"]

FORMAT_VERSION = 1


class SceneFileError(ValueError):
    """A scene file or dict that does not describe a valid scene (message: key path first)."""


# ---- value kinds: what a JSON value must look like, and how to say so ----


class _Kind(NamedTuple):
    expected: str
    accepts: object  # callable(value) -> bool


class _Required(NamedTuple):
    kind: _Kind


def _is_number(value):
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def _is_int(value):
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def _is_row(value, length, item=_is_number):
    return isinstance(value, (list, tuple)) and len(value) == length and all(map(item, value))


def _choice(options):
    return _Kind(f"one of {', '.join(map(json.dumps, options))}",
                 lambda v: isinstance(v, str) and v in options)


def _nullable(kind):
    return _Kind(f"null or {kind.expected}", lambda v: v is None or kind.accepts(v))


_ANY = _Kind("a JSON value", lambda v: True)
_NUMBER = _Kind("a number", _is_number)
_INTEGER = _Kind("an integer", _is_int)
_PIXELS = _Kind("a positive integer", lambda v: _is_int(v) and v > 0)
_BOOL = _Kind("true or false", lambda v: isinstance(v, bool))
_STRING = _Kind("a string", lambda v: isinstance(v, str))
_OBJECT = _Kind("an object", lambda v: isinstance(v, dict))
_ARRAY = _Kind("an array", lambda v: isinstance(v, (list, tuple)))
_VEC3 = _Kind("3 numbers", lambda v: _is_row(v, 3))
_RGB = _Kind("a number (grey) or 3 numbers (linear RGB)", lambda v: _is_number(v) or _is_row(v, 3))
_SCALE = _Kind("a number (uniform) or 3 numbers", lambda v: _is_number(v) or _is_row(v, 3))
_MATRIX = _Kind("a 4x4 matrix (4 rows of 4 numbers)",
               lambda v: _is_row(v, 4, lambda row: _is_row(row, 4)))
_VERSION = _Kind(str(FORMAT_VERSION), lambda v: _is_int(v) and v == FORMAT_VERSION)


def _join(path, key):
    return f"{path}.{key}" if path else key


def _show(value, limit=60):
    text = json.dumps(value, default=repr)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _expect(value, path, kind):
    if not kind.accepts(value):
        raise SceneFileError(f"{path or 'top level'}: got {_show(value)}; "
                             f"expected {kind.expected}")
    return value


def _unknown_key(path, key, table):
    near = difflib.get_close_matches(key, list(table), n=1)
    hint = f"did you mean {json.dumps(near[0])}? " if near else ""
    return SceneFileError(f"{_join(path, key)}: unknown key; {hint}"
                          f"expected one of: {', '.join(sorted(table))}")


def _read_object(value, path, table):
    """The entries of JSON object `value` found at key path `path`, each checked against
    `table` (key -> _Kind, or _Required(kind)). Absent optional keys are left out."""
    _expect(value, path, _OBJECT)
    for key in value:
        if key not in table:
            raise _unknown_key(path, key, table)
    entries = {}
    for key, spec in table.items():
        kind = spec.kind if isinstance(spec, _Required) else spec
        if key in value:
            entries[key] = _expect(value[key], _join(path, key), kind)
        elif isinstance(spec, _Required):
            raise SceneFileError(f"{_join(path, key)}: missing; expected {kind.expected}")
    return entries


_ARGUMENT_NAMES = re.compile(r"(\w+(?:, \w+)*): ")


@contextlib.contextmanager
def _at(path, rename=None):
    """Re-raise a builder's ValueError "name: ..." as SceneFileError "path.name: ...".

    rename maps a builder argument name to its key path where the two differ.
    """
    try:
        yield
    except SceneFileError:
        raise
    except ValueError as err:
        message, rename = str(err), rename or {}
        match = _ARGUMENT_NAMES.match(message)
        if not match:
            raise SceneFileError(f"{path or 'top level'}: {message}") from err
        names = [rename.get(name, _join(path, name)) for name in match.group(1).split(", ")]
        raise SceneFileError(f"{', '.join(names)}: {message[match.end():]}") from err


# ---- mesh ----

_NORMALS = {"weighting": _choice(WEIGHTINGS), "crease_angle": _nullable(_NUMBER)}
_MESH = {
    "path": _STRING, "builtin": _OBJECT, "vertices": _ARRAY, "faces": _ARRAY,
    "normals": _Kind("an object {weighting, crease_angle} or, with vertices, [V, 3] normals",
                     lambda v: isinstance(v, (dict, list, tuple))),
}
_MESH_SOURCES = ("path", "builtin", "vertices")
_GENERATORS = {
    "icosphere": (icosphere, {"subdivisions": _INTEGER, "radius": _NUMBER}),
    "torus": (torus, {"major_radius": _NUMBER, "minor_radius": _NUMBER,
                      "major_segments": _INTEGER, "minor_segments": _INTEGER}),
    "box": (box, {"size": _VEC3}),
}


def _rows(value, path, item, expected):
    """Check value is a list of 3-element rows of `item`; names the first bad row."""
    for i, row in enumerate(value):
        if not _is_row(row, 3, item):
            raise SceneFileError(f"{path}[{i}]: got {_show(row)}; expected 3 {expected}")
    return value


def _only_one(fields, path, options, what):
    given = [key for key in options if key in fields]
    if len(given) != 1:
        got = f"keys {', '.join(map(json.dumps, given))}" if given else "none of them"
        raise SceneFileError(f"{path}: got {got}; expected exactly one of "
                             f"{', '.join(map(json.dumps, options))} ({what})")
    return given[0]


def _builtin_mesh(value, path):
    _read_object(value, path, dict.fromkeys(_GENERATORS, _OBJECT))
    name = _only_one(value, path, tuple(_GENERATORS), "the shape")
    builder, table = _GENERATORS[name]
    kwargs = _read_object(value[name], _join(path, name), table)
    with _at(_join(path, name)):
        return builder(**kwargs)


def _path_mesh(relative, path, base_dir, options):
    full = os.path.join(base_dir, relative)
    if not os.path.exists(full):  # load_mesh says what else is wrong (a folder, the content)
        raise SceneFileError(f"{path}: mesh file {relative!r} not found (looked for "
                             f"{full!r}); expected a path relative to the scene file's folder")
    return load_mesh(full, **options)


def _inline_mesh(fields, path, normals, options):
    vertices = _rows(fields["vertices"], _join(path, "vertices"), _is_number, "numbers")
    faces = _rows(fields["faces"], _join(path, "faces"), _is_int, "integers")
    if normals is not None:
        normals = _rows(normals, _join(path, "normals"), _is_number, "numbers")
    return mesh_from_arrays(vertices, faces, normals, **options)


def _check_mesh_keys(fields, path, source):
    """faces only with (and required by) vertices; [V, 3] normals only with vertices."""
    if (source == "vertices") != ("faces" in fields):
        wanted = "missing; expected" if source == "vertices" else "only allowed with"
        raise SceneFileError(f"{_join(path, 'faces')}: {wanted} {_join(path, 'vertices')}")
    if source != "vertices" and not isinstance(fields.get("normals", {}), dict):
        raise SceneFileError(f"{_join(path, 'normals')}: got an array; expected an object "
                             f"{{weighting, crease_angle}} (arrays only with vertices)")


def _mesh(value, path, base_dir):
    fields = _read_object(value, path, _MESH)
    source = _only_one(fields, path, _MESH_SOURCES, "where the mesh comes from")
    _check_mesh_keys(fields, path, source)
    normals = fields.get("normals")
    has_options = isinstance(normals, dict)
    options_path = _join(path, "normals")
    options = _read_object(normals, options_path, _NORMALS) if has_options else {}
    rename = {name: _join(options_path, name) for name in _NORMALS}
    with _at(path, rename):
        if source == "path":
            return _path_mesh(fields["path"], _join(path, "path"), base_dir, options)
        if source == "vertices":
            return _inline_mesh(fields, path, None if has_options else normals, options)
        mesh = _builtin_mesh(fields["builtin"], _join(path, "builtin"))
        if not has_options:
            return mesh
        # Normal options on a built-in shape replace its analytic normals by computed ones.
        return mesh_from_arrays(np.asarray(mesh.vertices), np.asarray(mesh.faces), **options)


# ---- transform, camera, lights, material, settings ----

_TRANSFORM = {"translate": _VEC3, "rotate_deg": _VEC3, "scale": _SCALE, "matrix": _MATRIX}


def _model(value, path):
    """The 4x4 model matrix from {matrix} or {translate, rotate_deg, scale}."""
    fields = _read_object(value, path, _TRANSFORM)
    if "matrix" in fields:
        others = sorted(set(fields) - {"matrix"})
        if others:
            raise SceneFileError(f"{path}: got matrix and {', '.join(others)}; "
                                 "expected matrix alone or translate, rotate_deg, scale")
        return np.asarray(fields["matrix"], np.float64)
    if _is_number(fields.get("scale")):
        fields["scale"] = [fields["scale"]] * 3
    with _at(path):
        return model_matrix(**fields)


_CAMERA = {
    "eye": _Required(_VEC3), "target": _Required(_VEC3), "up": _VEC3,
    "width": _Required(_PIXELS), "height": _Required(_PIXELS), "fov_y": _NUMBER, "near": _NUMBER,
    "far": _NUMBER, "projection": _choice(PROJECTIONS), "ortho_height": _NUMBER,
}


_MATRIX3 = _Kind("a 3x3 matrix (3 rows of 3 numbers)",
                 lambda v: _is_row(v, 3, lambda row: _is_row(row, 3)))
_DIST = _Kind("[k1, k2, p1, p2] or [k1, k2, p1, p2, k3]",
              lambda v: _is_row(v, 4) or _is_row(v, 5))
# OpenCV's calibration (docs/calibrated-cameras.md); a camera with "K" is of this form
_OPENCV_CAMERA = {
    "K": _Required(_MATRIX3), "R": _Required(_MATRIX3), "t": _Required(_VEC3),
    "width": _Required(_PIXELS), "height": _Required(_PIXELS), "dist": _DIST,
    "near": _NUMBER, "far": _NUMBER,
}


def _camera(value, path):
    """A look-at camera, or an OpenCV one (docs/scene-format.md, "camera")."""
    opencv = isinstance(value, dict) and any(key in value for key in ("K", "R", "t", "dist"))
    kwargs = _read_object(value, path, _OPENCV_CAMERA if opencv else _CAMERA)
    with _at(path):
        return camera_from_opencv(**kwargs) if opencv else look_at(**kwargs)


_COLOURS = {"color": _RGB, "ambient": _RGB, "diffuse": _RGB, "specular": _RGB}
_POINT = {"position": _Required(_VEC3), **_COLOURS, "attenuation": _VEC3, "shadows": _BOOL}
_LIGHTS = {
    "ambient": (ambient_light, {"color": _RGB}),
    "directional": (directional_light, {"direction": _Required(_VEC3), **_COLOURS,
                                        "shadows": _BOOL}),
    "point": (point_light, _POINT),
    "spot": (spot_light, {**_POINT, "direction": _Required(_VEC3), "cutoff": _NUMBER,
                          "exponent": _NUMBER}),
    # a rectangle (edge_u, edge_v) or a disk (normal, radius): area_light says which
    "area": (area_light, {"center": _Required(_VEC3), "edge_u": _VEC3, "edge_v": _VEC3,
                          "normal": _VEC3, "radius": _NUMBER, **_COLOURS, "samples": _PIXELS,
                          "shadows": _BOOL}),
    "sphere": (sphere_light, {"position": _Required(_VEC3), "radius": _Required(_NUMBER),
                              **_COLOURS, "samples": _PIXELS, "shadows": _BOOL}),
}
_LIGHT_TYPE = _choice(tuple(_LIGHTS))


def _light(value, path):
    _expect(value, path, _OBJECT)
    type_path = _join(path, "type")
    if "type" not in value:
        raise SceneFileError(f"{type_path}: missing; expected {_LIGHT_TYPE.expected}")
    factory, table = _LIGHTS[_expect(value["type"], type_path, _LIGHT_TYPE)]
    kwargs = _read_object(value, path, {"type": _LIGHT_TYPE, **table})
    kwargs.pop("type")
    with _at(path):
        return factory(**kwargs)


_MATERIAL = {"ka": _RGB, "kd": _RGB, "ks": _nullable(_RGB), "shininess": _NUMBER,
             "emission": _nullable(_RGB), "kt": _nullable(_RGB)}


def _material(value, path):
    kwargs = _read_object(value, path, _MATERIAL)
    with _at(path):
        return material(**kwargs)


_KIND_OF_DEFAULT = {bool: _BOOL, int: _INTEGER, float: _NUMBER, str: _STRING}


def _settings(value, path):
    """RenderSettings from an object with any of its fields (all of them are keys)."""
    fields = dataclasses.fields(RenderSettings)
    table = {f.name: _KIND_OF_DEFAULT.get(type(f.default), _ANY) for f in fields}
    kwargs = _read_object(value, path, table)
    # A float field given as a JSON integer (sigma: 1) still hashes as the float would.
    kwargs = {k: float(v) if table[k] is _NUMBER else v for k, v in kwargs.items()}
    with _at(path):
        return RenderSettings(**kwargs)


_OBJECT_KEYS = {"mesh": _Required(_OBJECT), "transform": _OBJECT, "material": _OBJECT,
                "back_material": _nullable(_OBJECT)}
_ENTRY_KEYS = {**_OBJECT_KEYS, "name": _STRING}  # an entry of "objects"
_SCENE = {
    "version": _VERSION, **_OBJECT_KEYS, "objects": _ARRAY, "camera": _OBJECT,
    "cameras": _ARRAY, "lights": _ARRAY, "global_ambient": _RGB, "background": _RGB,
    "local_viewer": _BOOL, "two_sided": _BOOL, "settings": _OBJECT,
}


def _cameras(top):
    """The cameras of "camera" (one) or "cameras" (a non-empty array); exactly one given."""
    if "camera" not in top and "cameras" not in top:
        raise SceneFileError("camera: missing; expected an object (or \"cameras\": an array "
                             "of them)")
    if "camera" in top and "cameras" in top:
        raise SceneFileError("camera, cameras: got both; expected exactly one of \"camera\" "
                             "(an object) or \"cameras\" (an array of them)")
    if "camera" in top:
        return [_camera(top["camera"], "camera")]
    if not top["cameras"]:
        raise SceneFileError("cameras: got []; expected at least one camera object")
    return [_camera(v, f"cameras[{i}]") for i, v in enumerate(top["cameras"])]


def _object(value, path, base_dir, table=_OBJECT_KEYS):
    """(mesh, material, back_material, model matrix or None) of an object's keys (the
    top level's, or an entry of "objects")."""
    fields = _read_object(value, path, table)
    mesh = _mesh(fields["mesh"], _join(path, "mesh"), base_dir)
    model = (_model(fields["transform"], _join(path, "transform")) if "transform" in fields
             else None)
    front = _material(fields.get("material", {}), _join(path, "material"))
    back = fields.get("back_material")
    back = None if back is None else _material(back, _join(path, "back_material"))
    return mesh, front, back, model


def _objects(value, base_dir):
    """The SceneObjects of the "objects" array."""
    if not value:
        raise SceneFileError("objects: got []; expected a non-empty array of objects "
                             "{mesh, transform, material, back_material}")
    objects = []
    for i, entry in enumerate(value):
        path = f"objects[{i}]"
        mesh, front, back, model = _object(entry, path, base_dir, _ENTRY_KEYS)
        with _at(path):
            objects.append(scene_object(mesh, front, transform=model, back_material=back,
                                        name=entry.get("name")))
    try:
        object_names(objects)  # unique
    except ValueError as err:
        raise SceneFileError(str(err)) from None
    return objects


def _geometry(data, base_dir):
    """make_scene's geometry keywords: {objects, model} or {mesh, material, back_material,
    model}; a top-level transform moves every object."""
    if "objects" in data:
        single = [key for key in _OBJECT_KEYS if key in data and key != "transform"]
        if single:
            raise SceneFileError(f"{single[0]}: not allowed with objects; expected each "
                                 "object's mesh and materials inside objects")
        model = _model(data["transform"], "transform") if "transform" in data else None
        return {"objects": _objects(data["objects"], base_dir), "model": model}
    if "mesh" not in data:
        raise SceneFileError("mesh: missing; expected an object (or objects: an array of "
                             "objects)")
    single = {key: data[key] for key in _OBJECT_KEYS if key in data}
    mesh, front, back, model = _object(single, "", base_dir)
    return {"mesh": mesh, "material": front, "back_material": back, "model": model}


def scenes_from_dict(data, base_dir=".") -> tuple[tuple[Scene, ...], RenderSettings]:
    """(one Scene per camera, RenderSettings) from a parsed scene file; the scenes share
    the mesh (or objects), lights, materials and switches. Mesh paths are relative to
    base_dir.

    Raises SceneFileError (a ValueError) naming the key path of the first bad value.
    """
    # "mesh" is required only without "objects" (_geometry checks)
    scene_keys = {k: v.kind if isinstance(v, _Required) else v for k, v in _SCENE.items()}
    top = _read_object(data, "", scene_keys)
    geometry = _geometry(top, os.fspath(base_dir))
    cameras = _cameras(top)
    lights = [_light(v, f"lights[{i}]") for i, v in enumerate(top.get("lights", []))]
    kwargs = {k: top[k] for k in ("global_ambient", "background", "local_viewer", "two_sided")
              if k in top}
    with _at("", {"model": "transform"}):
        scene = make_scene(camera=cameras[0], lights=lights, **geometry, **kwargs)
    scenes = (scene, *(dataclasses.replace(scene, camera=c) for c in cameras[1:]))
    return scenes, _settings(top.get("settings", {}), "settings")


def _one(scenes, settings):
    if len(scenes) != 1:
        raise SceneFileError(f"cameras: got {len(scenes)} cameras; expected one here "
                             "(load_scenes and scenes_from_dict read several)")
    return scenes[0], settings


def scene_from_dict(data, base_dir=".") -> tuple[Scene, RenderSettings]:
    """(Scene, RenderSettings) from a parsed scene file of one camera; mesh paths are
    relative to base_dir.

    Raises SceneFileError (a ValueError) naming the key path of the first bad value.
    """
    return _one(*scenes_from_dict(data, base_dir))


def _reject_duplicates(pairs):
    keys = [key for key, _ in pairs]
    for key in keys:
        if keys.count(key) > 1:
            raise SceneFileError(f"key {json.dumps(key)} appears {keys.count(key)} times in "
                                 "one object; expected each key once")
    return dict(pairs)


def read_json(path, what="JSON file"):
    """The parsed JSON file at path (duplicate keys refused). Raises FileNotFoundError
    naming the path when there is no such file, and SceneFileError "<path>: ..." for
    invalid JSON, text that is not UTF-8 or nesting too deep to parse."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        if os.path.isdir(path):
            raise IsADirectoryError(f"{what} is a directory: {path!r}; expected a file")
        raise FileNotFoundError(f"{what} not found: {path!r}")
    try:
        with open(path, encoding="utf-8") as file:
            return json.load(file, object_pairs_hook=_reject_duplicates)
    except json.JSONDecodeError as err:
        raise SceneFileError(f"{path}: line {err.lineno}, column {err.colno}: invalid JSON: "
                             f"{err.msg}") from None
    except UnicodeDecodeError as err:
        raise SceneFileError(f"{path}: byte {err.start}: not UTF-8 text; expected a "
                             f"{what}") from None
    except RecursionError:
        raise SceneFileError(f"{path}: nested too deeply to parse; expected a {what}") from None
    except SceneFileError as err:
        raise SceneFileError(f"{path}: {err}") from None


def load_scenes(path) -> tuple[tuple[Scene, ...], RenderSettings]:
    """(one Scene per camera, RenderSettings) from a JSON scene file; mesh paths are
    relative to its folder. Errors as `load_scene`."""
    path = os.fspath(path)
    data = read_json(path, "scene file")
    try:
        return scenes_from_dict(data, base_dir=os.path.dirname(os.path.abspath(path)))
    except SceneFileError as err:
        raise SceneFileError(f"{path}: {err}") from err


def load_scene(path) -> tuple[Scene, RenderSettings]:
    """(Scene, RenderSettings) from a JSON scene file of one camera; mesh paths are
    relative to its folder.

    Raises FileNotFoundError naming the path when there is no such file, and
    SceneFileError "<path>: <key path>: ..." (or "<path>: line L, column C: ..." for
    invalid JSON) for a file that does not describe a valid scene.
    """
    scenes, settings = load_scenes(path)
    try:
        return _one(scenes, settings)
    except SceneFileError as err:
        raise SceneFileError(f"{os.fspath(path)}: {err}") from err


def _materials_of_objects(entries, names, count, path):
    """The entries of {"objects": [...]} or {"objects": {name: ...}} at key path `path`
    -> one Material stacked in object order, for a scene of `count` objects named
    `names` (None: unnamed, so a list only)."""
    where = _join(path, "objects")
    if isinstance(entries, dict):
        if names is None or set(entries) != set(names):
            raise SceneFileError(f"{where}: got the names {sorted(entries)}; expected one "
                                 "material for each object of the scene, "
                                 f"{list(names) if names else 'unnamed (give a list)'}")
        entries = [entries[n] for n in names]
    if not isinstance(entries, list) or len(entries) != count:
        raise SceneFileError(f"{where}: got {_show(entries)}; expected a list of {count} "
                             "materials (one per object) or an object {name: material}")
    return stack_materials([_material(e, f"{where}[{i}]") for i, e in enumerate(entries)])


def _material_for(data, scene):
    """A parsed material file (load_material) -> the Material for scene."""
    path = "material" if isinstance(data, dict) and "material" in data else ""
    data = data["material"] if path else data
    several = scene.objects is not None
    if isinstance(data, dict) and "objects" in data:
        if not several:
            raise SceneFileError(f"{_join(path, 'objects')}: got materials for several "
                                 "objects; expected one material, as the scene has one object")
        return _materials_of_objects(data["objects"], scene.objects.names,
                                     object_count(scene), path)
    found = _material(data, path)
    return stack_materials([found] * object_count(scene)) if several else found


def load_material(path, scene: Scene):
    """The Material in the JSON file at path, shaped for `scene`: a material object
    (keys ka, kd, ks, shininess, emission, kt, as a scene file's "material"), or any object
    holding one under "material" (a `diffshade fit` result.json); for a scene of several
    objects, {"objects": [one per object]} or {"objects": {name: one}} (a single material
    is given to every object). SceneFileError "<path>: <key path>: ..." for anything else."""
    data = read_json(path, "material file")
    try:
        return _material_for(data, scene)
    except SceneFileError as err:
        raise SceneFileError(f"{os.fspath(path)}: {err}") from err


# ---- writing ----


def _plain(value):
    """A JSON-ready number or nested list; float32 as its shortest round-trip decimal."""
    arr = np.asarray(value)
    if arr.dtype == np.float32:
        # 0.1f is 0.100000001490116...; writing "0.1" reads back as the same float32.
        arr = arr.astype(str).astype(np.float64)
    return arr.tolist()


def _rgb(value):
    """[3] colour as a JSON number when grey, else 3 numbers."""
    rgb = _plain(value)
    return rgb[0] if rgb[0] == rgb[1] == rgb[2] else rgb


def _mesh_to_dict(mesh, mesh_ref):
    if mesh_ref is None:
        return {"vertices": _plain(mesh.vertices), "faces": _plain(mesh.faces),
                "normals": _plain(mesh.normals)}
    if isinstance(mesh_ref, dict):
        return dict(mesh_ref)
    return {"path": os.fspath(mesh_ref)}


_LIGHT_TYPE_OF = {AmbientLight: "ambient", DirectionalLight: "directional", PointLight: "point",
                  SpotLight: "spot", RectLight: "area", DiskLight: "area", SphereLight: "sphere"}


def _light_to_dict(light, i):
    """Light i of a stacked light group: its fields are the factory's keywords (the
    ambient light's one field is its `color`)."""
    kind = _LIGHT_TYPE_OF[type(light)]
    out = {"type": kind}
    for field in dataclasses.fields(light):
        if field.name == "samples":  # static: one count for the whole group
            out["samples"] = light.samples
            continue
        if field.name == "shadows":  # static; written only where on
            count = len(jax.tree.leaves(light)[0])
            out |= {"shadows": True} if shadow_flags(light, count)[i] else {}
            continue
        value = np.asarray(getattr(light, field.name))[i]
        key = "color" if kind == "ambient" else field.name
        out[key] = _rgb(value) if key in _COLOURS else _plain(value)
    return out


def _lights_to_list(groups):
    lights = []
    for group in (groups.ambient, groups.directional, groups.point, groups.spot, groups.rect,
                  groups.disk, groups.sphere):
        count = 0 if group is None else len(jax.tree.leaves(group)[0])
        lights += [_light_to_dict(group, i) for i in range(count)]
    return lights


def _optional_rgb(value):
    return None if value is None else _rgb(value)


def _material_to_dict(mat):
    return {"ka": _rgb(mat.ka), "kd": _rgb(mat.kd), "ks": _optional_rgb(mat.ks),
            "shininess": 0.0 if mat.shininess is None else _plain(mat.shininess),
            "emission": _optional_rgb(mat.emission)} | (
                {} if mat.kt is None else {"kt": _rgb(mat.kt)})


def _is_pinhole_look_at(camera):
    """Whether the look-at keys describe camera (centred, fx = fy, no distortion)."""
    return (not np.any(np.asarray(camera.shift)) and float(camera.focal_ratio) == 1.0
            and not np.any(np.asarray(camera.dist)))


def camera_to_dict(camera) -> dict:
    """A scene file's camera object: the look-at keys, or the OpenCV ones for a camera
    with an off-centre principal point, fx != fy or distortion."""
    if not _is_pinhole_look_at(camera):
        opencv = camera_to_opencv(camera)
        return {**{k: _plain(opencv[k]) for k in ("K", "R", "t", "dist")},
                "width": camera.width, "height": camera.height,
                "near": _plain(camera.near), "far": _plain(camera.far)}
    arrays = {k: _plain(getattr(camera, k)) for k in ("eye", "target", "up", "fov_y", "near",
                                                      "far", "ortho_height")}
    return {**arrays, "width": camera.width, "height": camera.height,
            "projection": camera.projection}


def _objects_to_list(scene):
    """The "objects" of a scene of several objects: inline meshes (in model space, so
    without a transform) and each object's materials."""
    objects = []
    for i in range(object_count(scene)):
        entry = {"mesh": _mesh_to_dict(split_mesh(scene.mesh, scene.objects, i), None),
                 "material": _material_to_dict(unstack_material(scene.material, i))}
        if scene.back_material is not None:
            entry["back_material"] = _material_to_dict(unstack_material(scene.back_material, i))
        if scene.objects.names is not None:
            entry = {"name": scene.objects.names[i], **entry}
        objects.append(entry)
    return objects


def _geometry_to_dict(scene, mesh_ref):
    """The keys of the scene's mesh(es), transform and materials."""
    if scene.objects is not None:
        if mesh_ref is not None:
            raise ValueError(f"mesh_ref: got {mesh_ref!r}; expected None for a scene of "
                             "several objects (their meshes are written inline)")
        out = {"objects": _objects_to_list(scene)}
    else:
        out = {"mesh": _mesh_to_dict(scene.mesh, mesh_ref),
               "material": _material_to_dict(scene.material)}
        if scene.back_material is not None:
            out["back_material"] = _material_to_dict(scene.back_material)
    if not np.array_equal(np.asarray(scene.model), np.eye(4)):
        out["transform"] = {"matrix": _plain(scene.model)}
    return out


def scene_to_dict(scene: Scene, settings: RenderSettings, mesh_ref=None) -> dict:
    """The scene file (a JSON-ready dict) describing scene and settings.

    mesh_ref: None writes the mesh inline (vertices, faces and its normals); a path
    (str or PathLike, relative to the scene file's folder) or a mesh object such as
    {"builtin": {"icosphere": {"subdivisions": 3}}} is written as given instead. A scene
    of several objects is written as "objects" with inline meshes (mesh_ref None).
    Lights are written grouped by type (ambient, directional, point, spot, area
    rectangles, area disks, sphere).
    """
    return {"version": FORMAT_VERSION, **_geometry_to_dict(scene, mesh_ref),
            "camera": camera_to_dict(scene.camera), "lights": _lights_to_list(scene.lights),
            "global_ambient": _rgb(scene.global_ambient), "background": _rgb(scene.background),
            "local_viewer": scene.local_viewer, "two_sided": scene.two_sided,
            "settings": _settings_to_dict(settings)}


def _settings_to_dict(settings):
    """The settings' fields, the continuous ones (possibly arrays) as floats."""
    return {k: float(v) if k in DATA_FIELDS else v
            for k, v in dataclasses.asdict(settings).items()}


def save_scene(path, scene: Scene, settings: RenderSettings, mesh_ref=None) -> str:
    """Write scene_to_dict(scene, settings, mesh_ref) to path as JSON, atomically. An
    absolute mesh_ref path is written relative to the scene file's folder, as every mesh
    path is read, so that the folder keeps working when it is copied or moved with its
    mesh."""
    if isinstance(mesh_ref, (str, os.PathLike)) and os.path.isabs(mesh_ref):
        mesh_ref = os.path.relpath(mesh_ref, os.path.dirname(os.path.abspath(path)))
    return write_json(path, scene_to_dict(scene, settings, mesh_ref))

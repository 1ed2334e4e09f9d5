"""Synthetic fitting datasets: a built-in or loaded mesh, seen by several cameras, each
view lit by one light at a time, rendered by `diffshade.render`.

Layout (chosen so that the data separate every parameter):
- the mesh is normalized to the unit sphere around the origin (model matrix);
- `n_views` cameras on a circle of radius 3.2 around it, azimuths 360 / n_views apart,
  elevations alternating +20 and -10 degrees, fov 40 degrees (the object fills ~90 % of
  the frame);
- `n_lights` lights *per camera*, each lighting its own image, so a dataset holds
  n_views * n_lights images. Light j comes from a direction tilted from the camera's view
  axis by 65 degrees (even j) or 100 degrees (odd j), rolled around the axis by
  135 + 360 j / n_lights degrees; even j are directional lights, odd j point lights at
  distance 5. Each image therefore shows the terminator, a region unlit by its light
  (ambient only: separates ka from kd) and a highlight (ks, shininess);
- OpenGL's light model otherwise: global ambient GLOBAL_AMBIENT, white lights of
  intensity LIGHT_INTENSITY, infinite viewer, one-sided lighting, black background.
Targets are float renders, optionally scaled by a per-image camera gain (exposure and
white balance, applied to the unclamped render before the [0, 1] clip, as a sensor
would), with Gaussian noise and 8-bit quantization.

Each target is `diffshade.render`'s image, computed by its two public halves: every view's
fragments by `rasterize_scene` of the view without its lights, then `render_fragments`
with the lights. The images are the same bit for bit (tests/test_data_synth.py), and the
rasterization, the larger part of a render's compilation, compiles once for all views
instead of once per light layout (a directional and a point light: two programs). It
also runs once per camera: the images of one camera (one per light) share its fragments.
"""

import dataclasses
import os

import jax
import numpy as np

import diffshade as ds
from data_synth.materials import procedural_kd, random_material
from diffshade.budget import check, image_bytes
from diffshade.numerics import float_dtype
from diffshade.scene import MAX_IMAGE_SIZE, LightGroups, transform_points
from fitting.data.views import Dataset, View, view_scene

SHAPES = ("icosphere", "torus", "box")
GLOBAL_AMBIENT = 0.4
LIGHT_INTENSITY = 0.7
CAMERA_DISTANCE = 3.2
POINT_LIGHT_DISTANCE = 5.0
#: the values held per target pixel while a dataset is made (the render's RGBA)
TARGET_CHANNELS = 4


def _normalizing_model(vertices, rotate_deg=(0.0, 0.0, 0.0)):
    """Model matrix [4, 4]: bounding-box centre to the origin, bounding sphere to radius 1."""
    vertices = np.asarray(vertices, np.float64)
    centre = (vertices.min(0) + vertices.max(0)) / 2
    scale = 1.0 / np.max(np.linalg.norm(vertices - centre, axis=1))
    rotation = ds.model_matrix(rotate_deg=rotate_deg).astype(np.float64)
    matrix = rotation @ ds.model_matrix(translate=-centre * scale, scale=(scale,) * 3)
    # what the scene stores (the default float dtype), so that files round-trip
    return matrix.astype(float_dtype())


BUILTIN_MESHES = {
    "icosphere": ({"icosphere": {"subdivisions": 4}}, (0.0, 0.0, 0.0)),
    "torus": ({"torus": {"major_radius": 1.0, "minor_radius": 0.4, "major_segments": 64,
                         "minor_segments": 32}}, (35.0, 0.0, 0.0)),
    "box": ({"box": {"size": [1.0, 1.0, 1.0]}}, (30.0, 40.0, 0.0)),
}
_BUILDERS = {"icosphere": ds.icosphere, "torus": ds.torus, "box": ds.box}


def shape_mesh(shape, uv=False):
    """(Mesh, model [4, 4], info dict) for a built-in shape name, a mesh file path or a
    Mesh. info['mesh_ref'] is the scene-file mesh object of a built-in shape, else None.
    uv: a built-in shape with its UVs (a file or Mesh brings its own)."""
    if isinstance(shape, ds.Mesh):
        return shape, _normalizing_model(shape.vertices), {"shape": "mesh", "mesh_ref": None}
    if isinstance(shape, str) and shape in BUILTIN_MESHES:
        ref, rotate = BUILTIN_MESHES[shape]
        ref = {shape: {**ref[shape], "uv": True}} if uv else ref
        mesh = _BUILDERS[shape](**ref[shape])
    elif isinstance(shape, (str, os.PathLike)) and os.path.splitext(os.fspath(shape))[1]:
        ref, rotate = None, (0.0, 0.0, 0.0)
        mesh = ds.load_mesh(shape)
    else:
        raise ValueError(f"shape: got {shape!r}; expected one of {SHAPES} or a mesh file path")
    info = {"shape": os.fspath(shape), "mesh_ref": None if ref is None else {"builtin": ref}}
    return mesh, _normalizing_model(mesh.vertices, rotate), info


def _camera_frame(eye):
    back = np.asarray(eye, np.float64) / np.linalg.norm(eye)
    right = np.cross((0.0, 1.0, 0.0), back)
    right /= np.linalg.norm(right)
    return back, right, np.cross(back, right)


def camera_eyes(n_views):
    """Eye positions [n_views, 3] around the origin (see module docstring)."""
    eyes = []
    for k in range(n_views):
        azimuth = np.radians(30.0 + 360.0 * k / n_views)
        elevation = np.radians(20.0 if k % 2 == 0 else -10.0)
        eyes.append(CAMERA_DISTANCE * np.array([np.cos(elevation) * np.sin(azimuth),
                                                np.sin(elevation),
                                                np.cos(elevation) * np.cos(azimuth)]))
    return np.array(eyes)


def view_lights(eye, n_lights, intensity=LIGHT_INTENSITY):
    """The n_lights lights of the camera at `eye`, one per image (see module docstring)."""
    back, right, up = _camera_frame(eye)
    lights = []
    for j in range(n_lights):
        tilt = np.radians(65.0 if j % 2 == 0 else 100.0)
        roll = np.radians(135.0 + 360.0 * j / n_lights)
        axis_dir = np.cos(roll) * right + np.sin(roll) * up
        to_light = np.cos(tilt) * back + np.sin(tilt) * axis_dir
        if j % 2 == 0:
            lights.append(ds.directional_light(-to_light, intensity))
        else:
            lights.append(ds.point_light(POINT_LIGHT_DISTANCE * to_light, intensity))
    return lights


def degrade(image, rng, noise_std=0.0, quantize_8bit=False, clamp=True):
    """Add Gaussian noise (std noise_std), clip to [0, 1] when clamping, round to 8 bits."""
    image = np.asarray(image, np.float64)
    if noise_std > 0:
        image = image + rng.normal(0.0, noise_std, image.shape)
    if clamp or quantize_8bit:
        image = np.clip(image, 0.0, 1.0)
    if quantize_8bit:
        image = np.round(image * 255.0) / 255.0
    return image.astype(np.float32)


def _check_counts(n_views, n_lights, size, noise_std):
    for name, value in (("n_views", n_views), ("n_lights", n_lights), ("size", size)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name}: got {value!r}; expected a positive integer")
    if not (np.isfinite(noise_std) and noise_std >= 0):
        raise ValueError(f"noise_std: got {noise_std!r}; expected a number >= 0")
    if size > MAX_IMAGE_SIZE:
        raise ValueError(f"size: got {size}; expected at most {MAX_IMAGE_SIZE} pixels a side")
    images = n_views * n_lights
    # all three settings are named: any of them can make the dataset too large
    check("n_views, n_lights, size", f"{n_views}, {n_lights}, {size}",
          images * image_bytes(size, size, TARGET_CHANNELS),
          f"a dataset of {images} images of {size}x{size} pixels", size * size * TARGET_CHANNELS,
          host=True)


def _check_gains(gains, n_images):
    """gains: None, or per image a positive gain or 3 of them -> [n_images, 3] or None."""
    if gains is None:
        return None
    try:
        arr = np.asarray(gains, np.float64)
    except (TypeError, ValueError):
        arr = np.zeros(0)
    if arr.ndim == 1:
        arr = arr[:, None] * np.ones(3)
    if arr.shape != (n_images, 3) or not np.all(np.isfinite(arr)) or np.any(arr <= 0):
        raise ValueError(f"gains: got {gains!r}; expected {n_images} positive numbers (one "
                         "per image) or {n_images} rows of 3 (RGB)")
    return arr


# render's second half, compiled as render compiles it (default XLA options)
_render_fragments = jax.jit(ds.render_fragments)


def _render_target(dataset, index, gain, fragments):
    """The float render of view `index` with the truth (module docstring: rasterized
    without the view's lights, once per camera: `fragments` holds them by camera); with a
    gain, the unclamped render times the gain (the clip to [0, 1] is degrade's, as a
    sensor's after its gain)."""
    settings = dataset.settings
    camera = dataset.views[index].camera
    if id(camera) not in fragments:  # the views of one camera share its Camera (_layout)
        fragments[id(camera)] = ds.rasterize_scene(
            view_scene(dataset, index, dataset.truth, LightGroups()), settings)
    frags = fragments[id(camera)]
    scene = view_scene(dataset, index, dataset.truth)
    if gain is None:
        return np.asarray(_render_fragments(scene, frags, settings))[..., :3]
    unclamped = dataclasses.replace(settings, clamp=False)
    return np.asarray(_render_fragments(scene, frags, unclamped))[..., :3] * gain


def _scene_geometry(scene, material):
    """Dataset keywords of a Scene: its mesh (joined objects and their ids), its model
    followed by the normalizing one, its global ambient, lighting switches and materials
    (the truth)."""
    if material is not None:
        raise ValueError(f"material: got {material!r:.60}; expected None with a Scene, whose "
                         "materials (one per object) are the truth")
    world = transform_points(scene.model, scene.mesh.vertices)
    model = np.asarray(_normalizing_model(world), np.float64) @ np.asarray(scene.model)
    return {"mesh": scene.mesh, "model": model.astype(float_dtype()),
            "objects": scene.objects, "global_ambient": scene.global_ambient,
            "local_viewer": scene.local_viewer, "two_sided": scene.two_sided,
            "truth": scene.material}, {"shape": "scene", "mesh_ref": None}


def _geometry(shape, material, rng, texture=None):
    """(Dataset keywords, info) of a shape (see make_dataset)."""
    if isinstance(shape, ds.Scene):
        if texture is not None:
            raise ValueError(f"texture: got {texture!r} with a scene; expected the scene "
                             "file's own textures (or a shape)")
        return _scene_geometry(shape, material)
    if material is not None and (not isinstance(material, ds.Material)
                                 or np.ndim(material.kd) > 1):
        raise ValueError("material: got materials for several objects; expected one Material "
                         "for a shape (a Scene holds several objects)")
    mesh, model, info = shape_mesh(shape, uv=texture is not None)
    truth = random_material(rng) if material is None else material
    if texture is not None:
        truth = _with_texture(truth, texture, mesh, shape)
        info["texture"] = {"kd": texture}
    return {"mesh": mesh, "model": model, "global_ambient": GLOBAL_AMBIENT,
            "truth": truth}, info


def _with_texture(truth, texture, mesh, shape):
    """truth with kd the procedural texture of texture x texture texels."""
    if not isinstance(texture, int) or isinstance(texture, bool) or not 1 <= texture <= 8192:
        raise ValueError(f"texture: got {texture!r}; expected a resolution in [1, 8192]")
    if mesh.uv is None:
        raise ValueError(f"texture: the mesh of {shape!r} has no UVs; expected a built-in "
                         "shape or a mesh file with texture coordinates")
    return ds.replace(truth, kd=ds.texture(procedural_kd(texture)))


def _layout(shape, material, rng, n_views, n_lights, size, shading, settings, texture):
    """(Dataset with black targets, info) of make_dataset's arguments (the material drawn
    from `rng` when None)."""
    settings = ds.RenderSettings(shading=shading) if settings is None else settings
    geometry, info = _geometry(shape, material, rng, texture)
    blank = np.zeros((size, size, 3), np.float32)
    views = []
    for eye in camera_eyes(n_views):
        camera = ds.look_at(eye, (0.0, 0.0, 0.0), width=size, height=size, fov_y=40.0)
        views += [View(camera, [light], blank) for light in view_lights(eye, n_lights)]
    return Dataset(views=views, settings=settings, **geometry), info


def dataset_layout(shape="icosphere", material=None, *, n_views=3, n_lights=2, size=128,
                   seed=0, shading="phong", settings=None, texture=None) -> Dataset:
    """The Dataset make_dataset(...) with these arguments renders, before it renders:
    its mesh, cameras, lights, settings and truth, with black targets. What the fit of
    that dataset compiles depends on these alone (fitting.precompile)."""
    _check_counts(n_views, n_lights, size, 0.0)
    return _layout(shape, material, np.random.default_rng(seed), n_views, n_lights, size,
                   shading, settings, texture)[0]


def make_dataset(shape="icosphere", material=None, *, n_views=3, n_lights=2, size=128,
                 seed=0, quantize_8bit=False, noise_std=0.0, shading="phong",
                 settings=None, gains=None, texture=None) -> Dataset:
    """A Dataset of n_views * n_lights images (size x size) of `shape` ('icosphere',
    'torus', 'box', a mesh file path or a Mesh) with `material` (random from `seed` when None),
    laid out as in the module docstring. settings: RenderSettings (default: `shading`
    with clamping). gains: per image a camera gain (a number, or RGB), applied before the
    clip; None: 1. The true material is the dataset's `truth`.

    `shape` may also be a Scene (a scene file's, of one object or several): its mesh or
    objects, model (then normalized), materials (the truth; `material` must be None),
    global ambient and lighting switches are kept; its camera and lights are replaced by
    the layout's.

    texture: a resolution RES: the truth's kd is then data_synth.materials.procedural_kd
    (RES x RES texels) over the shape's UVs (a built-in shape gets its UVs)."""
    _check_counts(n_views, n_lights, size, noise_std)
    gains = _check_gains(gains, n_views * n_lights)
    rng = np.random.default_rng(seed)
    dataset, info = _layout(shape, material, rng, n_views, n_lights, size, shading, settings,
                            texture)
    fragments = {}  # by camera
    images = [_render_target(dataset, i, None if gains is None else gains[i], fragments)
              for i in range(len(dataset.views))]
    views = [View(v.camera, v.lights, degrade(img, rng, noise_std, quantize_8bit,
                                              dataset.settings.clamp))
             for v, img in zip(dataset.views, images, strict=True)]
    info.update(seed=seed, quantize_8bit=quantize_8bit, noise_std=noise_std,
                n_views=n_views, n_lights=n_lights)
    if gains is not None:
        info["gains"] = gains.tolist()
    return dataclasses.replace(dataset, views=views, info=info)

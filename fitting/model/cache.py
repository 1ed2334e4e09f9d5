"""The fast path: rasterize each view once, then shade only the covered pixels per step.

With geometry and cameras fixed, everything the lighting core needs except the material
and the lights is fixed too. `build_cache` rasterizes every view once
(`diffshade.rasterize_scene`), keeps the pixels that are covered, inside the view's mask
and (by default) not on the silhouette, and stores only what is fixed: the shading samples
those pixels read (world point, normal, direction to the viewer) and how they read them.
Both come from `diffshade.shading.samples`, the code `render` uses, per shading mode (per pixel
for Phong, per vertex and side for Gouraud and flat_last, per face for flat); which of
them the kept pixels' fragments read, and how, is `diffshade.pipeline.slot_samples`, the
step `diffshade.cache_shading` takes for the fragments a render blends. Two-sided
lighting is in the normals (reversed on back faces); the fitted material serves both
sides. With several objects each sample keeps its object id, which picks its row of the
(stacked) material.

Shadows: with geometry and lights fixed, which samples a shadowed light reaches is fixed
too. `build_cache` computes that visibility once per sample and light, with the shadow
maps and the lookup `render` uses (diffshade.shading.shadows, diffshade.shading.lighting
.light_visibility), and `shade` scales those lights' diffuse and specular terms by it,
where render does (shadowed points keep only the ambient terms). A fit that moves a
shadowed light (light_positions) therefore keeps its shadows where the given positions
cast them.

Transparency: with a material that has a kt (the base material's, see `build_cache`), the
kept pixels keep their K fragment layers (settings.faces_per_pixel), nearest first, and
their colours are composited as render composites them (diffshade.composite.transparency
.layer_weights) with each layer's object's kt, so kt can be fitted. What a pixel shows
through its last layer is the background, black in a dataset's scenes
(fitting.data.views.view_scene), so it adds nothing.

`predict` then runs `diffshade.shade` on the samples and gives the colours of the kept
pixels, equal to `diffshade.render` at those pixels (tested). Silhouette pixels are left
out (`edge_margin`) because a pixel cut by the outline is where two rasterizers, or a
rendered target and a photograph, disagree most.

Textures: with a base material that has a texture (a kd or ks map held fixed while the
uniform quantities are fitted, fitting.texture_run), each sample keeps its UV and `shade`
reads the material's textures there (diffshade.shading.textured_material), as render
reads them.
"""

import dataclasses
import hashlib
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.composite import layer_weights, layers_needed
from diffshade.io import FAST_COMPILE, LIGHT_COMPILE, stored_jit
from diffshade.numerics import clamp01, float_dtype
from diffshade.pipeline import slot_samples, view_dirs
from diffshade.raster import fragments_from_ids, project, search_depth, search_faces
from diffshade.scene import LightGroups, Material, Texture, shadow_flags, take_material
from diffshade.scene import material as make_material
from diffshade.shading import (
    Reader,
    ShadingParts,
    light_visibility,
    read,
    shade,
    shading_samples,
    shadow_maps,
    textured_material,
)
from fitting.data.views import Dataset, view_scene

# Geometry does not depend on the material; one fixed material keeps one compilation
# (and one with a kt: a transparent material needs every fragment layer).
_GEOMETRY_MATERIAL = make_material()
_LAYERED_MATERIAL = make_material(kt=0.0)
# A one-texel map makes the samples carry their UVs (its texel plays no part).
_UV_MAP = Texture(np.ones((1, 1, 3), np.float32))
TEXTURED_FIELDS = ("kd", "ks", "shininess")


def has_texture(material) -> bool:
    """Whether `material` has a texture (a kd, ks or shininess map)."""
    return any(isinstance(getattr(material, name), Texture) for name in TEXTURED_FIELDS)


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ViewSamples:
    """One view's shading samples and the kept pixels that read them.

    points, normals, view_dirs: [S, 3] world space (unit normals, reversed on back faces
    under two-sided lighting, and unit view_dirs); target: [N, 3] target colours of the
    kept pixels; pixels: [N] int32 flat index (row * width + column) of each kept pixel;
    reader: diffshade.shading.samples.Reader of the kept pixels' fragments ([N, 1, K] ids, one row
    each) into the samples, with no table when sample i is fragment i (Phong); objects:
    [S] int32 object ids of the samples (several objects), or None; shadows: {(kind,
    index): [S, 1]} the samples' visibility from each light with shadows, or None;
    layers: [N, K] bool, the kept pixels' fragment layers that hold a face (nearest
    first), or None for one opaque layer (K = 1); layer_objects: [N, K] int32 object of
    each layer (several objects and layers), or None; uv: [S, 2] the samples' texture
    coordinates (for a textured base material), or None."""

    points: jax.Array
    normals: jax.Array
    view_dirs: jax.Array
    target: jax.Array
    pixels: jax.Array
    reader: Reader
    objects: jax.Array | None = None
    shadows: dict | None = None
    layers: jax.Array | None = None
    layer_objects: jax.Array | None = None
    uv: jax.Array | None = None


@partial(jax.tree_util.register_dataclass,
         data_fields=["views", "lights", "material", "global_ambient", "settings"],
         meta_fields=[])
@dataclasses.dataclass(frozen=True)
class FitData:
    """Everything a cached fit step reads: views: tuple of ViewSamples (the fit's programs
    take them stacked once, a fitting.model.batch.ViewBatch: fitting.model.batch.batched); lights:
    tuple of LightGroups (one per view); material: the base Material (held-fixed quantities);
    global_ambient: [3]; settings: RenderSettings (a pytree: its structure is static)."""

    views: tuple
    lights: tuple
    material: Material
    global_ambient: jax.Array
    settings: object


def erode(mask, margin: int):
    """[H, W] bool mask minus the pixels within `margin` 4-neighbour steps of its outside."""
    for _ in range(margin):
        padded = np.pad(mask, 1, constant_values=False)
        mask = (mask & padded[:-2, 1:-1] & padded[2:, 1:-1]
                & padded[1:-1, :-2] & padded[1:-1, 2:])
    return mask


# Each view's geometry is rasterized once per fit (and once more for the report's
# panels): these programs compile without LLVM's optimizations (FAST_COMPILE), which takes
# about half their compile time off and costs nothing measurable at run time
# (benchmarks/fit_compile.py) ...
_project = stored_jit(project, compiler_options=FAST_COMPILE)


def _fragments(proj, faces, camera, settings, found, depth):
    soft = settings.raster == "soft"
    if found is None:  # JAX's tile search (settings.kernels)
        found = search_faces(proj.clip, faces, camera, depth, settings, soft)
    return fragments_from_ids(proj, faces, *found, soft=soft, host=False)


_host_searched = stored_jit(_fragments, static_argnames=("depth",),
                            compiler_options=FAST_COMPILE)
# ... except JAX's tile search (settings.kernels 'jax', as on a fresh install's first
# runs, diffshade.host.warmup): without LLVM's optimizations it runs 5x slower (0.25 s of
# CPU against 0.05 s for a 128x128 view of the README's sphere, twice per view and fit),
# with LIGHT_COMPILE it compiles in about 1.3x the time.
_jax_searched = stored_jit(_fragments, static_argnames=("depth",),
                           compiler_options=LIGHT_COMPILE)


def geometry_scene(dataset: Dataset, index: int, layered=False, textured=False):
    """View `index`'s Scene with a fixed material (with a kt when `layered`: every
    fragment layer is kept; with a kd map when `textured`: the samples carry UVs) and no
    lights: what rasterizing needs, one pytree structure for every view (so they share
    the compilations)."""
    material = _LAYERED_MATERIAL if layered else _GEOMETRY_MATERIAL
    if textured:
        material = dataclasses.replace(material, kd=_UV_MAP)
    return view_scene(dataset, index, material, LightGroups())


def _geometry_key(scene, settings, layers):
    """A digest of everything fixed_fragments' value depends on (the scene's structure and
    values, the settings and the kernels they mean, the layers, x64); None inside a
    trace."""
    leaves, tree = jax.tree.flatten(scene)
    digest = hashlib.sha256(repr((tree, settings, settings.use_host_kernels(), layers,
                                  jax.config.jax_enable_x64)).encode())
    for leaf in leaves:
        if isinstance(leaf, jax.core.Tracer):
            return None
        value = np.asarray(leaf)
        digest.update(repr((value.dtype, value.shape, getattr(leaf, "weak_type", False)))
                      .encode())
        digest.update(value.tobytes())
    return digest.digest()


_last = {}  # {key: (Projected, Fragments)}: the last geometry fixed_fragments rasterized


def fixed_fragments(scene, settings, layers=1):
    """(Projected, Fragments) of `scene`: diffshade.rasterize's fragments, equal to them
    up to float rounding, for geometry that does not change (a fit's views).

    Nothing here compiles a host callback, so every program is kept by JAX's persistent
    compilation cache (diffshade.io.compile_cache): with host kernels (settings.kernels) the
    candidate search runs once, on NumPy arrays between two jitted programs
    (diffshade.host.hostcall), and the per-fragment geometry is computed in jax.numpy.

    The views of one camera (one per light) have the same geometry scene: the last one
    rasterized is kept, and a call with the same scene, settings and layers (the next
    view of that camera, in the cache and in the report's panels) gets it again."""
    key = _geometry_key(scene, settings, layers)
    if key is None or key not in _last:
        found = _rasterized(scene, settings, layers)
        _last.clear()
        if key is None:
            return found
        _last[key] = found
    return _last[key]


def _rasterized(scene, settings, layers):
    proj = _project(scene)
    depth = search_depth(settings, layers)
    if not settings.use_host_kernels():
        return proj, _jax_searched(proj, scene.mesh.faces, scene.camera, settings, None, depth)
    found = search_faces(proj.clip, scene.mesh.faces, scene.camera, depth, settings,
                         settings.raster == "soft")
    return proj, _host_searched(proj, scene.mesh.faces, scene.camera, settings, found, depth)


# Not FAST_COMPILE: the samples' normals and view directions compiled so round
# differently, and a specular exponent of 350 magnifies that: the README fit's ks came
# out 1.3e-5 off the truth instead of 1.3e-6, to save a small part of one compilation.
@stored_jit
def _geometry(scene, settings, proj, frags):
    samples, reader = shading_samples(scene, proj, frags, settings.shading, host=False)
    return {"samples": samples, "reader": reader, "valid": frags.valid[..., 0],
            "view_dirs": view_dirs(scene, samples.points), "face_ids": frags.face_ids}


@jax.jit
def sample_visibility(scene, samples, settings) -> dict:
    """{(kind, index): [..., 1]} the visibility of the shading samples from every light of
    the scene with shadows, as render computes it (diffshade.shading.shadows)."""
    return light_visibility(scene.lights, samples.points, samples.normals, settings,
                            shadow_maps(scene, settings))


def casts_shadows(lights: LightGroups) -> bool:
    """Whether any light of `lights` has shadows."""
    groups = [getattr(lights, kind) for kind in ("directional", "point", "spot")]
    return any(any(shadow_flags(g, jax.tree.leaves(g)[0].shape[0]))
               for g in groups if g is not None)


def view_geometry(scene, settings) -> dict:
    """Rasterize and project once (fixed_fragments): the mode's shading samples
    (diffshade.shading.samples) with their view directions, how the pixels read them, and which
    pixels are covered ('valid', [H, W]). Lights and material play no part, so views of
    one camera size share the compilations (geometry_scene)."""
    proj, frags = fixed_fragments(scene, settings, layers_needed(scene, settings))
    return _geometry(scene, settings, proj, frags)


def kept_pixels(valid, mask, edge_margin):
    """Flat indices [N] of the covered pixels (valid: [H, W] bool) inside `mask` ([H, W]
    bool or None) and at least `edge_margin` pixels inside the silhouette."""
    keep = erode(np.asarray(valid), edge_margin)
    if mask is not None:
        keep = keep & mask
    return np.flatnonzero(keep).astype(np.int32)


def _kept_samples(geo, pixels, arrays):
    """`arrays` ([..., C] per sample, as geo's samples) at the samples the kept pixels'
    fragments (K layers each) read: [S, C] each; and the Reader of those fragments into
    them, [N, 1, K] ids (only the samples read are kept: diffshade.pipeline.slot_samples).
    An empty layer reads some sample: it weighs nothing in the composite
    (ViewSamples.layers)."""
    layers = np.asarray(geo["face_ids"]).shape[-1]
    slots = (pixels[:, None] * layers + np.arange(layers, dtype=np.int32)).reshape(-1)
    kept, reader = slot_samples(arrays, geo["reader"], slots, (len(pixels), 1, layers))
    weights = None if reader.weights is None else jnp.asarray(reader.weights, float_dtype())
    table = None if reader.table is None else jnp.asarray(reader.table, jnp.int32)
    return kept, Reader(reader.ids, weights, table)


def _layer_fields(dataset, geo, pixels):
    """(layers [N, K] bool, layer_objects [N, K] int32 or None) of the kept pixels."""
    face_ids = np.asarray(geo["face_ids"])
    face_ids = face_ids.reshape(-1, face_ids.shape[-1])[pixels]
    objects = None
    if dataset.objects is not None:
        faces = np.asarray(dataset.objects.faces)[np.maximum(face_ids, 0)]
        objects = jnp.asarray(faces, jnp.int32)
    return jnp.asarray(face_ids >= 0), objects


def view_samples(dataset: Dataset, index: int, edge_margin=1, layered=False,
                 textured=False) -> ViewSamples:
    """Rasterize view `index` once and return its ViewSamples (with every fragment layer
    when `layered`: for a transparent material; with the samples' UVs when `textured`),
    the visibility of its samples from its lights with shadows included."""
    scene = geometry_scene(dataset, index, layered, textured)
    geo = view_geometry(scene, dataset.settings)
    view = dataset.views[index]
    pixels = kept_pixels(geo["valid"], view.mask, edge_margin)
    samples = geo["samples"]
    arrays = [samples.points, samples.normals, geo["view_dirs"]]
    if samples.objects is not None:
        arrays.append(samples.objects[..., None])
    if textured:
        arrays.append(samples.uv)
    shadows = {}
    if casts_shadows(view.lights):
        lit = view_scene(dataset, index, scene.material)
        shadows = sample_visibility(lit, samples, dataset.settings)
    kept, reader = _kept_samples(geo, pixels, [np.asarray(a) for a in
                                               [*arrays, *shadows.values()]])
    floats = partial(jnp.asarray, dtype=float_dtype())
    points, normals, view_dirs = kept[:3]
    objects = (jnp.asarray(kept[3][:, 0], jnp.int32) if samples.objects is not None
               else None)
    uv = floats(kept[len(arrays) - 1]) if textured else None
    visible = dict(zip(shadows, (floats(a) for a in kept[len(arrays):]), strict=True))
    layers, layer_objects = _layer_fields(dataset, geo, pixels) if layered else (None, None)
    return ViewSamples(floats(points), floats(normals), floats(view_dirs),
                       floats(view.target.reshape(-1, 3)[pixels]), jnp.asarray(pixels), reader,
                       objects, visible or None, layers, layer_objects, uv)


def build_cache(dataset: Dataset, material: Material, *, edge_margin: int = 1,
                uv: bool | None = None) -> FitData:
    """FitData for `dataset`, with `material` as the base (held-fixed) material.

    edge_margin: pixels dropped inside the silhouette (0 keeps every covered pixel).
    A `material` with a kt (fitting kt needs one) keeps every pixel's fragment layers;
    the samples keep their UVs when `uv` says so (default: when `material` has a
    texture, has_texture; a mesh without UVs has none to keep). Raises ValueError when
    the settings rasterize softly (only hard coverage is cached) or when no pixel is
    kept."""
    if dataset.settings.raster != "hard":
        raise ValueError(f"settings.raster: got {dataset.settings.raster!r}; the cache "
                         "needs 'hard' (fit soft-rasterized data with the full-render loss)")
    if isinstance(edge_margin, bool) or not isinstance(edge_margin, int) or edge_margin < 0:
        raise ValueError(f"edge_margin: got {edge_margin!r}; expected an integer >= 0")
    layered = material.kt is not None
    textured = (has_texture(material) if uv is None else uv) and dataset.mesh.uv is not None
    views = tuple(view_samples(dataset, i, edge_margin, layered, textured)
                  for i in range(len(dataset.views)))
    if sum(v.pixels.shape[0] for v in views) == 0:
        raise ValueError("dataset: no covered pixel is left in any view (check the cameras, "
                         f"the masks and edge_margin={edge_margin})")
    scene = view_scene(dataset, 0, material)
    return FitData(views, tuple(v.lights for v in dataset.views), material,
                   scene.global_ambient, dataset.settings)


def _layer_kt(material, samples: ViewSamples):
    """[N, K, 3] transmittance of the kept pixels' layers (0 for a material without kt)."""
    shape = samples.layers.shape + (3,)
    if material.kt is None:
        return jnp.zeros(shape, samples.points.dtype)
    kt = material.kt
    if samples.layer_objects is not None:
        kt = jnp.take(kt, samples.layer_objects, axis=0)
    return jnp.broadcast_to(kt, shape)


def _to_pixels(values, samples: ViewSamples, material):
    """Sample values [S, C] -> kept-pixel values [N, C], as render combines them: read by
    the fragments, then their layers composited with `material`'s kt (in XLA: the arrays
    are small, and a gather beats a host callback per view and step)."""
    layers = read(values, samples.reader, host=False).reshape(
        samples.pixels.shape + (samples.reader.ids.shape[-1], values.shape[-1]))
    if samples.layers is None:
        return layers[:, 0]
    weights, _ = layer_weights(_layer_kt(material, samples), samples.layers)
    return jnp.sum(weights * layers, -2)


def _shade_samples(material, lights: LightGroups, global_ambient, samples, settings):
    if samples.objects is not None:
        material = take_material(material, samples.objects)
    if samples.uv is not None:
        material = textured_material(material, samples.uv, settings.use_host_kernels())
    return shade(material, lights, global_ambient, samples.points, samples.normals,
                 samples.view_dirs, settings, samples.shadows)


def pixel_parts(material, lights, global_ambient, samples: ViewSamples,
                settings) -> ShadingParts:
    """Unclamped ambient, diffuse, specular and emission at the kept pixels: [N, 3] each
    (the parts are interpolated, and layers composited, like colours, without clamping)."""
    parts = _shade_samples(material, lights, global_ambient, samples, settings)
    return parts.map(lambda a: _to_pixels(a, samples, material))


def predict(material, lights, global_ambient, samples: ViewSamples, settings):
    """Rendered colours at the kept pixels: [N, 3], clamped as the renderer clamps."""
    total = _shade_samples(material, lights, global_ambient, samples, settings).total
    colour = _to_pixels(clamp01(total) if settings.clamp else total, samples, material)
    # composited clamped colours can exceed 1 by a rounding error, as in render
    return clamp01(colour) if settings.clamp and samples.layers is not None else colour

"""The fast path: rasterize each view once, then shade only the covered pixels per step.

With geometry and cameras fixed, everything the lighting core needs except the material
and the lights is fixed too. `build_cache` rasterizes every view once
(`diffshade.rasterize_scene`), keeps the pixels that are covered, inside the view's mask
and (by default) not on the silhouette, and stores only what is fixed: the shading samples
those pixels read (world point, normal, direction to the viewer) and how they read them.
Both come from `diffshade.samples`, the code `render` uses, per shading mode (per pixel
for Phong, per vertex and side for Gouraud and flat_last, per face for flat). Two-sided
lighting is in the normals (reversed on back faces); the fitted material serves both
sides. With several objects each sample keeps its object id, which picks its row of the
(stacked) material.

`predict` then runs `diffshade.shade` on the samples and gives the colours of the kept
pixels, equal to `diffshade.render` at those pixels (tested). Silhouette pixels are left
out (`edge_margin`) because a pixel cut by the outline is where two rasterizers, or a
rendered target and a photograph, disagree most.
"""

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.lights import LightGroups
from diffshade.material import Material
from diffshade.material import material as make_material
from diffshade.numerics import clamp01, float_dtype
from diffshade.objects import take_material
from diffshade.project import project
from diffshade.raster import fragments_from_ids, search_depth, search_faces
from diffshade.render import view_dirs
from diffshade.samples import Reader, read, shading_samples
from diffshade.shading import ShadingParts, shade
from fitting.data import Dataset, view_scene

# Geometry does not depend on the material; one fixed material keeps one compilation.
_GEOMETRY_MATERIAL = make_material()


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ViewSamples:
    """One view's shading samples and the kept pixels that read them.

    points, normals, view_dirs: [S, 3] world space (unit normals, reversed on back faces
    under two-sided lighting, and unit view_dirs); target: [N, 3] target colours of the
    kept pixels; pixels: [N] int32 flat index (row * width + column) of each kept pixel;
    reader: diffshade.samples.Reader of the kept pixels ([N, 1, 1] ids, one row each) into
    the samples, with no table when sample i is pixel i (Phong); objects: [S] int32
    object ids of the samples (several objects), or None."""

    points: jax.Array
    normals: jax.Array
    view_dirs: jax.Array
    target: jax.Array
    pixels: jax.Array
    reader: Reader
    objects: jax.Array | None = None


@partial(jax.tree_util.register_dataclass,
         data_fields=["views", "lights", "material", "global_ambient", "settings"],
         meta_fields=[])
@dataclasses.dataclass(frozen=True)
class FitData:
    """Everything a cached fit step reads: views: tuple of ViewSamples; lights: tuple of
    LightGroups (one per view); material: the base Material (held-fixed quantities);
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


_project = jax.jit(project)


@partial(jax.jit, static_argnames=("depth",))
def _fragments(proj, faces, camera, settings, found, depth):
    soft = settings.raster == "soft"
    if found is None:  # JAX's tile search (settings.kernels)
        found = search_faces(proj.clip, faces, camera, depth, settings, soft)
    return fragments_from_ids(proj, faces, *found, soft=soft, host=False)


def geometry_scene(dataset: Dataset, index: int):
    """View `index`'s Scene with a fixed material and no lights: what rasterizing needs,
    one pytree structure for every view (so they share the compilations)."""
    return view_scene(dataset, index, _GEOMETRY_MATERIAL, LightGroups())


def fixed_fragments(scene, settings, layers=1):
    """(Projected, Fragments) of `scene`: diffshade.rasterize's fragments, equal to them
    up to float rounding, for geometry that does not change (a fit's views).

    Nothing here compiles a host callback, so every program is kept by JAX's persistent
    compilation cache (diffshade.compile_cache): with host kernels (settings.kernels) the
    candidate search runs once, on NumPy arrays between two jitted programs
    (diffshade.hostcall), and the per-fragment geometry is computed in jax.numpy."""
    proj = _project(scene)
    depth = search_depth(settings, layers)
    found = None
    if settings.use_host_kernels():
        found = search_faces(proj.clip, scene.mesh.faces, scene.camera, depth, settings,
                             settings.raster == "soft")
    return proj, _fragments(proj, scene.mesh.faces, scene.camera, settings, found, depth)


@jax.jit
def _geometry(scene, settings, proj, frags):
    samples, reader = shading_samples(scene, proj, frags, settings.shading, host=False)
    return {"samples": samples, "reader": reader, "valid": frags.valid[..., 0],
            "view_dirs": view_dirs(scene, samples.points)}


def view_geometry(scene, settings) -> dict:
    """Rasterize and project once (fixed_fragments): the mode's shading samples
    (diffshade.samples) with their view directions, how the pixels read them, and which
    pixels are covered ('valid', [H, W]). Lights and material play no part, so views of
    one camera size share the compilations (geometry_scene)."""
    proj, frags = fixed_fragments(scene, settings)
    return _geometry(scene, settings, proj, frags)


def kept_pixels(valid, mask, edge_margin):
    """Flat indices [N] of the covered pixels (valid: [H, W] bool) inside `mask` ([H, W]
    bool or None) and at least `edge_margin` pixels inside the silhouette."""
    keep = erode(np.asarray(valid), edge_margin)
    if mask is not None:
        keep = keep & mask
    return np.flatnonzero(keep).astype(np.int32)


def _kept_samples(geo, pixels):
    """(points, normals, view_dirs) [S, 3] of the samples the kept pixels read (and their
    object ids [S, 1] with several objects), and the Reader of the pixels into them (only
    the samples read are kept)."""
    samples = geo["samples"]
    arrays = [np.asarray(a) for a in (samples.points, samples.normals, geo["view_dirs"])]
    if samples.objects is not None:
        arrays.append(np.asarray(samples.objects)[..., None])
    reader = geo["reader"]
    ids = np.arange(len(pixels), dtype=np.int32).reshape(-1, 1, 1)
    if reader.table is None:
        return [a.reshape(-1, a.shape[-1])[pixels] for a in arrays], Reader(ids)
    rows = np.asarray(reader.ids).reshape(-1)[pixels]
    used = np.asarray(reader.table)[rows]
    unique, inverse = np.unique(used, return_inverse=True)
    weights = None
    if reader.weights is not None:
        weights = np.asarray(reader.weights).reshape(-1, used.shape[1])[pixels]
        weights = jnp.asarray(weights.reshape(-1, 1, 1, used.shape[1]), float_dtype())
    return ([a[unique] for a in arrays],
            Reader(ids, weights, jnp.asarray(inverse.reshape(used.shape), jnp.int32)))


def view_samples(dataset: Dataset, index: int, edge_margin=1) -> ViewSamples:
    """Rasterize view `index` once and return its ViewSamples."""
    geo = view_geometry(geometry_scene(dataset, index), dataset.settings)
    view = dataset.views[index]
    pixels = kept_pixels(geo["valid"], view.mask, edge_margin)
    (points, normals, view_dirs, *objects), reader = _kept_samples(geo, pixels)
    floats = partial(jnp.asarray, dtype=float_dtype())
    objects = jnp.asarray(objects[0][:, 0], jnp.int32) if objects else None
    return ViewSamples(floats(points), floats(normals), floats(view_dirs),
                       floats(view.target.reshape(-1, 3)[pixels]), jnp.asarray(pixels), reader,
                       objects)


def build_cache(dataset: Dataset, material: Material, *, edge_margin: int = 1) -> FitData:
    """FitData for `dataset`, with `material` as the base (held-fixed) material.

    edge_margin: pixels dropped inside the silhouette (0 keeps every covered pixel).
    Raises ValueError when the settings rasterize softly (only hard coverage is cached) or
    when no pixel is kept."""
    if dataset.settings.raster != "hard":
        raise ValueError(f"settings.raster: got {dataset.settings.raster!r}; the cache "
                         "needs 'hard' (fit soft-rasterized data with the full-render loss)")
    if isinstance(edge_margin, bool) or not isinstance(edge_margin, int) or edge_margin < 0:
        raise ValueError(f"edge_margin: got {edge_margin!r}; expected an integer >= 0")
    views = tuple(view_samples(dataset, i, edge_margin)
                  for i in range(len(dataset.views)))
    if sum(v.pixels.shape[0] for v in views) == 0:
        raise ValueError("dataset: no covered pixel is left in any view (check the cameras, "
                         f"the masks and edge_margin={edge_margin})")
    scene = view_scene(dataset, 0, material)
    return FitData(views, tuple(v.lights for v in dataset.views), material,
                   scene.global_ambient, dataset.settings)


def _to_pixels(values, samples: ViewSamples):
    """Sample values [S, C] -> kept-pixel values [N, C], as render combines them (in XLA:
    the arrays are small, and a gather beats a host callback per view and step)."""
    return read(values, samples.reader, host=False).reshape(
        samples.pixels.shape + values.shape[-1:])


def _shade_samples(material, lights: LightGroups, global_ambient, samples, settings):
    if samples.objects is not None:
        material = take_material(material, samples.objects)
    return shade(material, lights, global_ambient, samples.points, samples.normals,
                 samples.view_dirs, settings)


def pixel_parts(material, lights, global_ambient, samples: ViewSamples,
                settings) -> ShadingParts:
    """Unclamped ambient, diffuse, specular and emission at the kept pixels: [N, 3] each
    (the parts are interpolated like colours, without clamping)."""
    parts = _shade_samples(material, lights, global_ambient, samples, settings)
    return parts.map(lambda a: _to_pixels(a, samples))


def predict(material, lights, global_ambient, samples: ViewSamples, settings):
    """Rendered colours at the kept pixels: [N, 3], clamped as the renderer clamps."""
    total = _shade_samples(material, lights, global_ambient, samples, settings).total
    return _to_pixels(clamp01(total) if settings.clamp else total, samples)

"""The fast path: rasterize each view once, then shade only the covered pixels per step.

With geometry and cameras fixed, everything the lighting core needs except the material
and the lights is fixed too. `build_cache` rasterizes every view once
(`diffshade.rasterize_scene`), keeps the pixels that are covered, inside the view's mask
and (by default) not on the silhouette, and stores per *shading sample* the world point,
the normal and the direction to the viewer, as flat arrays:

- 'phong': one sample per kept pixel (normals interpolated and renormalized);
- 'gouraud': one per mesh vertex that a kept pixel reads, combined with the pixel's fixed
  barycentric weights after per-vertex clamping, as OpenGL does;
- 'flat': one per covered face (centroid, face normal); 'flat_last': one per face's last
  vertex. Two-sided lighting is folded into the normals (flipped on back faces), since the
  back material is the front one during a fit; so no front flags are stored.

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

from diffshade.interpolate import interpolate
from diffshade.lights import LightGroups
from diffshade.material import Material
from diffshade.material import material as make_material
from diffshade.numerics import clamp01, float_dtype, safe_normalize
from diffshade.project import project
from diffshade.render import flat_samples, rasterize_scene, view_dirs
from diffshade.shading import ShadingParts, shade
from fitting.data import Dataset, view_scene

# Geometry does not depend on the material; one fixed material keeps one compilation.
_GEOMETRY_MATERIAL = make_material()


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ViewSamples:
    """One view's shading samples and the kept pixels that read them.

    points, normals, view_dirs: [S, 3] world space (unit normals and view_dirs);
    target: [N, 3] target colours of the kept pixels; pixels: [N] int32 flat index
    (row * width + column) of each kept pixel; gather: [N, G] int32 sample index per pixel
    and weights: [N, G] its weights (G = 3 for Gouraud, 1 for flat), or both None when
    sample i is pixel i (Phong)."""

    points: jax.Array
    normals: jax.Array
    view_dirs: jax.Array
    target: jax.Array
    pixels: jax.Array
    gather: jax.Array | None = None
    weights: jax.Array | None = None


@partial(jax.tree_util.register_dataclass,
         data_fields=["views", "lights", "material", "global_ambient"],
         meta_fields=["settings"])
@dataclasses.dataclass(frozen=True)
class FitData:
    """Everything a cached fit step reads: views: tuple of ViewSamples; lights: tuple of
    LightGroups (one per view); material: the base Material (held-fixed quantities);
    global_ambient: [3]; settings: RenderSettings (static)."""

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


def _candidates(scene, proj, frags, shading):
    """Every potential shading sample of the mode: per pixel [H, W, 3] (Phong), per face
    [F, 3] (flat, with the face's side) or per vertex [V, 3] (Gouraud, flat_last)."""
    faces = scene.mesh.faces
    if shading == "phong":
        points = interpolate(proj.world, faces, frags)[..., 0, :]
        normals = safe_normalize(interpolate(proj.normals, faces, frags))[..., 0, :]
        return {"points": points, "normals": normals}
    if shading == "flat":
        points, normals, front = flat_samples(scene, proj)
        return {"points": points, "normals": normals, "front_faces": front}
    return {"points": proj.world, "normals": proj.normals}


@partial(jax.jit, static_argnames="settings")
def view_geometry(scene, settings) -> dict:
    """Rasterize and project once: the nearest face per pixel ('face_ids', 'bary',
    'front', 'valid', [H, W, ...]) and the candidate samples with their view directions.
    Lights and material play no part, so views of one camera size share the compilation."""
    frags = rasterize_scene(scene, settings)
    out = _candidates(scene, project(scene), frags, settings.shading)
    out["view_dirs"] = view_dirs(scene, out["points"])
    return out | {"face_ids": frags.face_ids[..., 0], "bary": frags.bary[..., 0, :],
                  "front": frags.front[..., 0], "valid": frags.valid[..., 0]}


def kept_pixels(valid, mask, edge_margin):
    """Flat indices [N] of the covered pixels (valid: [H, W] bool) inside `mask` ([H, W]
    bool or None) and at least `edge_margin` pixels inside the silhouette."""
    keep = erode(np.asarray(valid), edge_margin)
    if mask is not None:
        keep = keep & mask
    return np.flatnonzero(keep).astype(np.int32)


def _flip(normals, front, two_sided):
    """OpenGL two-sided lighting: back faces are lit with the reversed normal."""
    return np.where(front[:, None], normals, -normals) if two_sided else normals


def _per_pixel(geo, name, pixels):
    value = np.asarray(geo[name])
    return value.reshape(-1, *value.shape[2:])[pixels]


def _phong_samples(geo, pixels, two_sided):
    front = _per_pixel(geo, "front", pixels)
    normals = _flip(_per_pixel(geo, "normals", pixels), front, two_sided)
    return (_per_pixel(geo, "points", pixels), normals, _per_pixel(geo, "view_dirs", pixels),
            None, None)


def _compact(geo, ids, side_front, two_sided):
    """Samples at the unique `ids` [N, G] (vertex or face ids) — twice, front and back
    side, under two-sided lighting (side_front: [N] bool) — and gather [N, G] into them."""
    unique, inverse = np.unique(ids, return_inverse=True)
    gather = inverse.reshape(ids.shape)
    points, normals, view_dirs = (np.asarray(geo[k])[unique]
                                  for k in ("points", "normals", "view_dirs"))
    if not two_sided:
        return points, normals, view_dirs, gather
    gather = gather + np.where(side_front[:, None], 0, len(unique))
    return (np.concatenate([points, points]), np.concatenate([normals, -normals]),
            np.concatenate([view_dirs, view_dirs]), gather)


def _vertex_samples(geo, faces, pixels, two_sided, last_only):
    """Gouraud (3 corners, barycentric weights) or flat_last (the last corner, weight 1)."""
    corners = np.asarray(faces)[_per_pixel(geo, "face_ids", pixels)]
    weights = _per_pixel(geo, "bary", pixels)
    if last_only:
        corners, weights = corners[:, 2:], np.ones_like(weights[:, :1])
    front = _per_pixel(geo, "front", pixels)
    return (*_compact(geo, corners, front, two_sided), weights)


def _flat_samples(geo, pixels, two_sided):
    face_ids = _per_pixel(geo, "face_ids", pixels)[:, None]
    unique, inverse = np.unique(face_ids, return_inverse=True)
    normals = _flip(np.asarray(geo["normals"])[unique],
                    np.asarray(geo["front_faces"])[unique], two_sided)
    points, view_dirs = (np.asarray(geo[k])[unique] for k in ("points", "view_dirs"))
    return points, normals, view_dirs, inverse.reshape(-1, 1), np.ones((len(pixels), 1))


def _samples(geo, shading, faces, pixels, two_sided):
    if shading == "phong":
        return _phong_samples(geo, pixels, two_sided)
    if shading == "flat":
        return _flat_samples(geo, pixels, two_sided)
    return _vertex_samples(geo, faces, pixels, two_sided, shading == "flat_last")


def view_samples(dataset: Dataset, index: int, edge_margin=1) -> ViewSamples:
    """Rasterize view `index` once and return its ViewSamples."""
    scene = view_scene(dataset, index, _GEOMETRY_MATERIAL, LightGroups())
    geo = view_geometry(scene, dataset.settings)
    view = dataset.views[index]
    pixels = kept_pixels(geo["valid"], view.mask, edge_margin)
    points, normals, view_dirs, gather, weights = _samples(
        geo, dataset.settings.shading, scene.mesh.faces, pixels, scene.two_sided)
    floats = partial(jnp.asarray, dtype=float_dtype())
    return ViewSamples(floats(points), floats(normals), floats(view_dirs),
                       floats(view.target.reshape(-1, 3)[pixels]), jnp.asarray(pixels),
                       None if gather is None else jnp.asarray(gather, jnp.int32),
                       None if weights is None else floats(weights))


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
    """Sample values [S, C] -> kept-pixel values [N, C] through the fixed weights."""
    if samples.gather is None:
        return values
    weights, gather = samples.weights, samples.gather
    return sum(weights[:, g, None] * values[gather[:, g]] for g in range(gather.shape[1]))


def _shade_samples(material, lights: LightGroups, global_ambient, samples, settings):
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

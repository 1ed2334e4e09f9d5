"""Re-shading fixed geometry: everything of a render that material and lights leave alone.

When geometry and camera are fixed (fitting material or light parameters), a render's
fragments, blend weights and coverage are the same on every step; only the colours
change. `cache_shading(scene, frags, settings)` computes, once, the fragments whose blend
weight is not 0 (the *active* ones: in soft mode with a small gamma, about a third of the
H x W x K slots; in hard mode the nearest fragment of each covered pixel), their
shading samples (diffshade.shading.samples: the interpolated points and normals for Phong, the
vertices or faces the other modes light), their weights, the background's weight and the
alpha channel. `render_cached(scene, cache, settings)` then lights the samples, reads the
active fragments' colours and sums them into the pixels: the image of `render_fragments`
(to rounding), with gradients with respect to everything but geometry and camera.

The number of active fragments is data, so `cache_shading` runs eagerly (not under
`jit`; it jits its parts); `render_cached` compiles once per cache size.

`slot_samples` is the step both caches of fixed geometry share, this one and a fit's
(fitting.model.cache, which keeps the fragment layers of the pixels it fits): from the
shading samples of every fragment and their Reader, keep the samples that the chosen
fragments read, and no others, and a Reader of those fragments into them.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.composite.blend import soft_alpha
from diffshade.composite.transparency import is_transparent
from diffshade.numerics import clamp01
from diffshade.pipeline.rendering import blend_weights, check_arguments, shade_samples
from diffshade.raster.fragments import Fragments
from diffshade.raster.projection import project
from diffshade.shading.samples import Reader, Samples, read, shading_samples
from diffshade.shading.shadows import shadow_maps


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class ShadingCache:
    """samples: the Samples the active fragments read (only those); reader: how they read
    them (diffshade.shading.samples.Reader, ids [C, 1, 1]: one per active fragment); pixels: [C]
    int32 flat pixel index (row * width + column) of each active fragment, ascending;
    weights: [C] its blend weight; background: [H, W] the background's weight; alpha:
    [H, W] coverage."""

    samples: Samples
    reader: Reader
    pixels: jax.Array
    weights: jax.Array
    background: jax.Array
    alpha: jax.Array


@jax.jit
def _fixed_parts(scene, frags, settings):
    """Per slot: blend weight [H, W, K]; per pixel: background weight and alpha [H, W];
    and the mode's shading samples and reader for the slots (Phong: active slots only)."""
    if settings.raster == "hard":
        alpha = frags.valid[..., 0].astype(frags.bary.dtype)
        slot = jnp.zeros(frags.face_ids.shape, alpha.dtype).at[..., 0].set(alpha)
        background = 1.0 - alpha
    else:
        slot, background = blend_weights(scene, frags, settings)
        alpha = soft_alpha(frags, settings.sigma)
    active = slot > 0.0
    if settings.shading == "phong":
        frags = dataclasses.replace(frags, face_ids=jnp.where(active, frags.face_ids, -1))
    samples, reader = shading_samples(scene, project(scene), frags, settings.shading,
                                      settings.use_host_kernels())
    return slot, background, alpha, active, samples, reader


def slot_samples(arrays, reader: Reader, slots, shape):
    """The samples some fragments read, and how they read them (eager, in NumPy).

    arrays: per-sample values, NumPy arrays [S, ...] (per fragment, [H, W, K, ...], when
    reader has no table: Phong); reader: the Reader of every fragment (ids [H, W, K]);
    slots: [M] int flat indices of the fragments kept (row * width * K + column * K + k);
    shape: the shape, of M elements, of the kept fragments' ids.
    Returns (the arrays at the samples those fragments read, [S', ...] each: only those;
    a Reader of the kept fragments into them, NumPy arrays: ids `shape` (0..M-1), weights
    `shape` + [G] or None, table [M, G] int32 or None)."""
    ids = np.arange(len(slots), dtype=np.int32).reshape(shape)
    if reader.table is None:
        per_fragment = np.ndim(reader.ids)
        return [a.reshape((-1,) + a.shape[per_fragment:])[slots] for a in arrays], Reader(ids)
    rows = np.asarray(reader.ids).reshape(-1)[slots]
    # an empty slot (-1) reads the table's last row: a caller gives it no weight
    used = np.asarray(reader.table)[rows]
    unique, inverse = np.unique(used, return_inverse=True)
    weights = None
    if reader.weights is not None:
        weights = np.asarray(reader.weights).reshape(-1, used.shape[1])[slots]
        weights = weights.reshape(ids.shape + used.shape[1:])
    table = inverse.reshape(used.shape).astype(np.int32)
    return [a[unique] for a in arrays], Reader(ids, weights, table)


def cache_shading(scene, frags: Fragments, settings) -> ShadingCache:
    """The fixed part of rendering `frags` (rasterize_scene(scene, settings)) of `scene`
    (module docstring). Raises ValueError for a scene with a transparent material (its
    layers are composited, not blended)."""
    check_arguments(scene, settings)
    if not isinstance(frags, Fragments):
        raise TypeError(f"frags: got {type(frags).__name__}; expected Fragments "
                        "(diffshade.rasterize_scene)")
    if is_transparent(scene):
        raise ValueError("scene: has a transparent material (kt); cache_shading blends "
                         "opaque fragments only (use render_fragments)")
    slot, background, alpha, active, samples, reader = _fixed_parts(scene, frags, settings)
    k = slot.shape[-1]
    index = np.flatnonzero(np.asarray(active)).astype(np.int32)
    kept, reader = slot_samples([np.asarray(a) for a in samples.leaves()], reader, index,
                                (index.size, 1, 1))
    return ShadingCache(samples.with_leaves(list(map(jnp.asarray, kept))),
                        jax.tree.map(jnp.asarray, reader),
                        jnp.asarray(index // k), jnp.take(slot.reshape(-1), index),
                        background, alpha)


@jax.jit
def _render_cached(scene, cache: ShadingCache, settings):
    lit = shade_samples(scene, cache.samples, settings, shadow_maps(scene, settings))
    _, colour = read(lit, cache.reader, host=False)
    colour = colour.reshape(-1, 3)
    if settings.clamp:
        colour = clamp01(colour)
    height, width = cache.alpha.shape
    rgb = jax.ops.segment_sum(cache.weights[:, None] * colour, cache.pixels,
                              num_segments=height * width, indices_are_sorted=True)
    rgb = rgb.reshape(height, width, 3) + cache.background[..., None] * scene.background
    if settings.clamp:
        rgb = clamp01(rgb)
    return jnp.concatenate([rgb, cache.alpha[..., None]], -1)


def render_cached(scene, cache: ShadingCache, settings):
    """[H, W, 4] RGBA of `scene` (its material and lights) on the fixed geometry of
    `cache` (cache_shading of the same scene's geometry and settings)."""
    check_arguments(scene, settings)
    if not isinstance(cache, ShadingCache):
        raise TypeError(f"cache: got {type(cache).__name__}; expected ShadingCache "
                        "(diffshade.cache_shading)")
    return _render_cached(scene, cache, settings)

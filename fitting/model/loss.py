"""Image losses of a fit, on the cached pixels or on fully rendered images.

Per residual r = rendered - target (each pixel and channel), the loss is the mean of
rho(r) over the kept pixels and channels of all views:
- 'mse': r^2 (the default; Gaussian noise);
- 'l1': |r|;
- 'charbonnier': sqrt(r^2 + eps^2) - eps with eps = 1e-3 (smooth L1, robust to outliers);
- 'huber': r^2 / 2 within |r| <= 0.01, linear beyond.
Rendering clamps exactly as the targets were rendered (dataset settings).

`make_loss(spec, kind)` gives `loss_fn(params, data: FitData)` on the cached pixels;
`make_render_loss(spec, kind)` gives the same loss computed by calling `diffshade.render`
on every view (`RenderData`), for the benchmark and for checking the cache.
"""

import dataclasses
from functools import lru_cache, partial

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.pipeline import render
from diffshade.scene import replace
from fitting.data.views import view_scene
from fitting.model.batch import unpadded, view_map
from fitting.model.cache import FitData, predict
from fitting.spec.gains import scaled_material, view_gains
from fitting.spec.params import FitSpec, to_values, values_to_lights, values_to_material

LOSSES = ("mse", "l1", "charbonnier", "huber")
CHARBONNIER_EPS = 1e-3
HUBER_DELTA = 1e-2


def check_kind(kind):
    if kind not in LOSSES:
        raise ValueError(f"loss: got {kind!r}; expected one of {LOSSES}")


def rho(kind, r):
    """Per-residual loss: r [...] -> [...]."""
    if kind == "mse":
        return r * r
    if kind == "l1":
        return jnp.abs(r)
    if kind == "charbonnier":
        return jnp.sqrt(r * r + CHARBONNIER_EPS**2) - CHARBONNIER_EPS
    abs_r = jnp.abs(r)
    return jnp.where(abs_r <= HUBER_DELTA, 0.5 * r * r, HUBER_DELTA * (abs_r - 0.5 * HUBER_DELTA))


def irls_weight(kind, r):
    """rho'(r) / (2 r): the weight that turns rho into a weighted least-squares problem
    (iteratively reweighted least squares); 1 for 'mse'."""
    abs_r = jnp.abs(r)
    if kind == "mse":
        return jnp.ones_like(r)
    if kind == "l1":
        return 0.5 / jnp.maximum(abs_r, CHARBONNIER_EPS)
    if kind == "charbonnier":
        return 0.5 / jnp.sqrt(r * r + CHARBONNIER_EPS**2)
    return 0.5 * jnp.where(abs_r <= HUBER_DELTA, 1.0, HUBER_DELTA / jnp.maximum(abs_r, 1e-30))


def stacked_residuals(values, spec: FitSpec, data: FitData):
    """Physical values -> (residuals [V, N, 3]: rendered - target, 0 in the padding;
    weight [V, N]: 1 at the kept pixels), every view shaded by one vmapped program
    (fitting.model.batch; `data` as built or batched). Each view is rendered with its own gain
    (fitting.spec.gains) when the spec fits gains."""
    material = values_to_material(values, spec, data.material)
    lights = values_to_lights(values, spec, data.lights) if "lights" in values else None

    def one(samples, light, gain):
        m = material if gain is None else scaled_material(material, gain)
        return predict(m, light, data.global_ambient, samples, data.settings) - samples.target

    return view_map(one, data, lights, view_gains(values, len(data.views)))


def values_residuals(values, spec: FitSpec, data: FitData):
    """Physical values -> residuals (rendered - target) per view: tuple of [N_v, 3]."""
    return unpadded(stacked_residuals(values, spec, data)[0], data.views)


def residuals(params, spec: FitSpec, data: FitData):
    """Unconstrained params -> residuals per view: tuple of [N_v, 3]."""
    return values_residuals(to_values(params, spec), spec, data)


def mean_rho(kind, residual_list, weight_list=None):
    """Mean of rho over all residuals (optionally weighted: weights [N_v] per pixel)."""
    if weight_list is None:
        weight_list = [jnp.ones(r.shape[:-1], r.dtype) for r in residual_list]
    total = sum(jnp.sum(w[..., None] * rho(kind, r)) for r, w in zip(residual_list, weight_list,
                                                                       strict=True))
    count = sum(jnp.sum(w) * r.shape[-1] for r, w in zip(residual_list, weight_list, strict=True))
    return total / jnp.maximum(count, 1.0)


@lru_cache(maxsize=64)
def make_loss(spec: FitSpec, kind: str = "mse"):
    """loss_fn(params, data: FitData) -> scalar, on the cached pixels. Memoized, so that
    fits with the same spec and loss share one compiled step."""
    check_kind(kind)

    def loss_fn(params, data):
        r, weight = stacked_residuals(to_values(params, spec), spec, data)
        return mean_rho(kind, [r], [weight])
    return loss_fn


@partial(jax.tree_util.register_dataclass,
         data_fields=["scenes", "targets", "weights", "settings"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class RenderData:
    """The full-image path: scenes: tuple of Scene (one per view, base material);
    targets: tuple of [H, W, 3]; weights: tuple of [H, W] (1 at the kept pixels, else 0);
    settings: RenderSettings (a pytree: its structure is static)."""

    scenes: tuple
    targets: tuple
    weights: tuple
    settings: object


def render_data(dataset, data: FitData) -> RenderData:
    """RenderData over the same kept pixels as the cached `data`."""
    dtype = data.views[0].target.dtype
    scenes, weights = [], []
    for i, (view, samples) in enumerate(zip(dataset.views, data.views, strict=True)):
        scenes.append(view_scene(dataset, i, data.material))
        flat = np.zeros(view.target.shape[0] * view.target.shape[1], np.float32)
        flat[np.asarray(samples.pixels)] = 1.0
        weights.append(jnp.asarray(flat.reshape(view.target.shape[:2]), dtype))
    targets = tuple(jnp.asarray(v.target, dtype) for v in dataset.views)
    return RenderData(tuple(scenes), targets, tuple(weights), dataset.settings)


@lru_cache(maxsize=64)
def make_render_loss(spec: FitSpec, kind: str = "mse"):
    """loss_fn(params, data: RenderData) -> scalar: renders every view in full with
    `diffshade.render` each call, and compares at the kept pixels."""
    check_kind(kind)

    def loss_fn(params, data):
        values = to_values(params, spec)
        lights = values_to_lights(values, spec, [s.lights for s in data.scenes])
        gains = view_gains(values, len(data.scenes))
        scenes = []
        for v, (scene, light) in enumerate(zip(data.scenes, lights, strict=True)):
            material = values_to_material(values, spec, scene.material)
            if gains is not None:
                material = scaled_material(material, gains[v])
            scenes.append(replace(scene, material=material, lights=light))
        res = [img[..., :3] - t for img, t in zip(render_all(scenes, data.settings),
                                                   data.targets, strict=True)]
        return mean_rho(kind, res, list(data.weights))
    return loss_fn


def render_all(scenes, settings):
    """The images [H, W, 4] of a list of scenes: one batched render (jax.vmap) when they
    share one structure (image size, lights, mesh size), else one render each."""
    if len({jax.tree.structure(s) for s in scenes}) > 1 or len({
            tuple(np.shape(x) for x in jax.tree.leaves(s)) for s in scenes}) > 1:
        return [render(s, settings) for s in scenes]
    stacked = jax.tree.map(lambda *leaves: jnp.stack(leaves), *scenes)
    return list(jax.vmap(lambda s: render(s, settings))(stacked))

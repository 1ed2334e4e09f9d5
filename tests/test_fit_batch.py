"""The fit's views as one batch (fitting.model.batch): every program shades one view per light
layout under jax.vmap over the views padded and stacked, and gives what shading the
views one by one gives.

References, float64, 3 views x 2 lights of a 16 px icosphere (the views lit by a
directional or a point light: two light layouts, two vmapped groups), one view masked
out entirely (0 kept pixels: padded from another view): the
residuals of `fitting.model.cache.predict` called view by view in a Python loop, their
Jacobian by jax.jacfwd of that loop, the linear solve's normal equations summed from
`pixel_parts` view by view; and a whole 'linear' fit with stacking switched off (every
program then shades the views one by one), whose fitted values the batched fit
equals to float64 rounding.
"""

import dataclasses
from functools import lru_cache

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree

import diffshade as ds
import fitting.model.batch as batch
from data_synth import make_dataset
from fitting import DEFAULT_INIT, FitSpec, fit
from fitting.model import build_cache, make_loss
from fitting.model.batch import batched, light_layout, view_map
from fitting.model.cache import pixel_parts, predict
from fitting.model.loss import values_residuals
from fitting.solve.gauss_newton import _linearize
from fitting.solve.linear import normal_equations
from fitting.spec import to_unconstrained
from fitting.spec.params import to_values, values_to_material

TRUTH = dict(ka=0.15, kd=(0.55, 0.35, 0.25), ks=0.35, shininess=25.0)
GUESS = ds.material(ka=0.3, kd=0.4, ks=0.2, shininess=10.0)


@lru_cache(maxsize=1)
def dataset64():
    """3 cameras x 2 lights, 16 px, float64; view 4 masked out."""
    with jax.enable_x64(True):
        dataset = make_dataset(ds.icosphere(1), ds.material(**TRUTH), n_views=3, n_lights=2,
                               size=16, settings=ds.RenderSettings(kernels="host"))
    views = list(dataset.views)
    views[4] = dataclasses.replace(views[4], mask=np.zeros(views[4].target.shape[:2], bool))
    return dataclasses.replace(dataset, views=views)


@lru_cache(maxsize=1)
def cache64():
    with jax.enable_x64(True):
        return build_cache(dataset64(), DEFAULT_INIT)


def _loop_residuals(values, spec, data):
    """The reference: predict view by view, concatenated: [M]."""
    material = values_to_material(values, spec, data.material)
    return jnp.concatenate([
        (predict(material, lights, data.global_ambient, view, data.settings)
         - view.target).reshape(-1) for view, lights in zip(data.views, data.lights, strict=True)])


def test_the_scene_needs_padding():
    """The references below exercise what batching groups and pads: two light layouts,
    views of different pixel counts, a view without pixels."""
    data = cache64()
    assert len({light_layout(g) for g in data.lights}) == 2
    counts = [v.pixels.shape[0] for v in data.views]
    assert counts[4] == 0 and len(set(counts)) > 2


def test_residuals_loss_and_jacobian_equal_the_view_by_view_loop():
    data = cache64()
    spec = FitSpec()
    with jax.enable_x64(True):
        params = to_unconstrained(GUESS, spec)
        values = to_values(params, spec)
        want = np.asarray(_loop_residuals(values, spec, data))
        for form in (data, batched(data)):  # stacked inside the trace, or once on the host
            got = np.concatenate([np.ravel(r) for r in values_residuals(values, spec, form)])
            np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
        loss = float(jax.jit(make_loss(spec))(params, data))
        np.testing.assert_allclose(loss, np.mean(want**2), rtol=1e-12)
        got_loss, hess, grad = (np.asarray(a) for a in _linearize(params, data, spec))
        start, unravel = ravel_pytree(params)
        full = np.asarray(jax.jacfwd(lambda x: _loop_residuals(to_values(unravel(x), spec),
                                                               spec, data))(start))
    np.testing.assert_allclose(got_loss, np.mean(want**2), rtol=1e-12)
    np.testing.assert_allclose(hess, full.T @ full, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(grad, full.T @ want, rtol=1e-10, atol=1e-14)


def test_normal_equations_equal_the_view_by_view_sums():
    data = cache64()
    spec = FitSpec(ks=None, shininess=False)  # ka, kd in RGB: the Gram of ambient, diffuse
    with jax.enable_x64(True):
        unit = dataclasses.replace(data.material, ka=jnp.ones(3), kd=jnp.ones(3), ks=jnp.ones(3))
        gram = np.zeros((6, 6))
        rhs = np.zeros(6)
        for view, lights in zip(data.views, data.lights, strict=True):
            parts = pixel_parts(unit, lights, data.global_ambient, view, data.settings)
            fixed = np.asarray(parts.specular * data.material.ks + parts.emission)
            y = np.asarray(view.target) - fixed
            t = np.asarray(view.target)
            usable = (t > 1e-6) & (t < 1 - 1e-6)
            for c in range(3):
                x = np.stack([np.asarray(parts.ambient)[:, c], np.asarray(parts.diffuse)[:, c]],
                             1)[usable[:, c]]
                rows = [c, 3 + c]
                gram[np.ix_(rows, rows)] += x.T @ x
                rhs[rows] += x.T @ y[usable[:, c], c]
        got_gram, got_rhs, _, _ = normal_equations(np.log(25.0), data, spec)
    np.testing.assert_allclose(got_gram, gram, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(got_rhs, rhs, rtol=1e-12, atol=1e-14)


def test_view_map_falls_back_to_one_call_per_view(monkeypatch):
    """Views that do not stack are shaded one by one, padded alike."""
    data = cache64()
    with jax.enable_x64(True):
        def one(samples, lights, _):
            return predict(data.material, lights, data.global_ambient, samples, data.settings)
        stacked, weight = view_map(one, data)
        monkeypatch.setattr(batch, "stack_views", lambda views, lights: None)
        looped, weight_looped = view_map(one, data)
    np.testing.assert_array_equal(np.asarray(weight), np.asarray(weight_looped))
    kept = np.asarray(weight) > 0
    np.testing.assert_allclose(np.asarray(stacked)[kept], np.asarray(looped)[kept],
                               rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("method", ["linear"])
def test_a_fit_equals_the_unbatched_fit(monkeypatch, method):
    """The README's method on the float64 scene: the batched fit's values equal those of
    the same fit with stacking off (every program shading the views one by one)."""
    with jax.enable_x64(True):
        batched_fit = fit(dataset64(), FitSpec(), GUESS, method=method, steps=5)
        monkeypatch.setattr(batch, "stack_views", lambda views, lights: None)
        looped_fit = fit(dataset64(), FitSpec(), GUESS, method=method, steps=5)
    assert batched_fit.n_steps == looped_fit.n_steps
    for name, value in looped_fit.values.items():
        np.testing.assert_allclose(batched_fit.values[name], value, rtol=1e-9, err_msg=name)
    np.testing.assert_allclose(batched_fit.uncertainty.std_errors,
                               looped_fit.uncertainty.std_errors, rtol=1e-6)

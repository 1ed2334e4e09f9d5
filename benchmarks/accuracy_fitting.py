"""The fitting half of the accuracy-versus-time study (benchmarks/accuracy_vs_time.py).

Parameter error against the known truth, as a function of what it costs: optimizer steps
(Adam) and wall time, the linear-coefficient solver, image resolution, number of views,
and the per-step time with and without the fragment cache. The error of a fit is the
largest relative error over every fitted coefficient channel and shininess.
"""

import time

import jax
import numpy as np
from fit_step import time_step

from data_synth import make_dataset
from fitting import (
    DEFAULT_INIT,
    FitSpec,
    build_cache,
    fit,
    make_loss,
    make_optimizer,
    make_render_loss,
    make_step,
    render_data,
    to_unconstrained,
)

SEED = 3


def material_error(material, truth):
    """Largest relative error over ka, kd, ks (per channel) and shininess."""
    worst = 0.0
    for name in ("ka", "kd", "ks", "shininess"):
        fitted = np.asarray(getattr(material, name), np.float64)
        true = np.asarray(getattr(truth, name), np.float64)
        worst = max(worst, float(np.max(np.abs(fitted - true) / np.abs(true))))
    return worst


def timed_fit(dataset, **kwargs):
    """(result, compile_s): an untimed warm-up fit first compiles everything, so the
    result's wall_time is the steady-state time of a fit (cache building included)."""
    start = time.perf_counter()
    fit(dataset, with_uncertainty=False, **{**kwargs, "steps": 2})
    compile_s = time.perf_counter() - start
    return fit(dataset, with_uncertainty=False, **kwargs), compile_s


def steps_rows(dataset, checkpoints):
    """Adam: parameter error and wall time after each checkpoint step count."""
    fit(dataset, method="adam", steps=2, with_uncertainty=False)
    rows, start = [], time.perf_counter()

    def record(step, loss, material):
        if step + 1 in checkpoints:
            rows.append({"study": "steps", "method": "adam", "steps": step + 1,
                         "wall_s": time.perf_counter() - start,
                         "max_rel_error": material_error(material, dataset.truth)})
        return False
    fit(dataset, method="adam", steps=max(checkpoints), tol=0.0, atol=0.0,
        with_uncertainty=False, callback=record)
    return rows


def method_rows(dataset, adam_steps):
    """Adam (to convergence or adam_steps) versus the linear-coefficient solver."""
    rows = []
    for method, steps in (("adam", adam_steps), ("linear", None)):
        result, compile_s = timed_fit(dataset, method=method, steps=steps)
        rows.append({"study": "method", "method": method, "steps": result.n_steps,
                     "wall_s": result.wall_time, "compile_s": compile_s,
                     "max_rel_error": material_error(result.material, dataset.truth)})
    return rows


def scaling_rows(sizes, views, quantize):
    """The linear solver's error and wall time against resolution and number of views."""
    rows = []
    for size in sizes:
        for n_views in views:
            dataset = make_dataset(n_views=n_views, size=size, seed=SEED,
                                   quantize_8bit=quantize)
            result, compile_s = timed_fit(dataset, method="linear")
            rows.append({"study": "scaling", "method": "linear", "size": size,
                         "views": n_views, "quantized": quantize, "wall_s": result.wall_time,
                         "compile_s": compile_s,
                         "max_rel_error": material_error(result.material, dataset.truth)})
    return rows


def cache_rows(dataset, runs):
    """Median per-step time of the same Adam step with and without the fragment cache."""
    spec, optimizer = FitSpec(), make_optimizer()
    params = to_unconstrained(DEFAULT_INIT, spec)
    state = optimizer.init(params)
    cached = build_cache(dataset, DEFAULT_INIT)
    rows = []
    for name, loss, data in (("cached", make_loss(spec), cached),
                             ("full_render", make_render_loss(spec),
                              render_data(dataset, cached))):
        first, times = time_step(make_step(loss, optimizer), params, state, data, runs, 3)
        rows.append({"study": "cache", "path": name, "compile_s": first,
                     "step_ms": float(np.median(times) * 1e3)})
    return rows


def fitting_study(quick=False):
    """All fitting rows (quick: a seconds-long subset)."""
    size = 48 if quick else 128
    dataset = make_dataset(size=size, seed=SEED)
    checkpoints = (10, 50) if quick else (10, 30, 100, 300, 1000, 3000)
    rows = steps_rows(dataset, set(checkpoints))
    rows += method_rows(dataset, max(checkpoints))
    sizes, views = ((32,), (1, 3)) if quick else ((32, 64, 128, 256), (1, 2, 3, 5))
    rows += scaling_rows(sizes, views, quantize=False)
    if not quick:
        rows += scaling_rows((64, 128), (3,), quantize=True)
    rows += cache_rows(dataset, 5 if quick else 50)
    jax.clear_caches()
    return rows

"""The fitting half of the accuracy-versus-time study (benchmarks/accuracy_vs_time.py).

Parameter error against the known truth, as a function of what it costs: optimizer steps
(Adam) and wall time, the linear-coefficient solver, image resolution, number of views,
noisy and 8-bit targets, targets rendered by a finer mesh or another shading than the
fit's, the per-step time with and without the fragment cache, and the compile time of a
fresh process. The error of a fit is the largest relative error over every fitted
coefficient channel and shininess ('worst' names that parameter).

Every error is deterministic: datasets come from fixed seeds (SEED, NOISE_SEEDS), fits
start from fitting.DEFAULT_INIT and run a fixed number of steps or to their stopping
rule, in a fixed order. The columns ending in _s or _ms are timings and vary from run to
run (and with the machine's load).
"""

import dataclasses
import functools
import json
import os
import subprocess
import sys
import time

import jax
import numpy as np
from common import time_settings, timing_columns

import diffshade as ds
from data_synth import make_dataset
from fitting import DEFAULT_INIT, FitSpec, fit
from fitting.model import build_cache, make_loss, make_render_loss, render_data
from fitting.solve import make_optimizer, make_step
from fitting.spec import to_unconstrained

SEED = 3
NOISE_SEEDS = (3, 4, 5, 6, 7)
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def material_errors(material, truth):
    """{parameter: largest relative error over its channels} for ka, kd, ks, shininess."""
    return {name: float(np.max(np.abs(np.asarray(getattr(material, name), np.float64)
                                      - np.asarray(getattr(truth, name), np.float64))
                               / np.abs(np.asarray(getattr(truth, name), np.float64))))
            for name in ("ka", "kd", "ks", "shininess")}


def material_error(material, truth):
    """Largest relative error over ka, kd, ks (per channel) and shininess."""
    return max(material_errors(material, truth).values())


def error_columns(material, truth):
    """max_rel_error and the parameter it comes from ('worst')."""
    errors = material_errors(material, truth)
    worst = max(errors, key=errors.get)
    return {"max_rel_error": errors[worst], "worst": worst}


def steps_rows(dataset, checkpoints):
    """Adam with a fixed step budget (no stopping rule): at each checkpoint the error of
    the current iterate and of the lowest-loss parameters seen so far (what `fit`
    returns when its budget ends there), the loss of the current iterate, and wall time."""
    fit(dataset, method="adam", steps=2, with_uncertainty=False)
    rows, start = [], time.perf_counter()
    seen = {"previous": DEFAULT_INIT, "best": None, "best_loss": np.inf}

    def record(step, loss, material):
        # loss is the loss of the parameters before this step (the previous iterate)
        if loss < seen["best_loss"]:
            seen["best"], seen["best_loss"] = seen["previous"], float(loss)
        seen["previous"] = material
        if step + 1 in checkpoints:
            rows.append({"study": "steps", "method": "adam", "steps": step + 1,
                         "wall_s": time.perf_counter() - start, "loss": float(loss),
                         "max_rel_error": material_error(material, dataset.truth),
                         "best_rel_error": material_error(seen["best"], dataset.truth)})
        return False
    fit(dataset, method="adam", steps=max(checkpoints), tol=0.0, atol=0.0,
        with_uncertainty=False, callback=record)
    return rows


def timed_fit(dataset, **kwargs):
    """A fit's result after an untimed warm-up fit of 2 steps (which compiles it), so that
    result.wall_time is the steady-state time of a fit (cache building included)."""
    fit(dataset, with_uncertainty=False, **{**kwargs, "steps": 2})
    return fit(dataset, with_uncertainty=False, **kwargs)


def method_rows(dataset):
    """Adam to its stopping rule versus the linear-coefficient solver."""
    rows = []
    for method in ("adam", "linear"):
        result = timed_fit(dataset, method=method)
        rows.append({"study": "method", "method": method, "steps": result.n_steps,
                     "wall_s": result.wall_time, **error_columns(result.material,
                                                                 dataset.truth)})
    return rows


def scaling_rows(sizes, views):
    """The linear solver's error and wall time against resolution and number of views."""
    rows = []
    for size in sizes:
        for n_views in views:
            dataset = make_dataset(n_views=n_views, size=size, seed=SEED)
            result = timed_fit(dataset, method="linear")
            rows.append({"study": "scaling", "method": "linear", "size": size,
                         "views": n_views, "wall_s": result.wall_time,
                         **error_columns(result.material, dataset.truth)})
    return rows


def noise_rows(size, views, conditions, seeds=NOISE_SEEDS):
    """The linear solver on degraded targets against the number of views: per condition
    (noise_std, 8-bit) and view count, the median and the largest error over `seeds`
    (each seed draws its own material and noise)."""
    rows = []
    for noise_std, quantize in conditions:
        for n_views in views:
            errors, walls = [], []
            for seed in seeds:
                dataset = make_dataset(n_views=n_views, size=size, seed=seed,
                                       noise_std=noise_std, quantize_8bit=quantize)
                result = fit(dataset, method="linear", with_uncertainty=False)
                errors.append(material_error(result.material, dataset.truth))
                walls.append(result.wall_time)
            rows.append({"study": "noise", "method": "linear", "size": size,
                         "views": n_views, "noise_std": noise_std, "quantized": quantize,
                         "seeds": len(seeds), "median_rel_error": float(np.median(errors)),
                         "max_rel_error": float(np.max(errors)),
                         "wall_s": float(np.median(walls))})
    return rows


def mismatch_rows(size, target_level, fitted):
    """Targets rendered from an icosphere of subdivision `target_level` with Phong
    shading, fitted (linear solver) with the coarser meshes and shadings of `fitted`
    ((subdivisions, shading) pairs): the model error a fit meets on real data."""
    target = make_dataset(shape=ds.icosphere(target_level), size=size, seed=SEED,
                          shading="phong")
    rows = []
    for level, shading in fitted:
        dataset = dataclasses.replace(target, mesh=ds.icosphere(level),
                                      settings=ds.RenderSettings(shading=shading))
        result = timed_fit(dataset, method="linear")
        rows.append({"study": "mismatch", "method": "linear", "size": size,
                     "target": f"subdiv {target_level} phong", "subdivisions": level,
                     "shading": shading, "wall_s": result.wall_time,
                     **error_columns(result.material, dataset.truth)})
    return rows


def cache_rows(dataset, timing):
    """Per-step time of the same Adam step with and without the fragment cache, the two
    timed against each other (common.time_settings)."""
    spec, optimizer = FitSpec(), make_optimizer()
    params = to_unconstrained(DEFAULT_INIT, spec)
    state = optimizer.init(params)
    cached = build_cache(dataset, DEFAULT_INIT)
    calls = {}
    for name, loss, data in (("cached", make_loss(spec), cached),
                             ("full_render", make_render_loss(spec),
                              render_data(dataset, cached))):
        step = make_step(loss, optimizer)
        # the same step from the same state each call: the time of one step
        calls[name] = functools.partial(step, params, state, data)
    stats = time_settings(calls, **timing)
    return [{"study": "cache", "path": name,
             **timing_columns(stats[name], "step", "first_call_s")} for name in calls]


# One fit from a fresh interpreter: argv = method size; prints one JSON line.
_FRESH = """
import json, sys, time
start = time.perf_counter()
from data_synth import make_dataset
from fitting import fit
imported = time.perf_counter()
dataset = make_dataset(size=int(sys.argv[2]), seed=int(sys.argv[3]))
made = time.perf_counter()
times = []
for _ in range(2):
    t = time.perf_counter()
    fit(dataset, method=sys.argv[1], with_uncertainty=False)
    times.append(time.perf_counter() - t)
print(json.dumps({"import_s": imported - start, "dataset_s": made - imported,
                  "first_fit_s": times[0], "second_fit_s": times[1]}))
"""


def fresh_rows(size, methods):
    """Compile time of a fit in a fresh process with the persistent compilation cache off
    (DIFFSHADE_COMPILE_CACHE=0; numba's kernel cache stays as installed): the first fit
    (compile + run) less the second (run) of the same dataset, with import and dataset
    times (the targets' render compiles there) beside it."""
    env = {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}
    env.update(DIFFSHADE_COMPILE_CACHE="0",
               PYTHONPATH=os.pathsep.join(p for p in (ROOT, env.get("PYTHONPATH")) if p))
    rows = []
    for method in methods:
        out = subprocess.run([sys.executable, "-c", _FRESH, method, str(size), str(SEED)],
                             env=env, cwd=ROOT, capture_output=True, text=True, check=True)
        times = json.loads(out.stdout.strip().splitlines()[-1])
        rows.append({"study": "fresh", "method": method, "size": size, **times,
                     "compile_s": times["first_fit_s"] - times["second_fit_s"]})
    return rows


def fitting_study(quick=False):
    """All fitting rows (quick: a subset whose error rows are also full-study rows)."""
    if quick:
        rows = scaling_rows((32,), (1,))
        rows += noise_rows(32, (1,), ((0.0, True),), seeds=NOISE_SEEDS[:1])
        jax.clear_caches()
        return rows
    dataset = make_dataset(size=128, seed=SEED)
    rows = steps_rows(dataset, {10, 30, 100, 300, 1000, 3000})
    rows += method_rows(dataset)
    rows += cache_rows(dataset, {"rounds": 25})
    rows += scaling_rows((32, 64, 128, 256), (1, 2, 4, 8))
    rows += noise_rows(128, (1, 2, 4, 8), ((0.0, True), (0.01, False), (0.03, False)))
    rows += noise_rows(32, (1,), ((0.0, True),), seeds=NOISE_SEEDS[:1])  # the quick row
    rows += mismatch_rows(128, 6, [(level, shading) for shading in ("gouraud", "phong")
                                   for level in (2, 3, 4, 5)])
    rows += fresh_rows(128, ("linear", "adam"))
    jax.clear_caches()
    return rows

"""What accuracy costs in time: rendering and fitting settings against ground truth.

    python benchmarks/accuracy_vs_time.py                 # the full study (its JSON's "run"
                                                          # record gives its run time)
    python benchmarks/accuracy_vs_time.py --quick         # ~1.5 CPU-minutes; CI runs it
    python benchmarks/accuracy_vs_time.py --plots docs/img  # also draw the PNG plots
    python benchmarks/accuracy_vs_time.py --sections fitting --merge  # rerun one section,
                                                          # keep the others in --out

Rendering error is measured against an analytic sphere (diffshade.analytic: the exact
ray-sphere intersection, shaded with the exact normal by the same lighting core),
supersampled 8x8 per pixel, so tessellation, interpolation, resolution and rasterization
errors are all visible. Errors are in 1/255 units: RMSE over the image, the maximum
absolute error, and the RMSE inside the highlights (pixels where the reference's specular
part exceeds 0.05). Times follow common.time_settings: the settings of one table (all
configurations at one image size for the mesh section) are timed against each other in
one interleaved run, each warmed up until its time settles; the median and quartiles of
the rounds are kept, the first call (trace, compile, run) apart as compile_s. 'fwd+bwd'
is the gradient of an MSE loss with respect to the material.

Every error column is deterministic (no random input; fixed seeds in the fitting study)
and reproduces to the printed digit on the same machine; the columns ending in _s or _ms
are timings, which vary from run to run and with the machine's load.
"""

import argparse
import functools
import json
import os
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import (  # noqa: E402
    finish_record,
    print_table,
    run_record,
    time_settings,
    timing_columns,
    with_spreads,
    write_results,
)

import diffshade as ds  # noqa: E402
from diffshade.analytic import render_analytic_sphere  # noqa: E402
from diffshade.pipeline.rendering import render_supersampled  # noqa: E402

NAME = "vs_time"
OUT = "benchmarks/results/accuracy_vs_time.json"
REFERENCE_SUPERSAMPLE = 8
HIGHLIGHT_THRESHOLD = 0.05


def sphere_scene(subdivisions, size):
    """The study's scene: a unit icosphere, a directional and a point light, a glossy red."""
    return ds.make_scene(
        ds.icosphere(subdivisions),
        ds.look_at((0.4, 0.3, 3.2), (0.0, 0.0, 0.0), width=size, height=size, fov_y=40.0),
        [ds.directional_light((-1.0, -1.0, -1.0), 0.8),
         ds.point_light((2.0, 2.5, 2.0), 0.6, attenuation=(1.0, 0.05, 0.01))],
        ds.material(ka=0.2, kd=(0.7, 0.3, 0.2), ks=0.5, shininess=60.0))


def reference(size):
    """(analytic RGBA [H, W, 4], highlight mask [H, W]) for the study's scene, computed once
    per size and float precision."""
    return _reference(size, bool(jax.config.jax_enable_x64))


@functools.cache
def _reference(size, x64):
    scene = sphere_scene(1, size)
    settings = ds.RenderSettings()
    ref = np.asarray(render_analytic_sphere(scene, settings, supersample=REFERENCE_SUPERSAMPLE))
    glossy = ds.replace(scene, material=ds.material(ka=0.0, kd=0.0, ks=0.5, shininess=60.0),
                        global_ambient=jnp.zeros(3))
    spec = np.asarray(render_analytic_sphere(glossy, settings, supersample=REFERENCE_SUPERSAMPLE))
    return ref, spec[..., :3].max(-1) > HIGHLIGHT_THRESHOLD


def errors(image, ref, highlight):
    """RMSE, max abs and highlight RMSE of the RGB channels, in 1/255 units."""
    diff = np.asarray(image, np.float64)[..., :3] - ref[..., :3]
    return {"rmse_255": 255 * float(np.sqrt(np.mean(diff ** 2))),
            "max_255": 255 * float(np.abs(diff).max()),
            "highlight_rmse_255": 255 * float(np.sqrt(np.mean(diff[highlight] ** 2)))}


def timed_calls(render_fn, scene, target):
    """Zero-argument calls of the forward render ("fwd") and of the gradient of an MSE
    loss with respect to the material ("fwd_bwd"), for common.time_settings."""
    fwd = jax.jit(render_fn)

    def loss(material):
        image = render_fn(ds.replace(scene, material=material))
        return jnp.mean((image[..., :3] - target) ** 2)
    grad = jax.jit(jax.grad(loss))
    return {"fwd": lambda: fwd(scene), "fwd_bwd": lambda: grad(scene.material)}


def time_rows(rows, calls, timing):
    """Add the time columns to `rows`, timing every row's calls (one timed_calls dict per
    row) against each other in one interleaved run."""
    flat = {(i, kind): fn for i, row_calls in enumerate(calls) for kind, fn in row_calls.items()}
    stats = time_settings(flat, **timing)
    for i, row in enumerate(rows):
        row.update(timing_columns(stats[i, "fwd"], "fwd", "compile_s"))
        row.update(timing_columns(stats[i, "fwd_bwd"], "fwd_bwd"))
    return rows


def mesh_config(level, mode, size):
    """(scene, settings, calls) of one mesh row: a hard render of subdivision `level`."""
    ref, _ = reference(size)
    scene = sphere_scene(level, size)
    settings = ds.RenderSettings(shading=mode)
    calls = timed_calls(lambda s: ds.render(s, settings), scene,
                        jnp.asarray(ref[..., :3], jnp.float32))
    return scene, settings, calls


def mesh_rows(levels, modes, sizes, timing):
    """Subdivision x shading x size; the configurations of one size are timed together."""
    rows = []
    for size in sizes:
        ref, highlight = reference(size)
        size_rows, calls = [], []
        for level in levels:
            for mode in modes:
                scene, settings, row_calls = mesh_config(level, mode, size)
                row = {"study": "mesh", "subdivisions": level, "shading": mode, "size": size}
                row.update(errors(ds.render(scene, settings), ref, highlight))
                size_rows.append(row)
                calls.append(row_calls)
        rows += time_rows(size_rows, calls, timing)
    return rows


def supersample_config(level, size, factor):
    """(scene, settings, calls) of one supersampling row."""
    ref, _ = reference(size)
    scene = sphere_scene(level, size)
    settings = ds.RenderSettings(shading="phong")
    calls = timed_calls(lambda s: render_supersampled(s, settings, factor), scene,
                        jnp.asarray(ref[..., :3], jnp.float32))
    return scene, settings, calls


def supersample_rows(level, sizes, factors, timing):
    rows, calls = [], []
    for size in sizes:
        ref, highlight = reference(size)
        edge = _silhouette(ref)
        for factor in factors:
            scene, settings, row_calls = supersample_config(level, size, factor)
            calls.append(row_calls)
            image = np.asarray(render_supersampled(scene, settings, factor))
            row = {"study": "supersample", "subdivisions": level, "shading": "phong",
                   "size": size, "factor": factor,
                   "silhouette_rmse_255": 255 * float(np.sqrt(np.mean(
                       (image[..., :3] - ref[..., :3])[edge] ** 2)))}
            row.update(errors(image, ref, highlight))
            rows.append(row)
    return time_rows(rows, calls, timing)


def _silhouette(ref):
    """Pixels partly covered by the exact sphere: [H, W] bool."""
    return (ref[..., 3] > 0.0) & (ref[..., 3] < 1.0)


def soft_config(level, size, sigma, gamma, k):
    """(scene, settings, calls) of one soft-rasterization row."""
    ref, _ = reference(size)
    scene = sphere_scene(level, size)
    settings = ds.RenderSettings(shading="phong", raster="soft", sigma=sigma, gamma=gamma,
                                 faces_per_pixel=k)
    calls = timed_calls(lambda s: ds.render(s, settings), scene,
                        jnp.asarray(ref[..., :3], jnp.float32))
    return scene, settings, calls


def soft_rows(level, size, sigmas, gammas, ks, timing):
    ref, highlight = reference(size)
    hard = np.asarray(ds.render(sphere_scene(level, size), ds.RenderSettings(shading="phong")))
    rows, calls = [], []
    for sigma in sigmas:
        for gamma in gammas:
            for k in ks:
                scene, settings, row_calls = soft_config(level, size, sigma, gamma, k)
                calls.append(row_calls)
                image = np.asarray(ds.render(scene, settings))
                row = {"study": "soft", "subdivisions": level, "size": size, "sigma": sigma,
                       "gamma": gamma, "K": k,
                       "vs_hard_rmse_255": 255 * float(np.sqrt(np.mean(
                           (image[..., :3] - hard[..., :3]) ** 2)))}
                row.update(errors(image, ref, highlight))
                rows.append(row)
    return time_rows(rows, calls, timing)


def _under_x64(fn, x64):
    """fn called with float64 switched on or off, so that float32 and float64 settings can
    be timed interleaved (each call runs the program compiled under its own flag)."""
    def call():
        with jax.enable_x64(x64):
            return fn()
    return call


def precision_config(level, size, x64):
    """(scene, settings, calls) of one precision row; build it under jax.enable_x64(x64)."""
    ref, _ = reference(size)
    scene = sphere_scene(level, size)
    settings = ds.RenderSettings(shading="phong")
    calls = timed_calls(lambda s: ds.render(s, settings), scene, jnp.asarray(ref[..., :3]))
    return scene, settings, {kind: _under_x64(fn, x64) for kind, fn in calls.items()}


def precision_rows(level, sizes, timing):
    rows, calls = [], []
    for x64 in (False, True):
        with jax.enable_x64(x64):
            for size in sizes:
                ref, highlight = reference(size)
                scene, settings, row_calls = precision_config(level, size, x64)
                calls.append(row_calls)
                row = {"study": "precision", "subdivisions": level, "size": size,
                       "dtype": "float64" if x64 else "float32"}
                row.update(errors(ds.render(scene, settings), ref, highlight))
                rows.append(row)
    return time_rows(rows, calls, timing)


def pareto(rows, error_key="rmse_255", time_key="fwd_ms"):
    """Mark rows on the Pareto front of (time, error): no other row is both faster and
    more accurate."""
    for row in rows:
        row["pareto"] = not any(o[time_key] <= row[time_key] and o[error_key] <= row[error_key]
                                and (o[time_key], o[error_key]) != (row[time_key],
                                                                    row[error_key])
                                for o in rows)
    return rows


def cheapest_within(rows, bound_255, error_key="rmse_255", time_key="fwd_ms"):
    """The fastest row whose error is within `bound_255`, or None."""
    ok = [r for r in rows if r[error_key] <= bound_255]
    return min(ok, key=lambda r: r[time_key]) if ok else None


MESH_COLUMNS = [("subdivisions", "subdiv", "{}"), ("shading", "shading", "{}"),
                ("size", "size", "{}"), ("rmse_255", "rmse/255", "{:.2f}"),
                ("max_255", "max/255", "{:.1f}"), ("highlight_rmse_255", "hilite/255", "{:.2f}"),
                ("fwd_ms", "fwd ms", "{:.1f}"), ("fwd_bwd_ms", "fwd+bwd ms", "{:.1f}"),
                ("compile_s", "compile s", "{:.1f}")]


def configs(quick):
    if quick:
        # the mesh rows are rows of the full study too (tests/test_accuracy_quick.py
        # compares them with the published ones)
        return {"levels": (1, 3, 5), "modes": ("phong",), "sizes": (64,), "ss_sizes": (48,),
                "factors": (1, 2), "sigmas": (0.5,), "gammas": (1e-4,), "ks": (4,),
                "precision_sizes": (48,), "timing": {"rounds": 3, "max_warmup": 6}}
    return {"levels": (1, 2, 3, 4, 5, 6), "modes": ("flat", "gouraud", "phong"),
            "sizes": (64, 128, 256, 512), "ss_sizes": (128, 256), "factors": (1, 2, 4),
            "sigmas": (0.1, 0.5, 2.0), "gammas": (1e-4, 1e-2), "ks": (4, 8, 16),
            "precision_sizes": (128, 256), "timing": {"rounds": 7}}


SECTIONS = ("mesh", "supersample", "soft", "precision", "fitting")


def run(quick=False, sections=SECTIONS):
    """The studies named in `sections`: a dict of row lists, and under "measured" the run
    record (commit, start, minutes, load before and after) of each section."""
    c = configs(quick)
    timing = c["timing"]
    studies = {
        "mesh": lambda: pareto(mesh_rows(c["levels"], c["modes"], c["sizes"], timing)),
        "supersample": lambda: supersample_rows(5, c["ss_sizes"], c["factors"], timing),
        "soft": lambda: soft_rows(4, c["ss_sizes"][0], c["sigmas"], c["gammas"], c["ks"],
                                  timing),
        "precision": lambda: precision_rows(5, c["precision_sizes"], timing),
        "fitting": lambda: _fitting_study(quick),
    }
    results, measured = {}, {}
    for name in sections:
        record = run_record()
        results[name] = studies[name]()
        measured[name] = finish_record(record)
    results["measured"] = measured
    results["reference_supersample"] = REFERENCE_SUPERSAMPLE
    return results


def _fitting_study(quick):
    from accuracy_fitting import fitting_study
    return fitting_study(quick)


def tables(results):
    """The markdown of the doc block (benchmarks/accuracy_tables.py)."""
    from accuracy_tables import vs_time_tables
    return vs_time_tables(results)


def plots(results, folder):
    from accuracy_plots import draw_all, draw_precision
    return draw_all(results, folder) + draw_precision(results, folder)


def report(results):
    if "mesh" in results:
        print("\n== mesh: subdivision x shading x resolution vs the analytic sphere")
        print_table(results["mesh"], MESH_COLUMNS + [("pareto", "pareto", "{}")])
    if "supersample" in results:
        print("\n== supersampling (anti-aliased silhouettes)")
        print_table(results["supersample"], [("size", "size", "{}"),
                                             ("factor", "factor", "{}"),
                                             ("silhouette_rmse_255", "silhouette/255",
                                              "{:.2f}")] + MESH_COLUMNS[3:])
    if "soft" in results:
        print("\n== soft rasterization (Phong): against the hard image and the analytic "
              "sphere")
        print_table(results["soft"], [("sigma", "sigma px2", "{}"), ("gamma", "gamma", "{}"),
                                      ("K", "K", "{}"), ("vs_hard_rmse_255", "vs hard/255",
                                                         "{:.2f}")] + MESH_COLUMNS[3:])
    if "precision" in results:
        print("\n== float32 vs float64")
        print_table(results["precision"], [("dtype", "dtype", "{}")] + MESH_COLUMNS[2:])
    if "fitting" in results:
        report_fitting(results["fitting"])
    if "mesh" not in results or "supersample" not in results:
        return
    for bound in (1.0, 2.0):
        best = cheapest_within(results["mesh"] + results["supersample"], bound)
        text = ("none" if best is None else
                f"{best['study']} subdiv {best['subdivisions']} {best['shading']} "
                f"{best['size']}px x{best.get('factor', 1)} ({best['fwd_ms']:.1f} ms)")
        print(f"cheapest setting within {bound}/255 RMSE of the analytic sphere: {text}")


def report_fitting(rows):
    print("\n== fitting: parameter error (max relative, all coefficients and shininess)")
    for title, columns in FITTING_TABLES:
        chosen = [r for r in rows if r["study"] == title]
        if chosen:
            print_table(with_spreads(chosen), columns)


FITTING_TABLES = [
    ("steps", [("steps", "steps", "{}"), ("wall_s", "wall s", "{:.2f}"),
               ("loss", "loss", "{:.1e}"), ("max_rel_error", "iterate err", "{:.1e}"),
               ("best_rel_error", "best-loss err", "{:.1e}")]),
    ("method", [("method", "method", "{}"), ("steps", "steps", "{}"),
                ("wall_s", "wall s", "{:.2f}"), ("max_rel_error", "max rel err", "{:.1e}"),
                ("worst", "worst", "{}")]),
    ("scaling", [("size", "px", "{}"), ("views", "views", "{}"),
                 ("wall_s", "wall s", "{:.2f}"), ("max_rel_error", "max rel err", "{:.1e}"),
                 ("worst", "worst", "{}")]),
    ("noise", [("size", "px", "{}"), ("noise_std", "noise std", "{}"),
               ("quantized", "8-bit", "{}"), ("views", "views", "{}"), ("seeds", "seeds", "{}"),
               ("median_rel_error", "median rel err", "{:.1e}"),
               ("max_rel_error", "max rel err", "{:.1e}"), ("wall_s", "wall s", "{:.2f}")]),
    ("mismatch", [("target", "targets", "{}"), ("subdivisions", "fit subdiv", "{}"),
                  ("shading", "fit shading", "{}"), ("wall_s", "wall s", "{:.2f}"),
                  ("max_rel_error", "max rel err", "{:.1e}"), ("worst", "worst", "{}")]),
    ("cache", [("path", "loss path", "{}"), ("step_ms", "step ms", "{:.1f}"),
               ("step_spread", "step spread ms", "{}"),
               ("first_call_s", "first call s", "{:.1f}")]),
    ("fresh", [("method", "method", "{}"), ("size", "px", "{}"),
               ("import_s", "import s", "{:.1f}"), ("dataset_s", "dataset s", "{:.1f}"),
               ("first_fit_s", "first fit s", "{:.1f}"),
               ("second_fit_s", "second fit s", "{:.1f}"), ("compile_s", "compile s", "{:.1f}")]),
]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a seconds-long subset (CI)")
    parser.add_argument("--out", default=OUT)
    parser.add_argument("--plots", default=None, help="folder for the PNG plots")
    parser.add_argument("--no-fitting", action="store_true", help="skip the fitting study")
    parser.add_argument("--sections", default=",".join(SECTIONS),
                        help=f"comma-separated sections to run (default: all of {SECTIONS})")
    parser.add_argument("--merge", action="store_true",
                        help="keep the other sections of the existing --out file")
    args = parser.parse_args(argv)
    sections = [s for s in args.sections.split(",") if s and not (args.no_fitting
                                                                  and s == "fitting")]
    unknown = [s for s in sections if s not in SECTIONS]
    if unknown:
        parser.error(f"--sections: got {unknown}; expected names from {SECTIONS}")
    record = run_record()
    results = run(args.quick, sections)
    if args.merge and os.path.exists(args.out):
        with open(args.out, encoding="utf-8") as file:
            old = json.load(file)
        if old.get("quick") != args.quick:
            parser.error(f"--merge: {args.out} has quick={old.get('quick')}; this run has "
                         f"quick={args.quick}")
        results = {**{k: old[k] for k in SECTIONS if k in old and k not in results},
                   **results, "measured": {**old.get("measured", {}), **results["measured"]}}
    payload = {"benchmark": NAME, "quick": args.quick, **results,
               "run": finish_record(record)}
    write_results(args.out, payload)
    report(results)
    if args.plots:
        plots(results, args.plots)
    return payload


if __name__ == "__main__":
    main()

"""How the cost of a soft render grows with faces, pixels, K and views.

Soft Phong rendering (default sigma, gamma, threshold; float32) of the judged scene of
benchmarks/peers.py (an icosphere seen from 3 units, one directional light), swept one
variable at a time from a base point:
- faces: icosphere subdivisions 3..8 (1,280 ... 1,310,720 faces), 256^2, K = 8, 1 view;
- pixels: 128^2 ... 1024^2, 5,120 faces, K = 8, 1 view;
- K (faces_per_pixel): 1 ... 32, 5,120 faces, 256^2, 1 view;
- views: 1 ... 16 views in one `render_views` call (cameras on a circle around the
  sphere), 5,120 faces, 128^2, K = 8.
Timed: forward (render / render_views) and forward + backward (value_and_grad of the MSE
to a grey image with respect to vertices, kd and ks). Counted (by `rasterize_scene`, over
all views): the covered (pixel, face) pairs that the candidate search finds, i.e. the
fragments kept in the K slots plus those dropped beyond K (`Fragments.dropped`); and the
fragments kept. Times: the median wall clock, and the median CPU seconds of the process's
threads per call (on a machine loaded by others the steadier measure of the work; with
2 cores idle it is up to twice the wall time). Cost per pair = CPU time / pairs, and a
least-squares cost model (CPU time against pairs, kept fragments, pixels and faces) says
where the cost is not linear in pairs.

Each point runs in its own process, so that its peak resident memory (getrusage
ru_maxrss: imports, scene, compilation and runs) is its own: measured after forward (which
runs first) and after forward + backward, with the baseline after imports and scene.
XLA's compiled temp memory is reported too. A point gets --point-budget seconds in all
(timed calls stop after --call-budget seconds; a point whose compiled memory exceeds
--max-gib is not run, and says so). Results: JSON and a plot (--plot PNG).

    python benchmarks/scaling.py [--quick] [--sweeps faces,pixels,k,views]
        [--plot docs/img/scaling.png] [--from-json benchmarks/results/scaling.json]
"""

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BASE = {"subdivisions": 4, "size": 256, "k": 8, "views": 1}
SWEEPS = {"faces": ("subdivisions", (3, 4, 5, 6, 7, 8)),
          "pixels": ("size", (128, 256, 512, 1024)),
          "k": ("k", (1, 2, 4, 8, 16, 32)),
          "views": ("views", (1, 2, 4, 8, 16))}
QUICK = {"faces": (3, 4, 5, 6), "pixels": (128, 256, 512), "k": (1, 4, 16), "views": (1, 4)}
VIEWS_SIZE = 128
MODES = ("forward", "forward_backward")


def points(sweeps, quick):
    """The configurations to run: dicts of subdivisions, size, k, views and the sweep."""
    out = []
    for name in sweeps:
        field, values = SWEEPS[name]
        base = dict(BASE, size=VIEWS_SIZE) if name == "views" else BASE
        for value in (QUICK[name] if quick else values):
            out.append(dict(base, **{field: value}, sweep=name))
    return out


def cameras(n, size):
    """n cameras on a circle of radius 3 around the sphere, slightly above it."""
    import diffshade as ds

    eyes = [(3.0 * math.sin(a), 0.5, 3.0 * math.cos(a))
            for a in (2.0 * math.pi * i / n for i in range(n))]
    return [ds.look_at(e, (0.0, 0.0, 0.0), width=size, height=size, fov_y=45.0) for e in eyes]


def pair_counts(scene, cams, settings):
    """(covered pixel-face pairs, fragments kept in the K slots), summed over the views."""
    import diffshade as ds

    pairs = kept = 0
    for cam in cams:
        frags = ds.rasterize_scene(ds.replace(scene, camera=cam), settings)
        valid = int(frags.valid.sum())
        pairs, kept = pairs + valid + int(frags.dropped), kept + valid
    return pairs, kept


def peak_rss_bytes():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def run_point(config, args):
    """Measure one point, printing a JSON line after each phase (a point cut short by its
    budget keeps what it measured)."""
    import jax
    import jax.numpy as jnp
    from peers import judged_scene
    from raster import loss_fn, measure

    import diffshade as ds

    size, n = config["size"], config["views"]
    scene = judged_scene(size, config["subdivisions"])
    settings = ds.RenderSettings(raster="soft", faces_per_pixel=config["k"], shading="phong")
    cams = cameras(n, size) if n > 1 else [scene.camera]
    stacked = ds.stack_cameras(cams)
    render = ((lambda s, st: ds.render_views(s, stacked, st)) if n > 1 else ds.render)
    target = jnp.full(((n,) if n > 1 else ()) + (size, size, 4), 0.5, jnp.float32)
    out = {**config, "faces": int(scene.mesh.faces.shape[0]),
           "baseline_rss_bytes": peak_rss_bytes(), "loadavg_1min": os.getloadavg()[0]}
    emit = lambda: print(json.dumps(out), flush=True)
    out["pairs"], out["kept"] = pair_counts(scene, cams, settings)
    emit()
    fns = {"forward": (lambda s: render(s, settings), (scene,)),
           "forward_backward": (jax.value_and_grad(loss_fn(render, settings, scene, target)),
                                ((scene.mesh.vertices, scene.material.kd, scene.material.ks),))}
    for mode in MODES:
        result = measure(*fns[mode], args.repeats, budget_s=args.call_budget,
                         max_bytes=args.max_gib * 2**30)
        out[mode] = {k: v for k, v in result.items() if k != "times_s"}
        out[mode]["peak_rss_bytes"] = peak_rss_bytes()
        emit()


def last_json(text):
    """The last JSON line of a worker's output, or None."""
    if isinstance(text, bytes):
        text = text.decode(errors="replace")
    lines = [line for line in (text or "").splitlines() if line.startswith("{")]
    return json.loads(lines[-1]) if lines else None


def spawn(config, args):
    """Run one point in a subprocess within --point-budget seconds."""
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", json.dumps(config),
           "--repeats", str(args.repeats), "--call-budget", str(args.call_budget),
           "--max-gib", str(args.max_gib)]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [ROOT] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    start = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env=env,
                              timeout=args.point_budget)
        result, error = last_json(proc.stdout), proc.stderr if proc.returncode else None
    except subprocess.TimeoutExpired as err:
        result, error = last_json(err.stdout), f"over the {args.point_budget:g} s budget"
    result = result or dict(config)
    if error:
        result["error"] = error.strip().splitlines()[-1] if error.strip() else "failed"
    result["wall_s"] = time.perf_counter() - start
    return result


def cell(result, mode):
    """'wall ms / CPU ms (CPU ns per pair)' of one mode, or why it is missing."""
    r = result.get(mode)
    if r is None:
        return "—"
    if "skipped" in r:
        return "not run: " + r["skipped"]
    per_pair = r["cpu_median_s"] / result["pairs"] * 1e9 if result.get("pairs") else math.nan
    return f"{r['median_s'] * 1e3:.0f} / {r['cpu_median_s'] * 1e3:.0f} ms ({per_pair:.0f} ns)"


def rss(result, mode):
    r = result.get(mode)
    return "—" if r is None else f"{r['peak_rss_bytes'] / 2**30:.2f}"


def table(results):
    """Markdown table of all points."""
    lines = ["| sweep | faces | pixels | K | views | pairs | kept | forward: wall / CPU "
             "(CPU per pair) | f+b: wall / CPU (CPU per pair) | peak RSS GiB fwd / f+b | "
             "XLA temp f+b GiB |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        fb = r.get("forward_backward") or {}
        temp = f"{fb['temp_bytes'] / 2**30:.2f}" if "temp_bytes" in fb else "—"
        note = f" ({r['error']})" if "error" in r else ""
        lines.append(f"| {r['sweep']} | {r.get('faces', '?')} | {r['size']}² | {r['k']} | "
                     f"{r['views']} | {r.get('pairs', '—')} | {r.get('kept', '—')} | "
                     f"{cell(r, 'forward')} | {cell(r, 'forward_backward')}{note} | "
                     f"{rss(r, 'forward')} / {rss(r, 'forward_backward')} | {temp} |")
    return "\n".join(lines)


AXIS_LABELS = {"faces": "faces", "pixels": "pixels (image size)",
               "k": "K (fragment slots per pixel)", "views": "views (one render_views call)"}


def swept_value(r):
    return {"faces": r.get("faces"), "pixels": r["size"] ** 2, "k": r["k"],
            "views": r["views"]}[r["sweep"]]


def short(value, _=None):
    """1280 -> '1.3k', 327680 -> '328k', 1310720 -> '1.3M' (tick labels)."""
    for div, suffix in ((1e6, "M"), (1e3, "k")):
        if value >= div:
            digits = ".2g" if value < 100 * div else ".0f"
            return f"{value / div:{digits}}{suffix}"
    return f"{value:g}"


def side(value, _=None):
    """Pixels as the image side: 65536 -> '256²'."""
    return f"{math.isqrt(int(value))}²"


def cost_model(results, mode):
    """Least-squares fit (relative error, non-negative coefficients) of the CPU time to
    a * pairs + b * kept + c * pixels + d * faces (pixels and faces summed over views):
    ({term: seconds per unit}, [model / measured per point])."""
    import numpy as np
    from scipy.optimize import nnls

    done = [r for r in results if "median_s" in (r.get(mode) or {}) and r.get("pairs")]
    if len(done) < len(MODEL_TERMS):
        return None, []
    x = np.array([[term(r) for term in MODEL_TERMS.values()] for r in done], float)
    t = np.array([r[mode]["cpu_median_s"] for r in done])
    scale = x.max(0)
    coef, _ = nnls(x / scale / t[:, None], np.ones(len(t)))
    coef = coef / scale
    return dict(zip(MODEL_TERMS, coef, strict=True)), list(x @ coef / t)


MODEL_TERMS = {"pair": lambda r: r["pairs"], "kept fragment": lambda r: r["kept"],
               "pixel": lambda r: r["size"] ** 2 * r["views"],
               "face": lambda r: r["faces"] * r["views"]}


def print_model(results):
    """The cost model's coefficients and where it fits worst, per mode."""
    for mode in MODES:
        coef, ratios = cost_model(results, mode)
        if coef is None:
            continue
        terms = " + ".join(f"{coef[k] * 1e9:.1f} ns/{k}" for k in coef)
        done = [r for r in results if "median_s" in (r.get(mode) or {}) and r.get("pairs")]
        worst = sorted(zip(ratios, done, strict=True), key=lambda p: abs(math.log(p[0])))[-3:]
        where = "; ".join(f"{r['sweep']} {swept_value(r)}: {q:.2f}" for q, r in worst[::-1])
        print(f"{mode}: time ~ {terms}; model/measured worst at {where}")


def plot(results, path):
    """Per sweep (columns): median wall time, CPU time per covered pair and peak RSS
    (rows)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import ticker

    sweeps = [s for s in SWEEPS if any(r["sweep"] == s for r in results)]
    fig, axes = plt.subplots(3, len(sweeps), figsize=(3.6 * len(sweeps), 9), squeeze=False)
    for col, sweep in enumerate(sweeps):
        rows = [r for r in results if r["sweep"] == sweep and r.get("pairs")]
        for mode, style in zip(MODES, ("o-", "s--"), strict=True):
            done = [r for r in rows if "median_s" in (r.get(mode) or {})]
            x = [swept_value(r) for r in done]
            label = "forward" if mode == "forward" else "forward + backward"
            axes[0, col].loglog(x, [r[mode]["median_s"] * 1e3 for r in done], style, label=label)
            axes[1, col].semilogx(x, [r[mode]["cpu_median_s"] / r["pairs"] * 1e9
                                      for r in done], style, label=label)
            axes[2, col].semilogx(x, [r[mode]["peak_rss_bytes"] / 2**30 for r in done], style,
                                  label=label)
        for ax in axes[:, col]:
            ax.set_xticks(sorted({swept_value(r) for r in rows}))
            ax.xaxis.set_major_formatter(ticker.FuncFormatter(side if sweep == "pixels"
                                                               else short))
            ax.xaxis.set_minor_locator(ticker.NullLocator())
        axes[0, col].yaxis.set_major_locator(ticker.LogLocator(subs=(1.0, 2.0, 5.0)))
        axes[0, col].yaxis.set_major_formatter(ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        axes[0, col].yaxis.set_minor_formatter(ticker.NullFormatter())
        axes[1, col].set_ylim(bottom=0)
        axes[2, col].set_ylim(bottom=0)
        axes[0, col].set_title(f"{sweep} sweep")
        axes[2, col].set_xlabel(AXIS_LABELS[sweep])
    for row, label in enumerate(("median time, wall (ms)", "CPU time per covered pair (ns)",
                                 "peak RSS (GiB)")):
        axes[row, 0].set_ylabel(label)
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    print(f"wrote {path}")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"only {QUICK}")
    parser.add_argument("--sweeps", type=lambda t: t.split(","), default=list(SWEEPS))
    parser.add_argument("--repeats", type=int, default=10, help="timed calls at most")
    parser.add_argument("--call-budget", type=float, default=10.0,
                        help="seconds of timed calls per mode (at least one call)")
    parser.add_argument("--point-budget", type=float, default=400.0,
                        help="seconds per point in all, compilation included")
    parser.add_argument("--max-gib", type=float, default=4.0,
                        help="do not run a computation whose compiled memory exceeds this")
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks/results/scaling.json"))
    parser.add_argument("--plot", help="write the plot to this PNG")
    parser.add_argument("--from-json", help="plot and tabulate these results, measure nothing")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        run_point(json.loads(args.worker), args)
        return
    if args.from_json:
        with open(args.from_json) as f:
            results = json.load(f)["results"]
    else:
        unknown = sorted(set(args.sweeps) - set(SWEEPS))
        if unknown:
            parser.error(f"--sweeps: got {unknown}; expected names from {list(SWEEPS)}")
        results = measure_all(args)
    print(table(results))
    print_model(results)
    if args.plot:
        plot(results, args.plot)


def measure_all(args):
    results = []
    for config in points(args.sweeps, args.quick):
        results.append(spawn(config, args))
        r = results[-1]
        print(f"{r['sweep']:6s} {r.get('faces', '?'):>8} faces {r['size']:5d}^2 K={r['k']:2d} "
              f"views={r['views']:2d} pairs={r.get('pairs', '?')}: forward "
              f"{cell(r, 'forward')}, f+b {cell(r, 'forward_backward')}, wall "
              f"{r['wall_s']:.0f} s {r.get('error', '')}", flush=True)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    meta = {"command": " ".join([os.path.relpath(sys.argv[0], ROOT)] + sys.argv[1:]),
            "cpus": os.cpu_count(), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "loadavg_end": os.getloadavg()}
    with open(args.out, "w") as f:
        json.dump({"meta": meta, "results": results}, f, indent=1)
    print(f"wrote {args.out}")
    return results


if __name__ == "__main__":
    main()

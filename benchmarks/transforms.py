"""Benchmark of the kernel paths and of batched views (docs/transforms.md).

1. The judged scene: icosphere(4) (5,120 faces) at 256^2, soft Phong, K = 8, a point and a
   directional light, float32. Forward (render) and forward + backward (value_and_grad of
   the MSE to a grey image with respect to vertices, kd and ks), for every path:
   - `host`: the default on CPU (RenderSettings(kernels='host')): numba kernels behind
     JAX primitives that keep every transform;
   - `jax`: RenderSettings(kernels='jax'), the ops in jax.numpy (the accelerator path);
   - `baseline` (with --baseline REV): the same worker run on git revision REV's code
     (default 48d2648, before this change: custom_vjp ops, reverse mode only), so that
     today's and the earlier figures come from one run on one machine.
2. Batched views: 4 views of icosphere(4) at 128^2, soft Phong, K = 8: one
   `render_views` call against a Python loop of a jitted single-view `render` (what a
   user's loop does; gradients summed) and against the 4 renders inside one `jit`:
   forward, forward + backward with respect to vertices and kd, and with respect to the
   material only (kd, ks), each summed over the views. The three forms run in one
   process, in turns (one call of each per round), so that the load of a shared machine
   hits them alike; printed are the medians of the per-round ratios, of wall and of CPU
   time, per process (--processes, default 2). As many processes again run on one CPU
   with one numba thread: their least time is the work of the 4 views, and the fastest
   Python loop over half that work (on 2 CPUs) bounds what batching could gain.

Each path of 1. runs in its own process. Printed: compile seconds (lower + compile; for
the Python loop, its first call) and the median of --repeats calls after warm-up.

    .venv/bin/python benchmarks/transforms.py [--repeats 20] [--baseline 48d2648]
        [--only judged|views|search] [--processes 2]

`--only search` times the host face search of the 4 views alone (numba, no JAX): 4 calls
of find_candidates against one call of its batch form; run it with and without
OMP_WAIT_POLICY=passive in the environment to see the OpenMP threads' spinning.
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

from raster import measure  # benchmarks/raster.py, beside this script

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BASELINE = "48d2648"
#: set in a worker's environment: run it on one CPU (the work a batch has to do)
ONE_CPU = "DIFFSHADE_BENCH_ONE_CPU"


def sphere_scene(size, eye=(0.0, 0.0, 3.0)):
    import diffshade as ds

    cam = ds.look_at(eye, (0.0, 0.0, 0.0), width=size, height=size, fov_y=45.0)
    lights = [ds.point_light((2.0, 2.0, 3.0), 0.7), ds.directional_light((-0.3, -0.5, -1.0), 0.4)]
    mat = ds.material(ka=0.2, kd=(0.6, 0.5, 0.4), ks=0.4, shininess=20.0)
    return ds.make_scene(ds.icosphere(4), cam, lights, mat)


def settings_for(path):
    import diffshade as ds

    extra = {} if path == "baseline" else {"kernels": path}
    return ds.RenderSettings(raster="soft", faces_per_pixel=8, shading="phong", **extra)


def judged(path, repeats):
    """Forward and forward + backward on the judged scene, by one path."""
    import jax
    import jax.numpy as jnp

    import diffshade as ds

    settings, scene = settings_for(path), sphere_scene(256)
    target = jnp.full((256, 256, 4), 0.5, jnp.float32)

    def loss(params):
        vertices, kd, ks = params
        moved = ds.replace(scene, mesh=ds.replace(scene.mesh, vertices=vertices),
                           material=ds.replace(scene.material, kd=kd, ks=ks))
        return jnp.mean((ds.render(moved, settings) - target) ** 2)
    params = (scene.mesh.vertices, scene.material.kd, scene.material.ks)
    return {"forward": measure(lambda s: ds.render(s, settings), (scene,), repeats),
            "forward_backward": measure(jax.value_and_grad(loss), (params,), repeats)}


def interleaved(fns, args, repeats, jit=True):
    """Compile each fn (jit=True; a name starting with "python" is called as it is: its
    compile seconds are those of its first call), warm it up, then time them in turns (one
    call of each per round), so that a changing load on the machine hits all of them
    alike. Per fn: compile seconds, median wall and CPU seconds (process_time: all
    threads); and per round the wall and CPU times, from which main() takes the medians
    of the ratios."""
    import jax

    compiled, out = {}, {}
    for name, fn in fns.items():
        t0 = time.perf_counter()
        if jit and not name.startswith("python"):
            compiled[name] = jax.jit(fn).lower(*args).compile()
        else:
            compiled[name] = fn
            jax.block_until_ready(fn(*args))
        out[name] = {"compile_s": time.perf_counter() - t0, "times_s": [], "cpu_s": []}
        for _ in range(2):
            jax.block_until_ready(compiled[name](*args))
    for _ in range(repeats):
        for name in fns:
            t0, c0 = time.perf_counter(), time.process_time()
            jax.block_until_ready(compiled[name](*args))
            out[name]["times_s"].append(time.perf_counter() - t0)
            out[name]["cpu_s"].append(time.process_time() - c0)
    for r in out.values():
        r["median_s"] = statistics.median(r["times_s"])
        r["cpu_median_s"] = statistics.median(r["cpu_s"])
    return out


def views_setup():
    import diffshade as ds

    eyes = [(0.0, 0.0, 3.0), (2.0, 0.5, 2.2), (-2.0, 1.0, 2.0), (0.5, -2.5, 1.8)]
    scene = sphere_scene(128)
    cams = [ds.look_at(e, (0.0, 0.0, 0.0), width=128, height=128, fov_y=45.0) for e in eyes]
    return scene, cams


def search(repeats):
    """The host face search of the 4 views alone (numba, no JAX): 4 calls against one
    call of find_candidates' batch form, in turns."""
    import numpy as np

    import diffshade as ds
    from diffshade.host.candidates import find_candidates
    from diffshade.raster.search import soft_radius

    settings = settings_for("host")
    scene, cams = views_setup()
    clips = np.stack([np.asarray(ds.project(ds.replace(scene, camera=c)).clip) for c in cams])
    faces = np.asarray(scene.mesh.faces)
    kw = dict(width=128, height=128, k=settings.faces_per_pixel,
              radius_px=float(soft_radius(settings)), sigma=settings.sigma,
              gamma=settings.gamma)
    fns = {"loop": lambda: [find_candidates(c, faces, cams[0].near, cams[0].far, **kw)
                            for c in clips],
           "batched": lambda: find_candidates(clips, faces, cams[0].near, cams[0].far, **kw)}
    out = {"loop": {}, "batched": {}}
    for name, r in interleaved(fns, (), repeats, jit=False).items():
        out[name]["search"] = r
    return out


def views(repeats):
    """render_views against a loop of render, 4 views at 128^2, timed in turns: `loop`, the
    views' renders in one jit (independent, yet XLA runs them one after another);
    `python_loop`, a Python loop of one jitted single-view call per view (gradients
    summed: what a user's loop does); `batched`, one render_views call."""
    import jax
    import jax.numpy as jnp

    import diffshade as ds

    settings = settings_for("host")
    scene, cams = views_setup()
    stacked = ds.stack_cameras(cams)

    def loop(s):
        return jnp.stack([ds.render(ds.replace(s, camera=c), settings) for c in cams])

    def batched(s):
        return ds.render_views(s, stacked, settings)

    one = jax.jit(lambda s, c: ds.render(ds.replace(s, camera=c), settings))

    def python_loop(s):
        return [one(s, c) for c in cams]

    def moved(params):
        return ds.replace(scene, mesh=ds.replace(scene.mesh, **{
            n: v for n, v in params.items() if n == "vertices"}),
            material=ds.replace(scene.material, **{
                n: v for n, v in params.items() if n != "vertices"}))

    def loss_of(render_all):
        return jax.value_and_grad(lambda params: jnp.mean(render_all(moved(params)) ** 2))

    # the loss of one view: its share of the mean over all views
    one_loss = jax.jit(jax.value_and_grad(lambda params, c: jnp.mean(
        ds.render(ds.replace(moved(params), camera=c), settings) ** 2) / len(cams)))

    def python_loop_grad(params):
        parts = [one_loss(params, c) for c in cams]
        return (sum(v for v, _ in parts),
                jax.tree.map(lambda *g: sum(g[1:], g[0]), *[g for _, g in parts]))

    geometry = {"vertices": scene.mesh.vertices, "kd": scene.material.kd}
    material = {"kd": scene.material.kd, "ks": scene.material.ks}
    gradients = {"loop": loss_of(loop), "python_loop": python_loop_grad,
                 "batched": loss_of(batched)}
    parts = {"forward": ({"loop": loop, "python_loop": python_loop, "batched": batched},
                         (scene,)),
             "forward_backward": (gradients, (geometry,)),
             "material_forward_backward": (gradients, (material,))}
    out = {"loop": {}, "python_loop": {}, "batched": {}}
    for part, (fns, args) in parts.items():
        for name, r in interleaved(fns, args, repeats).items():
            out[name][part] = r
    return out


def spawn(task, args, pythonpath=None, extra_env=None):
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", task,
           "--repeats", str(args.repeats)]
    env = dict(os.environ, **(extra_env or {}))
    if pythonpath:
        env["PYTHONPATH"] = pythonpath
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=pythonpath or ROOT, env=env)
    if proc.returncode != 0:
        return {"error": proc.stderr[-3000:]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def baseline_tree(rev, where):
    """Check out revision `rev`'s code (git archive) into the folder `where`."""
    archive = subprocess.run(["git", "archive", rev], cwd=ROOT, capture_output=True,
                             check=True).stdout
    subprocess.run(["tar", "-x", "-C", where], input=archive, check=True)
    return where


def line(name, r):
    if "error" in r:
        return f"{name:10s} FAILED\n{r['error']}"
    f, b = r["forward"], r["forward_backward"]
    return (f"{name:10s} forward {f['median_s'] * 1e3:7.1f} ms (compile {f['compile_s']:4.1f} s)"
            f"   forward+backward {b['median_s'] * 1e3:7.1f} ms (compile "
            f"{b['compile_s']:4.1f} s)")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--baseline", default=BASELINE,
                        help="git revision to measure side by side ('' to skip)")
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks/results/transforms.json"))
    parser.add_argument("--only", choices=("judged", "views", "search"),
                        help="run one of the two parts (default: both)")
    parser.add_argument("--processes", type=int, default=2,
                        help="worker processes for the views and search parts (for views, as "
                        "many again on one CPU)")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        if os.environ.get(ONE_CPU):  # the work measurement: one CPU, one numba thread
            os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
        kind, _, path = args.worker.partition(":")
        result = (judged(path, args.repeats) if kind == "judged" else
                  search(args.repeats) if kind == "search" else views(args.repeats))
        print(json.dumps(result))
        return
    # a part not run keeps its figures from the last run (the results file)
    results = {}
    if args.only and os.path.exists(args.out):
        with open(args.out) as f:
            results = json.load(f)
    results["meta"] = {"repeats": args.repeats, "baseline": args.baseline,
                       "cpus": os.cpu_count(), "loadavg_before": os.getloadavg()}
    if args.only in (None, "judged"):
        judged_part(args, results)
    if args.only in (None, "views"):
        views_part(args, results, "views")
    if args.only in (None, "search"):
        views_part(args, results, "search")
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    results["meta"]["loadavg_after"] = os.getloadavg()
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)
    print(f"wrote {args.out}")


def judged_part(args, results):
    results["judged"] = {}
    print("judged scene: 5,120 faces, 256^2, K = 8, soft Phong, float32")
    with tempfile.TemporaryDirectory() as tmp:
        paths = [("host", None), ("jax", None)]
        if args.baseline:
            paths.append(("baseline", baseline_tree(args.baseline, tmp)))
        for path, tree in paths:
            results["judged"][path] = spawn(f"judged:{path}", args, tree)
            label = f"baseline {args.baseline}" if path == "baseline" else path
            print(line(label, results["judged"][path]), flush=True)


def views_part(args, results, kind):
    """The batched-views part: `views` (render_views against the loops) or `search` (the
    host face search alone; OMP_WAIT_POLICY etc. are passed on to the worker), in
    --processes worker processes (this machine runs some processes 15-100% slower than
    others: the ratios, taken within a process, do not care; absolute times do). For
    `views`, as many workers again run on one CPU with one numba thread, in turns with
    the others: the least one-CPU time of the three forms is the work of the 4 views, and
    the fastest Python loop on all CPUs over that work shared perfectly between them is
    the most any batching could gain (the ceiling)."""
    key = kind if kind == "views" else f"search_{os.environ.get('OMP_WAIT_POLICY', 'default')}"
    print(f"4 views of 5,120 faces at 128^2, soft Phong, K = 8 (default path): {kind}, "
          f"OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY', '(unset)')}")
    runs, one_cpu = [], []
    for _ in range(args.processes):
        runs.append(spawn(kind, args))
        if kind == "views":
            one_cpu.append(spawn(kind, args, extra_env={ONE_CPU: "1", "NUMBA_NUM_THREADS": "1"}))
    for r in runs + one_cpu:
        if "error" in r:
            print(line(kind, r))
            return
    results[key] = {"runs": runs, "one_cpu_runs": one_cpu, "speedup": {}}
    cpus = len(os.sched_getaffinity(0))
    for part in runs[0]["batched"]:
        speedup = results[key]["speedup"][part] = {}
        for name in [n for n in runs[0] if n != "batched"]:
            per_run = []
            for r in runs:
                loop, batched = r[name][part], r["batched"][part]
                per_run.append({measure_kind: statistics.median(a / b for a, b in zip(
                    loop[field], batched[field], strict=True))
                    for measure_kind, field in (("wall", "times_s"), ("cpu", "cpu_s"))})
                print(f"batched against {name:12s} {part:26s} median of per-round ratios: "
                      f"wall {per_run[-1]['wall']:.2f}x, CPU {per_run[-1]['cpu']:.2f}x  "
                      f"(medians: {loop['median_s'] * 1e3:.0f} ms / "
                      f"{loop['cpu_median_s'] * 1e3:.0f} ms CPU, batched "
                      f"{batched['median_s'] * 1e3:.0f} ms / "
                      f"{batched['cpu_median_s'] * 1e3:.0f} ms CPU; compile "
                      f"{loop['compile_s']:.1f} s / {batched['compile_s']:.1f} s)")
            speedup[name] = per_run
        if kind == "views":
            works = {name: min(r[name][part]["median_s"] for r in one_cpu)
                     for name in ("python_loop", "loop", "batched")}
            work = min(works.values())
            python_loop = min(r["python_loop"][part]["median_s"] for r in runs)
            speedup["ceiling"] = python_loop / (work / cpus)
            print("  fastest on one CPU: " + ", ".join(
                f"{name} {t * 1e3:.0f} ms" for name, t in works.items()) +
                f"; ceiling on {cpus} CPUs: fastest python_loop {python_loop * 1e3:.0f} ms "
                f"/ ({work * 1e3:.0f} ms / {cpus}) = {speedup['ceiling']:.2f}x")


if __name__ == "__main__":
    main()

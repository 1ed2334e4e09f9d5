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
   `render_views` call against a Python loop of `render`, forward and forward + backward
   (with respect to vertices and kd, summed over the views).

Each path runs in its own process. Printed: compile seconds (lower + compile) and the
median of --repeats calls after one warm-up call.

    .venv/bin/python benchmarks/transforms.py [--repeats 20] [--baseline 48d2648]
"""

import argparse
import json
import os
import subprocess
import sys
import tempfile

from raster import measure  # benchmarks/raster.py, beside this script

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
BASELINE = "48d2648"


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


def views(repeats):
    """render_views against a loop of render, 4 views at 128^2."""
    import jax
    import jax.numpy as jnp

    import diffshade as ds

    settings = settings_for("host")
    eyes = [(0.0, 0.0, 3.0), (2.0, 0.5, 2.2), (-2.0, 1.0, 2.0), (0.5, -2.5, 1.8)]
    scene = sphere_scene(128)
    cams = [ds.look_at(e, (0.0, 0.0, 0.0), width=128, height=128, fov_y=45.0) for e in eyes]
    stacked = ds.stack_cameras(cams)

    def loop(s):
        return jnp.stack([ds.render(ds.replace(s, camera=c), settings) for c in cams])

    def batched(s):
        return ds.render_views(s, stacked, settings)

    def loss_of(render_all):
        def loss(params):
            v, kd = params
            s = ds.replace(scene, mesh=ds.replace(scene.mesh, vertices=v),
                           material=ds.replace(scene.material, kd=kd))
            return jnp.mean(render_all(s) ** 2)
        return jax.value_and_grad(loss)
    params = (scene.mesh.vertices, scene.material.kd)
    out = {}
    for name, fn in (("loop", loop), ("batched", batched)):
        out[name] = {"forward": measure(fn, (scene,), repeats),
                     "forward_backward": measure(loss_of(fn), (params,), repeats)}
    return out


def spawn(task, args, pythonpath=None):
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", task,
           "--repeats", str(args.repeats)]
    env = dict(os.environ)
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
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        kind, _, path = args.worker.partition(":")
        result = judged(path, args.repeats) if kind == "judged" else views(args.repeats)
        print(json.dumps(result))
        return
    results = {"judged": {}}
    print("judged scene: 5,120 faces, 256^2, K = 8, soft Phong, float32")
    with tempfile.TemporaryDirectory() as tmp:
        paths = [("host", None), ("jax", None)]
        if args.baseline:
            paths.append(("baseline", baseline_tree(args.baseline, tmp)))
        for path, tree in paths:
            results["judged"][path] = spawn(f"judged:{path}", args, tree)
            label = f"baseline {args.baseline}" if path == "baseline" else path
            print(line(label, results["judged"][path]), flush=True)
    print("4 views of 5,120 faces at 128^2, soft Phong, K = 8 (default path)")
    results["views"] = spawn("views", args)
    for name in ("loop", "batched"):
        print(line(name, results["views"].get(name, results["views"])))
    if "loop" in results["views"]:
        for part in ("forward", "forward_backward"):
            ratio = (results["views"]["loop"][part]["median_s"]
                     / results["views"]["batched"][part]["median_s"])
            print(f"batched speed-up, {part}: {ratio:.2f}x")
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    results["meta"] = {"repeats": args.repeats, "baseline": args.baseline,
                       "cpus": os.cpu_count(), "loadavg": os.getloadavg()}
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

"""Benchmark of soft rasterization: forward and forward + backward, time and memory.

Scene: an icosphere (subdivisions 2..5: 320 ... 20,480 faces) filling most of a square
image (128^2, 256^2, 512^2), lit by a point and a directional light, Phong shading, soft
mode with the default sigma and gamma, K = faces_per_pixel in (4, 8, 16), float32.
- forward: render(scene) -> [H, W, 4];
- forward + backward: value_and_grad of the MSE to a target image (uniform grey: the
  cost does not depend on it) with respect to the vertices and kd, ks.

Each configuration runs in its own process, so that its peak resident memory
(getrusage ru_maxrss) is its own. Reported per configuration: compile time (lower +
compile), steady-state median of `--repeats` calls after one warm-up call, XLA's compiled
memory (temp + output bytes, from `memory_analysis()`) and bytes per pixel per K, the
process's peak RSS after forward + backward (which runs first) and its baseline before
(imports and scene), `dropped`; and the same timings of the dense O(pixels x faces) oracle
of tests/soft_reference.py (jitted, row blocks rematerialized in the backward pass) with
the speed-up over it. The oracle evaluates every (pixel, face) pair whatever the image
holds, so its cost is linear in the number of rows: it is timed on a band of rows of
about --dense-pairs pairs (the whole image when it fits) and scaled to the image; it
does not depend on K, so it is timed once per mesh and size.

    .venv/bin/python benchmarks/raster.py [--quick] [--out benchmarks/results/raster.json]
"""

import argparse
import importlib.metadata
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SUBDIVISIONS, SIZES, KS = (2, 3, 4, 5), (128, 256, 512), (4, 8, 16)
QUICK = [(2, 128, 4), (4, 256, 8)]
#: pairs of (pixel, face) per block of the dense oracle: bounds its memory
DENSE_BLOCK_PAIRS = 1 << 20


def make_scene(subdivisions, size):
    """The benchmark scene: a unit icosphere seen from 3 units (it spans ~80% of the image)."""
    import diffshade as ds

    cam = ds.look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=size, height=size, fov_y=45.0)
    lights = [ds.point_light((2.0, 2.0, 3.0), 0.7), ds.directional_light((-0.3, -0.5, -1.0), 0.4)]
    mat = ds.material(ka=0.2, kd=(0.6, 0.5, 0.4), ks=0.4, shininess=20.0)
    return ds.make_scene(ds.icosphere(subdivisions), cam, lights, mat)


def loss_fn(render, settings, scene, target_image):
    """MSE to the target as a function of (vertices, kd, ks)."""
    import jax.numpy as jnp

    from diffshade import replace

    def loss(params):
        vertices, kd, ks = params
        moved = replace(scene, mesh=replace(scene.mesh, vertices=vertices),
                        material=replace(scene.material, kd=kd, ks=ks))
        return jnp.mean((render(moved, settings) - target_image) ** 2)
    return loss


def measure(fn, args, repeats, budget_s=None, max_bytes=None, warmup=1):
    """Compile seconds, warm-up seconds, steady-state median seconds (wall clock, and CPU
    seconds of all the process's threads: on a loaded machine the steadier measure of the
    work done) and memory stats.
    budget_s: stop timing once the timed calls add up to this (at least one is timed);
    max_bytes: when XLA's compiled memory (temp + output) exceeds it, do not run: the
    result then holds 'skipped' (the reason) and the compile figures only. warmup: untimed
    calls before the timed ones (warmup_s is the first's)."""
    import jax

    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - t0
    mem = compiled.memory_analysis()
    out = {"compile_s": compile_s, "temp_bytes": int(mem.temp_size_in_bytes),
           "output_bytes": int(mem.output_size_in_bytes),
           "argument_bytes": int(mem.argument_size_in_bytes)}
    needed = out["temp_bytes"] + out["output_bytes"]
    if max_bytes is not None and needed > max_bytes:
        return {**out, "skipped": f"XLA needs {needed / 2**30:.1f} GiB "
                                  f"(> {max_bytes / 2**30:.1f} GiB allowed)"}
    t0 = time.perf_counter()
    jax.block_until_ready(compiled(*args))
    warmup_s = time.perf_counter() - t0
    for _ in range(warmup - 1):
        jax.block_until_ready(compiled(*args))
    times, cpu_times = [], []
    while len(times) < repeats and (budget_s is None or not times or sum(times) < budget_s):
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(compiled(*args))
        times.append(time.perf_counter() - t0)
        cpu_times.append(time.process_time() - c0)
    return {**out, "warmup_s": warmup_s, "median_s": statistics.median(times),
            "times_s": times, "cpu_median_s": statistics.median(cpu_times)}


def largest_divisor(n, at_most):
    """The largest divisor of n that is <= at_most (and >= 1)."""
    d = max(1, min(n, int(at_most)))
    while n % d:
        d -= 1
    return d


def peak_rss_bytes():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def measure_dense(scene, settings, target_image, params, max_pairs, repeats):
    """Time the dense oracle on a band of rows holding <= max_pairs (pixel, face) pairs
    and scale to the whole image: the oracle evaluates every pair, whatever it holds, so
    its cost is proportional to the number of rows."""
    import jax

    sys.path.insert(0, os.path.join(ROOT, "tests"))
    from soft_reference import soft_reference

    size, num_faces = scene.camera.height, int(scene.mesh.faces.shape[0])
    band = largest_divisor(size, max_pairs // (size * num_faces))
    block = largest_divisor(band, DENSE_BLOCK_PAIRS // (size * num_faces))

    def dense_render(s, _settings):
        return soft_reference(s, settings, block_rows=block, row_range=(0, band))
    out = {"band_rows": band, "block_rows": block, "scale": size / band,
           "forward": measure(lambda s: dense_render(s, settings), (scene,), repeats),
           "forward_backward": measure(jax.value_and_grad(
               loss_fn(dense_render, settings, scene, target_image[:band])), (params,), repeats)}
    for name in ("forward", "forward_backward"):
        out[name]["image_s"] = out[name]["median_s"] * out["scale"]
    return out


def run_config(subdivisions, size, k, repeats, dense_pairs, dense_repeats):
    """One configuration (in a fresh process): a JSON-able dict; the dense oracle is timed
    when dense_pairs > 0 (see measure_dense). Forward + backward runs first, so that the
    peak RSS after it is its own (over the baseline of imports and scene)."""
    import jax
    import jax.numpy as jnp

    from diffshade import CPU_TUNING, RenderSettings, rasterize_scene, render

    settings = RenderSettings(raster="soft", faces_per_pixel=k, shading="phong")
    scene = make_scene(subdivisions, size)
    # a grey target: its content does not change the cost, and rendering one would
    # raise the peak memory before the measurement
    target_image = jnp.full((size, size, 4), 0.5, jnp.float32)
    params = (scene.mesh.vertices, scene.material.kd, scene.material.ks)
    out = {"subdivisions": subdivisions, "faces": int(scene.mesh.faces.shape[0]), "size": size,
           "k": k, "baseline_rss_bytes": peak_rss_bytes(), "loadavg_1min": os.getloadavg()[0],
           "cpu_tuning": CPU_TUNING}
    loss = loss_fn(render, settings, scene, target_image)
    out["forward_backward"] = measure(jax.value_and_grad(loss), (params,), repeats)
    out["peak_rss_bytes"] = peak_rss_bytes()
    out["forward"] = measure(lambda s: render(s, settings), (scene,), repeats)
    out["dropped"] = int(rasterize_scene(scene, settings).dropped)
    for name in ("forward", "forward_backward"):
        m = out[name]
        m["bytes_per_pixel_per_k"] = (m["temp_bytes"] + m["output_bytes"]) / (size * size * k)
    if dense_pairs > 0:
        out["dense"] = measure_dense(scene, settings, target_image, params, dense_pairs,
                                     dense_repeats)
    return out


def spawn(config, dense, args):
    """Run one configuration in a subprocess; its last stdout line is the JSON result."""
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", json.dumps(config),
           "--repeats", str(args.repeats), "--dense-repeats", str(args.dense_repeats),
           "--dense-pairs", str(int(args.dense_pairs) if dense else 0)]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    if proc.returncode != 0:
        return {"config": config, "error": proc.stderr[-2000:]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def add_speedups(result, dense):
    """The dense oracle's whole-image time over ours (it does not depend on K)."""
    result["dense"] = dense
    for name in ("forward", "forward_backward"):
        result[f"{name}_speedup"] = dense[name]["image_s"] / result[name]["median_s"]


def row(r):
    if "error" in r:
        return f"{r['config']}: FAILED\n{r['error']}"
    fwd, fb = r["forward"], r["forward_backward"]
    text = (f"{r['faces']:6d} faces {r['size']:4d}^2 K={r['k']:2d} | "
            f"fwd {fwd['median_s'] * 1e3:8.1f} ms  fwd+bwd {fb['median_s'] * 1e3:8.1f} ms | "
            f"compile {fwd['compile_s']:5.1f} + {fb['compile_s']:5.1f} s | "
            f"B/px/K {fwd['bytes_per_pixel_per_k']:6.0f} / {fb['bytes_per_pixel_per_k']:6.0f} | "
            f"fwd+bwd peak RSS {r['peak_rss_bytes'] / 2**30:5.2f} GiB "
            f"(baseline {r['baseline_rss_bytes'] / 2**30:4.2f}) | dropped {r['dropped']}")
    if "dense" in r:
        d = r["dense"]
        how = "measured" if d["scale"] == 1 else f"{d['band_rows']} rows x {d['scale']:g}"
        text += (f"\n{'':29s}dense ({how}): fwd {d['forward']['image_s']:8.2f} s "
                 f"({r['forward_speedup']:6.0f}x)  fwd+bwd "
                 f"{d['forward_backward']['image_s']:8.2f} s "
                 f"({r['forward_backward_speedup']:6.0f}x)")
    return text


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"only {QUICK}")
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks/results/raster.json"))
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--dense-repeats", type=int, default=1)
    parser.add_argument("--dense-pairs", type=float, default=1e7,
                        help="(pixel, face) pairs of the band the dense oracle is timed on "
                             "(0: skip it)")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        config = json.loads(args.worker)
        print(json.dumps(run_config(*config, args.repeats, args.dense_pairs,
                                    args.dense_repeats)))
        return
    configs = QUICK if args.quick else [(s, n, k) for s in SUBDIVISIONS for n in SIZES
                                        for k in KS]
    results, dense = [], {}
    for config in configs:
        scene_key = tuple(config[:2])
        result = spawn(config, args.dense_pairs > 0 and scene_key not in dense, args)
        if "dense" in result:
            dense[scene_key] = result["dense"]
        if "error" not in result and scene_key in dense:
            add_speedups(result, dense[scene_key])
        results.append(result)
        print(row(result), flush=True)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    meta = {"command": " ".join([os.path.relpath(sys.argv[0], ROOT)] + sys.argv[1:]),
            "machine": platform.platform(), "cpus": os.cpu_count(),
            "python": platform.python_version(), "jax": importlib.metadata.version("jax"),
            "repeats": args.repeats}
    with open(args.out, "w") as f:
        json.dump({"meta": meta, "results": results}, f, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

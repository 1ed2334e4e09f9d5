"""The host soft search of a git revision against the working copy's, on the judged scene.

A change to the soft search kernel (diffshade/host/candidates.py) should find the same
face ids and drop the same fragments, faster. This loads the revision's candidates.py
(`git show REF:diffshade/host/candidates.py`, as a module of its own) next to the working
copy's, calls each one's search (`_search_soft`, the kernel the soft render's FFI target
runs) on the judged scene of benchmarks/peers.py, and times them interleaved in one
process (call A, call B, A, B, ...: both see the same state of a shared machine), after a
warm-up; numba compiles both first (not timed). Printed per variant: the median and the
minimum wall time at the given thread count, the fragments dropped and a CRC of the face
ids, which must match.

    python benchmarks/search_ab.py [--ref HEAD] [--threads 1] [--repeats 60] [--size 256]

One thread shows a kernel's work; two, what the render sees. Nothing is written.
"""

import argparse
import importlib.util
import os
import statistics
import subprocess
import sys
import tempfile
import time
import zlib

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
KERNEL = "diffshade/host/candidates.py"


def load(name, source, folder):
    """The module `name` made from `source` (a file of its own in `folder`)."""
    path = os.path.join(folder, f"{name}.py")
    with open(path, "w") as f:
        f.write(source)
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ref", default="HEAD", help="git revision of the baseline")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=60)
    parser.add_argument("--size", type=int, default=256)
    args = parser.parse_args(argv)

    import jax
    import numba
    import numpy as np
    from peers import judged_scene

    import diffshade as ds
    from diffshade.raster.projection import project
    from diffshade.raster.search import soft_radius

    shown = subprocess.run(["git", "show", f"{args.ref}:{KERNEL}"], cwd=ROOT,
                           capture_output=True, text=True)
    if shown.returncode != 0:
        parser.error(f"--ref {args.ref!r}: git has no {KERNEL} there "
                     f"({shown.stderr.strip()})")
    baseline = shown.stdout
    with open(os.path.join(ROOT, KERNEL)) as f:
        current = f.read()
    scene = judged_scene(args.size, 4)
    soft = ds.RenderSettings(raster="soft", faces_per_pixel=8, shading="phong")
    cam = scene.camera
    clip = np.asarray(jax.jit(project)(scene).clip, np.float64)[None].copy()
    faces = np.asarray(scene.mesh.faces, np.int64)
    radii = np.array([float(soft_radius(soft))])
    params = np.array([[soft.sigma, soft.gamma, float(cam.near), float(cam.far)]])
    numba.set_num_threads(args.threads)
    with tempfile.TemporaryDirectory() as folder:
        variants = {args.ref: load("search_ab_ref", baseline, folder),
                    "working copy": load("search_ab_new", current, folder)}

        def call(module):
            start = time.perf_counter()
            ids, dropped = module._search_soft(clip, faces, cam.width, cam.height, 8, False,
                                               radii, params, True, args.threads)[:2]
            return time.perf_counter() - start, ids, dropped

        for module in variants.values():  # compile, then warm up
            for _ in range(3):
                call(module)
        times = {name: [] for name in variants}
        for _ in range(args.repeats):
            for name, module in variants.items():
                times[name].append(call(module)[0])
        found = {name: call(module)[1:] for name, module in variants.items()}
    print(f"soft search, judged scene at {args.size}^2, K = 8, {args.threads} thread(s), "
          f"{args.repeats} calls each, interleaved; loadavg {os.getloadavg()[0]:.1f}")
    for name, runs in times.items():
        ids, dropped = found[name]
        print(f"  {name:14s} median {statistics.median(runs) * 1e3:7.3f} ms  min "
              f"{min(runs) * 1e3:7.3f} ms  dropped {int(dropped[0]):7d}  "
              f"ids crc {zlib.crc32(np.ascontiguousarray(ids).tobytes()):08x}")
    (ids_a, dropped_a), (ids_b, dropped_b) = found.values()
    same = np.array_equal(ids_a, ids_b) and np.array_equal(dropped_a, dropped_b)
    print("same face ids and dropped counts" if same else "RESULTS DIFFER")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())

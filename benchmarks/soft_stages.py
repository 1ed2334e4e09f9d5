"""Where the soft render's time goes, stage by stage, on the judged scene of peers.py.

The judged scene (benchmarks/peers.py: 5,120-face icosphere, 256^2, one directional
light, soft K = 8, Phong). Each stage is timed on its own, on the inputs the render gives
it: the whole soft forward (render), the hard forward, the rasterization
(rasterize_scene: search + fragment geometry), the search kernel alone
(candidates.find_candidates), the geometry and interpolation kernels alone
(fragment_kernels), the blend weights, the active-slot compaction (compact.active_indices)
and what follows the rasterization (render_fragments); everything after the search (the
fragment geometry from fixed face ids, then render_fragments), forward and forward +
backward with respect to the material and the vertices; then forward + backward with
respect to the material, and to the material and the vertices; and the cached material
steps (value_and_grad w.r.t. the material through render_fragments on cached fragments,
and through render_cached on cache_shading).

Printed per stage: the median wall time and the median and minimum CPU time (all
threads) of --repeats calls after a warm-up call. On a machine shared with other jobs, the
minimum CPU time is the steadiest figure; run with NUMBA_NUM_THREADS=1 to see each stage's
work without OpenMP threads spinning at barriers (docs/performance.md).

    python benchmarks/soft_stages.py [--repeats 15]
"""

import argparse
import importlib
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def timed(fn, repeats):
    import jax

    jax.block_until_ready(fn())
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn())
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu), min(cpu)


def stages(size):
    """(name, zero-argument function) per stage."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from peers import SOFT_K, judged_scene, mse_grad

    import diffshade as ds
    from diffshade.host import fragment_kernels as kernels
    from diffshade.host.candidates import find_candidates
    from diffshade.raster import fragments as raster
    from diffshade.raster.fragments import fragments_from_ids
    from diffshade.raster.projection import project
    from diffshade.raster.search import soft_radius
    from diffshade.shading.compact import active_indices

    render_module = importlib.import_module("diffshade.pipeline.rendering")
    scene = judged_scene(size, 4)
    soft = ds.RenderSettings(raster="soft", faces_per_pixel=SOFT_K, shading="phong")
    hard = ds.RenderSettings(raster="hard", shading="phong")
    frags = ds.rasterize_scene(scene, soft)
    proj = jax.jit(project)(scene)
    faces = scene.mesh.faces
    clip = np.asarray(proj.clip, np.float64)
    radius = float(soft_radius(soft))
    ids = np.asarray(frags.face_ids).reshape(-1, SOFT_K)
    coeffs = np.asarray(raster.face_edge_coefficients(proj.clip, faces)[0])
    corner_w = np.asarray(jnp.take(proj.clip[:, 3], faces))
    corner_z = np.asarray(jnp.take(proj.depth, faces))
    scr = np.asarray(jnp.take(raster._screen_positions(proj.clip, size, size), faces, axis=0))
    bary = np.asarray(frags.bary).reshape(-1, SOFT_K, 3)
    corners = np.asarray(jnp.take(jnp.concatenate([proj.world, proj.normals], -1), faces,
                                  axis=0))
    weights = jax.jit(lambda s, f: render_module.blend_weights(s, f, soft))
    active = (weights(scene, frags)[0] > 0.0).reshape(-1)
    compaction = jax.jit(lambda m: active_indices(m, size * size * 4))
    after_raster = jax.jit(lambda s, f: ds.render_fragments(s, f, soft))
    target = jnp.full((size, size, 4), 0.5, jnp.float32)
    fb_material = jax.jit(mse_grad(scene, soft, target)[0])
    fb_vertices, vertex_args = mse_grad(scene, soft, target, True)
    fb_vertices = jax.jit(fb_vertices)

    def mse(image):
        return jnp.mean((image - target) ** 2)

    def after_search(material, vertices):
        moved = ds.replace(scene, material=material,
                           mesh=ds.replace(scene.mesh, vertices=vertices))
        moved_proj = project(moved)
        moved_frags = fragments_from_ids(moved_proj, faces, frags.face_ids, frags.dropped,
                                         soft=True)
        return ds.render_fragments(moved, moved_frags, soft, proj=moved_proj)
    after_search_fwd = jax.jit(after_search)
    after_search_fb = jax.jit(jax.value_and_grad(lambda m, v: mse(after_search(m, v)),
                                                 argnums=(0, 1)))
    material_vertices = (scene.material, scene.mesh.vertices)
    cached_frags = jax.jit(jax.value_and_grad(lambda m, s, f: mse(
        ds.render_fragments(ds.replace(s, material=m), f, soft))))
    cache = ds.cache_shading(scene, frags, soft)
    cached = jax.jit(jax.value_and_grad(lambda m, s, c: mse(
        ds.render_cached(ds.replace(s, material=m), c, soft))))
    return [
        ("soft forward (render)", lambda: ds.render(scene, soft)),
        ("hard forward (render)", lambda: ds.render(scene, hard)),
        ("rasterize_scene, soft", lambda: ds.rasterize_scene(scene, soft)),
        ("  search kernel", lambda: find_candidates(
            clip, np.asarray(faces), float(scene.camera.near), float(scene.camera.far),
            width=size, height=size, k=SOFT_K, radius_px=radius, sigma=soft.sigma,
            gamma=soft.gamma)),
        ("  geometry forward kernel", lambda: kernels.geometry_forward(
            ids, corner_w, corner_z, coeffs, scr, size, size, True, 1e-30, kernels.chunks())),
        ("render_fragments", lambda: after_raster(scene, frags)),
        ("  interpolation kernel, all slots", lambda: kernels.interpolate_forward(
            ids, bary, corners, kernels.chunks())),
        ("  blend weights", lambda: weights(scene, frags)),
        ("  active slots (compaction)", lambda: compaction(active)),
        ("after the search, forward", lambda: after_search_fwd(*material_vertices)),
        ("after the search, f+b mat. + vert.", lambda: after_search_fb(*material_vertices)),
        ("soft f+b, material", lambda: fb_material(scene.material)),
        ("soft f+b, material + vertices", lambda: fb_vertices(*vertex_args)),
        ("cached step, render_fragments", lambda: cached_frags(scene.material, scene, frags)),
        ("cached step, render_cached", lambda: cached(scene.material, scene, cache)),
    ]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args()
    print(f"judged scene at {args.size}^2; loadavg {os.getloadavg()[0]:.1f}; "
          f"NUMBA_NUM_THREADS={os.environ.get('NUMBA_NUM_THREADS', 'default')}")
    print(f"{'stage':36s} {'wall ms':>9s} {'CPU ms':>9s} {'min CPU ms':>11s}")
    for name, fn in stages(args.size):
        wall, cpu, cpu_min = timed(fn, args.repeats)
        print(f"{name:36s} {wall * 1e3:9.1f} {cpu * 1e3:9.1f} {cpu_min * 1e3:11.1f}", flush=True)


if __name__ == "__main__":
    main()

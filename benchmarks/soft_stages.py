"""Where the soft render's time goes, stage by stage, on the judged scene of peers.py.

The judged scene (benchmarks/peers.py: 5,120-face icosphere, 256^2, one directional
light, soft K = 8, Phong). Each stage is timed on its own, on the inputs the render gives
it: the whole soft forward (render), the hard forward and its search kernel alone, the
rasterization (rasterize_scene: search + fragment geometry), the search kernel alone
(candidates.find_candidates) and its per-face setup and binning into tiles (the part
before its parallel loop over tiles), the geometry and interpolation kernels alone
(fragment_kernels), forward and backward (given cotangents where a reverse pass has them:
barycentrics and depth where the blend weight is not 0, the distance wherever a face
is), the interpolation at the active slots as render's forward runs it
(interpolate_at, compact.on_active's largest size), the interpolation backward also on
the active slots gathered as a forward + backward runs it, the blend weights, the active-slot
compaction (compact.active_indices) and what follows the rasterization
(render_fragments); everything after the search (the fragment geometry from fixed face
ids, then render_fragments), forward and forward + backward with respect to the material
and the vertices; then forward + backward with respect to the material, and to the
material and the vertices; and the cached material steps (value_and_grad w.r.t. the
material through render_fragments on cached fragments, and through render_cached on
cache_shading).

Printed per stage: the median wall time and the median and minimum CPU time (all
threads) of --repeats calls after a warm-up call, and the stage's memory-traffic floor:
the bytes it must at least read and write (its per-fragment inputs and outputs, each once;
`traffic` below says which) over the machine's memory bandwidth, measured first as the
best of a few large NumPy copies (one thread; read + write). A stage far above its floor
is bound by its arithmetic or its overheads, not by memory. On a machine shared with other
jobs, the minimum CPU time is the steadiest figure; run with NUMBA_NUM_THREADS=1 to see
each stage's work without OpenMP threads spinning at barriers (docs/performance.md).

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


def bandwidth(megabytes=256, repeats=5):
    """Memory bandwidth in bytes per second: the best of `repeats` copies of a
    `megabytes` float64 array (bytes read + bytes written over the time), one thread."""
    import numpy as np

    src = np.ones(megabytes * 2 ** 20 // 8)
    dst = np.empty_like(src)
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        np.copyto(dst, src)
        best = min(best, time.perf_counter() - t0)
    return 2 * src.nbytes / best


def traffic(frags, capacity, image_bytes):
    """Bytes each stage must at least read and write, by stage kind, from the soft
    fragments' arrays (N = H x W x K slots): the search writes the face ids (4N); the
    geometry reads them and writes barycentrics, depth and distance (24N); the
    interpolation reads ids and barycentrics and writes 6 floats per slot (positions and
    normals, 40N); the blend weights read ids, depth and distance and write a weight
    (16N); the compaction reads the mask (N) and writes `capacity` indices; shading and
    blending read the fragments and write the image (a cached step: the shading cache,
    stages()). The geometry backward reads the ids, the saved nearest edges (N) and the
    cotangents of the geometry's outputs (25N in all); the interpolation backward reads
    the ids, barycentrics and the cotangents of its 6 floats and writes the barycentrics'
    (52N). A forward + backward reads and
    writes at least as much again (each array the forward reads has a cotangent of its
    size). The interpolation backward on the compacted active slots reads and writes as
    much per slot, for `capacity` slots of one fragment each; the interpolation at the
    active slots (render's forward) reads a position, a face id and barycentrics and
    writes 6 floats per slot. The hard search writes one
    face id per pixel. Per-face inputs and the image are small next to these."""
    nbytes = lambda name: getattr(frags, name).nbytes
    ids, slots = nbytes("face_ids"), frags.face_ids.size
    geometry_out = nbytes("bary") + nbytes("depth") + nbytes("dist")
    search, geometry = ids, ids + geometry_out
    fragments = ids + geometry_out + nbytes("front")
    shading = fragments + image_bytes
    forward = search + geometry + shading
    # hard mode: one slot per pixel (ids, barycentrics, depth, side; no distance)
    pixels = slots // frags.face_ids.shape[-1]
    hard = pixels * (4 + (4 + 16) + (4 + 16 + 1)) + image_bytes
    return {"forward": forward, "hard": hard, "hard_search": pixels * 4,
            "raster": search + geometry, "search": search, "geometry": geometry,
            "geometry_backward": ids + slots + geometry_out,
            "interpolation_backward": ids + 2 * nbytes("bary") + 6 * 4 * slots,
            "interpolation_backward_active": capacity * (4 + 2 * 12 + 6 * 4),
            "interpolation_active": capacity * (4 + 4 + 12 + 6 * 4),
            "shading": shading, "interpolation": ids + nbytes("bary") + 6 * 4 * slots,
            "weights": ids + nbytes("depth") + nbytes("dist") + 4 * slots,
            "compaction": slots + 4 * capacity, "after_search": geometry + shading,
            "after_search_fb": 2 * (geometry + shading), "fb": 2 * forward,
            "cached": 2 * shading}


def _cotangents(ids, active, seed=0):
    """Cotangents as a reverse pass gives them to the geometry and interpolation kernels:
    of the barycentrics [P, K, 3], depth [P, K] and interpolated values [P, K, 6] where
    active [P, K] (the blend weight is not 0), of the distance [P, K] where a face is
    (the coverage counts every fragment); random normal, float32."""
    import numpy as np

    rng = np.random.default_rng(seed)
    normal = lambda *shape: rng.standard_normal(ids.shape + shape).astype(np.float32)
    on, valid = active[..., None], (ids >= 0)
    return normal(3) * on, normal() * active, normal() * valid, normal(6) * on


def stages(size):
    """(name, zero-argument function, traffic key) per stage."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from peers import SOFT_K, judged_scene, mse_grad

    import diffshade as ds
    from diffshade.host import candidates
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
    geometry_args = (ids, corner_w, corner_z, coeffs, scr, size, size, True, 1e-30,
                     kernels.chunks())
    edge = kernels.geometry_forward(*geometry_args)[3]
    g_bary, g_depth, g_dist, g_values = _cotangents(ids, np.asarray(active).reshape(ids.shape))
    # the indices are found for the largest tier (compact.on_active)
    capacity = size * size * max(render_module.ACTIVE_SLOTS_PER_PIXEL)
    compaction = jax.jit(lambda m: active_indices(m, capacity))
    # the active slots as on_active gathers them: pixels of one slot each, the padding
    # (index N) with face id -1
    idx = np.asarray(compaction(active)[0])
    inside = idx < ids.size
    rows = np.minimum(idx, ids.size - 1)
    ids_active = np.where(inside, ids.reshape(-1)[rows], -1).astype(np.int32)[:, None]
    bary_active = bary.reshape(-1, 3)[rows][:, None]
    g_active = g_values.reshape(-1, 6)[rows][:, None] * inside[:, None, None]
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
    faces64, radii = np.asarray(faces, np.int64), np.array([radius])
    params = np.array([[soft.sigma, soft.gamma, float(scene.camera.near),
                        float(scene.camera.far)]])

    def search_setup():
        setup = candidates._soft_setup(clip[None], faces64, size, size, False, radii, params,
                                       scene.camera.projection == "perspective")
        _, _, _, zndc, box, reach, _ = setup
        return setup, candidates._bin_faces(box, reach, zndc, size, size)
    floors = traffic(frags, capacity, size * size * 4 * 4)
    # the setup reads the vertices and faces and writes its per-face and per-tile arrays
    floors["setup"] = clip.nbytes + faces64.nbytes + sum(
        a.nbytes for part in search_setup() for a in part)
    # the cached step reads the shading cache and writes its cotangent
    floors["render_cached"] = 2 * sum(leaf.nbytes for leaf in jax.tree.leaves(cache))
    return floors, [
        ("soft forward (render)", lambda: ds.render(scene, soft), "forward"),
        ("hard forward (render)", lambda: ds.render(scene, hard), "hard"),
        ("  hard search kernel", lambda: find_candidates(
            clip, np.asarray(faces), float(scene.camera.near), float(scene.camera.far),
            width=size, height=size, k=1), "hard_search"),
        ("rasterize_scene, soft", lambda: ds.rasterize_scene(scene, soft), "raster"),
        ("  search kernel", lambda: find_candidates(
            clip, np.asarray(faces), float(scene.camera.near), float(scene.camera.far),
            width=size, height=size, k=SOFT_K, radius_px=radius, sigma=soft.sigma,
            gamma=soft.gamma), "search"),
        ("    its setup and binning", search_setup, "setup"),
        ("  geometry forward kernel", lambda: kernels.geometry_forward(*geometry_args),
         "geometry"),
        ("  geometry backward kernel", lambda: kernels.geometry_backward(
            *geometry_args, edge, g_bary, g_depth, g_dist), "geometry_backward"),
        ("render_fragments", lambda: after_raster(scene, frags), "shading"),
        ("  interpolation kernel, all slots", lambda: kernels.interpolate_forward(
            ids, bary, corners, kernels.chunks()), "interpolation"),
        ("  interpolation at the active slots", lambda: kernels.interpolate_at(
            idx, ids.reshape(-1), bary.reshape(-1, 3), corners, kernels.chunks()),
         "interpolation_active"),
        ("  interpolation backward, all slots", lambda: kernels.interpolate_backward(
            ids, bary, corners, g_values, kernels.chunks()), "interpolation_backward"),
        ("  interp. backward, active slots", lambda: kernels.interpolate_backward(
            ids_active, bary_active, corners, g_active, kernels.chunks()),
         "interpolation_backward_active"),
        ("  blend weights", lambda: weights(scene, frags), "weights"),
        ("  active slots (compaction)", lambda: compaction(active), "compaction"),
        ("after the search, forward", lambda: after_search_fwd(*material_vertices),
         "after_search"),
        ("after the search, f+b mat. + vert.", lambda: after_search_fb(*material_vertices),
         "after_search_fb"),
        ("soft f+b, material", lambda: fb_material(scene.material), "fb"),
        ("soft f+b, material + vertices", lambda: fb_vertices(*vertex_args), "fb"),
        ("cached step, render_fragments", lambda: cached_frags(scene.material, scene, frags),
         "cached"),
        ("cached step, render_cached", lambda: cached(scene.material, scene, cache),
         "render_cached"),
    ]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args()
    print(f"judged scene at {args.size}^2; loadavg {os.getloadavg()[0]:.1f}; "
          f"NUMBA_NUM_THREADS={os.environ.get('NUMBA_NUM_THREADS', 'default')}")
    rate = bandwidth()
    print(f"memory bandwidth {rate / 1e9:.1f} GB/s (best NumPy copy, read + write)")
    floors, timed_stages = stages(args.size)
    print(f"{'stage':36s} {'wall ms':>9s} {'CPU ms':>9s} {'min CPU ms':>11s} "
          f"{'floor ms':>9s} {'MB':>6s} {'x floor':>8s}")
    for name, fn, kind in timed_stages:
        wall, cpu, cpu_min = timed(fn, args.repeats)
        floor = floors[kind] / rate
        print(f"{name:36s} {wall * 1e3:9.1f} {cpu * 1e3:9.1f} {cpu_min * 1e3:11.1f} "
              f"{floor * 1e3:9.2f} {floors[kind] / 1e6:6.1f} {wall / floor:8.1f}", flush=True)


if __name__ == "__main__":
    main()

"""Peer benchmark: diffshade against Mitsuba 3 on the judged scene, in one run.

The judged scene: an icosphere (subdivision 4: 5,120 faces, exact vertex normals) seen
from (0, 0, 3) with a 45-degree vertical field of view at 256^2, lit by one white
directional light travelling along (-0.3, -0.5, -1).
- diffshade: Blinn-Phong material (ka 0.2, kd (0.6, 0.5, 0.4), ks 0.4, shininess 20),
  global ambient 0.2, Phong shading; hard raster, and soft raster with K = 8. Timed: hard
  forward; hard forward + backward (value_and_grad of the MSE to a grey image with
  respect to the material); soft forward; soft f+b material; soft f+b material and
  vertices; the cached material step of a fit (fitting.model.build_cache +
  fitting.solve.make_step: an Adam step on the kept pixels of the same view, as
  benchmarks/fit_step.py times it); the soft cached material step (value_and_grad of
  the MSE w.r.t. the material of diffshade.render_cached on the soft render's
  cache_shading: fixed geometry, re-lit).
- Mitsuba 3 (variant llvm_ad_rgb, the `prb` integrator with max_depth 2: direct light,
  all a convex object with one light has), `diffuse` BSDF with reflectance kd, 4 samples
  per pixel, box pixel filter, the same mesh (positions, faces, normals), a `perspective`
  sensor with fov 45 along y and to_world = look_at(eye, target, up), and a `directional`
  emitter with the same direction and irradiance pi (so that kd/pi * cos * pi equals
  diffshade's Lambert term kd * cos). Timed: forward (mi.render) and forward + backward
  (dr.backward of the MSE to a grey image, gradient with respect to the reflectance).

The cameras are checked to match: a diffshade render with a Lambert-only material (no
ambient, no specular) against Mitsuba's image; printed: the IoU of the coverage masks
(alpha > 0.5) and the largest colour difference inside both masks (away from the outline).

Each engine runs in its own process (--rounds times, alternating; Mitsuba with an empty
kernel cache in the first round). Printed: compile seconds (the first call: tracing and
compilation, cold) and the median of --repeats calls after WARMUP untimed calls (the
first included), the same number for both; the speed ratio of the pooled medians, and
the lowest and highest ratio of a single round (each round times both engines, one
process after the other), which shows how much the machine moved between rounds. Mitsuba is an
optional extra (pip install '.[peers]'); where it cannot run (not installed, or Dr.Jit
finds no libLLVM: see docs/performance.md), one line says so and the script exits with
status 0 after diffshade's figures.

    python benchmarks/peers.py [--size 256] [--subdivisions 4] [--repeats 20] [--rounds 1]
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EYE, FOV_Y, LIGHT_DIRECTION, KD = (0.0, 0.0, 3.0), 45.0, (-0.3, -0.5, -1.0), (0.6, 0.5, 0.4)
SPP, VARIANT, SOFT_K = 4, "llvm_ad_rgb", 8
#: untimed calls before the timed ones, for both engines: the first (compile and run) and
#: two more (diffshade's compile runs nothing, so it makes all three calls after it)
WARMUP = 3
#: (key, label, Mitsuba row it is compared with)
ROWS = (("hard_forward", "hard forward", "forward"),
        ("hard_fb_material", "hard f+b, material", "forward_backward"),
        ("soft_forward", "soft forward", "forward"),
        ("soft_fb_material", "soft f+b, material", "forward_backward"),
        ("soft_fb_material_vertices", "soft f+b, material + vertices", None),
        ("cached_step", "cached material step", "forward_backward"),
        ("soft_cached_step", "soft cached material step", "forward_backward"))
KEYS = [key for key, _, _ in ROWS]


def judged_scene(size, subdivisions, lambert=False):
    """The judged scene; lambert: kd only, no ambient (the term Mitsuba's diffuse equals)."""
    import diffshade as ds

    cam = ds.look_at(EYE, (0.0, 0.0, 0.0), width=size, height=size, fov_y=FOV_Y)
    light = ds.directional_light(LIGHT_DIRECTION, 1.0)
    if lambert:
        return ds.make_scene(ds.icosphere(subdivisions), cam, [light],
                             ds.material(ka=0.0, kd=KD), global_ambient=0.0)
    return ds.make_scene(ds.icosphere(subdivisions), cam, [light],
                         ds.material(ka=0.2, kd=KD, ks=0.4, shininess=20.0))


def mse_grad(scene, settings, target, with_vertices=False):
    """value_and_grad of the MSE to `target` w.r.t. the material (and the vertices)."""
    import jax
    import jax.numpy as jnp

    import diffshade as ds

    def loss(params):
        material, vertices = params
        moved = ds.replace(scene, material=material,
                           mesh=ds.replace(scene.mesh, vertices=vertices))
        return jnp.mean((ds.render(moved, settings) - target) ** 2)
    if with_vertices:
        return jax.value_and_grad(loss), ((scene.material, scene.mesh.vertices),)
    return (jax.value_and_grad(lambda m: loss((m, scene.mesh.vertices))), (scene.material,))


def cached_step(scene, settings, repeats):
    """The cached material step of a fit of this one view: (compile_s, median_s)."""
    from fit_step import time_step  # benchmarks/fit_step.py, beside this script

    import diffshade as ds
    import fitting

    target = np.asarray(ds.render(scene, settings))[..., :3]
    view = fitting.View(scene.camera, scene.lights, target)
    dataset = fitting.Dataset(scene.mesh, [view], global_ambient=0.2, settings=settings)
    spec, optimizer = fitting.FitSpec(), fitting.solve.make_optimizer()
    params = fitting.spec.to_unconstrained(fitting.DEFAULT_INIT, spec)
    step = fitting.solve.make_step(fitting.model.make_loss(spec), optimizer)
    first, times = time_step(step, params, optimizer.init(params),
                             fitting.model.build_cache(dataset, fitting.DEFAULT_INIT), repeats,
                             WARMUP - 1)
    return {"compile_s": first, "median_s": float(np.median(times))}


def soft_cached(scene, settings, target):
    """value_and_grad of the MSE w.r.t. the material on the soft render's fixed geometry
    (diffshade.cache_shading, computed once): (function, arguments) for measure."""
    import jax
    import jax.numpy as jnp

    import diffshade as ds

    cache = ds.cache_shading(scene, ds.rasterize_scene(scene, settings), settings)

    def loss(material, scene, cache):
        moved = ds.replace(scene, material=material)
        return jnp.mean((ds.render_cached(moved, cache, settings) - target) ** 2)
    return jax.value_and_grad(loss), (scene.material, scene, cache)


def diffshade_worker(args):
    """All diffshade timings, and the mesh and Lambert render for the camera check."""
    import jax.numpy as jnp
    from raster import measure  # benchmarks/raster.py, beside this script

    import diffshade as ds

    scene = judged_scene(args.size, args.subdivisions)
    hard = ds.RenderSettings(raster="hard", shading="phong")
    soft = ds.RenderSettings(raster="soft", faces_per_pixel=SOFT_K, shading="phong")
    target = jnp.full((args.size, args.size, 4), 0.5, jnp.float32)
    render = lambda settings: (lambda s: ds.render(s, settings))
    timed = lambda fn, fn_args: measure(fn, fn_args, args.repeats, warmup=WARMUP)
    tasks = {"hard_forward": lambda: timed(render(hard), (scene,)),
             "hard_fb_material": lambda: timed(*mse_grad(scene, hard, target)),
             "soft_forward": lambda: timed(render(soft), (scene,)),
             "soft_fb_material": lambda: timed(*mse_grad(scene, soft, target)),
             "soft_fb_material_vertices": lambda: timed(*mse_grad(scene, soft, target, True)),
             "cached_step": lambda: cached_step(scene, hard, args.repeats),
             "soft_cached_step": lambda: timed(*soft_cached(scene, soft, target))}
    out = {key: tasks[key]() for key in args.only}
    lambert = ds.render(judged_scene(args.size, args.subdivisions, lambert=True), hard)
    np.savez(args.exchange, vertices=np.asarray(scene.mesh.vertices, np.float32),
             faces=np.asarray(scene.mesh.faces, np.uint32),
             normals=np.asarray(scene.mesh.normals, np.float32), diffshade=np.asarray(lambert))
    return {key: {"compile_s": r["compile_s"], "median_s": r["median_s"]}
            for key, r in out.items()}


def mitsuba_reflectance(albedo):
    """A Mitsuba reflectance: an RGB triple as is; a texture (texels [H, W, 3], linear,
    row 0 = v = 1) as a bitmap read as stored ("raw": no sRGB decoding), bilinear and
    repeating as diffshade's default texture (docs/textures.md)."""
    texels = np.asarray(albedo, np.float32)
    if texels.ndim == 1:
        return {"type": "rgb", "value": texels.tolist()}
    import mitsuba as mi
    return {"type": "bitmap", "bitmap": mi.Bitmap(texels), "raw": True,
            "filter_type": "bilinear", "wrap_mode": "repeat"}


def mitsuba_mesh(mi, mesh, albedo):
    """A mesh (positions, faces, normals and, where a texture is given, "uv": NumPy
    arrays) as a Mitsuba shape with a diffuse BSDF of reflectance `albedo` (an RGB triple
    or a texture: mitsuba_reflectance). Mitsuba reads a texture with v = 0 at the image's
    top row, diffshade (OBJ, OpenGL) at its bottom: the UVs go in as (u, 1 - v)."""
    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "diffuse",
                                  "reflectance": mitsuba_reflectance(albedo)})
    uv = mesh["uv"] if "uv" in mesh else None
    shape = mi.Mesh("sphere", len(mesh["vertices"]), len(mesh["faces"]), props=props,
                    has_vertex_normals=True, has_vertex_texcoords=uv is not None)
    params = mi.traverse(shape)
    params["vertex_positions"] = mi.Float(mesh["vertices"].ravel())
    params["vertex_normals"] = mi.Float(mesh["normals"].ravel())
    params["faces"] = mi.UInt32(mesh["faces"].ravel())
    if uv is not None:
        flipped = np.stack([uv[:, 0], 1.0 - uv[:, 1]], -1).astype(np.float32)
        params["vertex_texcoords"] = mi.Float(flipped.ravel())
    params.update()
    return shape


def mitsuba_scene(mi, mesh, size):
    """The judged scene in Mitsuba (see the module docstring)."""
    shape = mitsuba_mesh(mi, mesh, KD)
    film = {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"},
            "pixel_format": "rgba"}
    sensor = {"type": "perspective", "fov": FOV_Y, "fov_axis": "y", "near_clip": 0.1,
              "far_clip": 100.0, "film": film,
              "to_world": mi.ScalarTransform4f().look_at(origin=list(EYE), target=[0, 0, 0],
                                                         up=[0, 1, 0]),
              "sampler": {"type": "independent", "sample_count": SPP}}
    light = {"type": "directional", "direction": list(LIGHT_DIRECTION),
             "irradiance": {"type": "rgb", "value": float(np.pi)}}
    return mi.load_dict({"type": "scene", "integrator": {"type": "prb", "max_depth": 2},
                         "sensor": sensor, "light": light, "sphere": shape})


def mitsuba_worker(args):
    """Mitsuba's timings and image, or {'unavailable': why} when it cannot run."""
    try:
        import mitsuba as mi
        mi.set_variant(VARIANT)
        import drjit as dr
    except (ImportError, AttributeError) as err:
        return {"unavailable": f"{type(err).__name__}: {err}".splitlines()[0]}
    from common import time_call  # benchmarks/common.py, beside this script

    exchange = np.load(args.exchange)
    scene = mitsuba_scene(mi, exchange, args.size)
    params, key = mi.traverse(scene), "sphere.bsdf.reflectance.value"
    target = mi.TensorXf(np.full((args.size, args.size, 4), 0.5, np.float32))

    last = {}

    def forward():
        last["image"] = mi.render(scene, spp=SPP)
        dr.eval(last["image"])
        dr.sync_thread()

    def forward_backward():
        loss = dr.mean(dr.square(mi.render(scene, params, spp=SPP) - target), axis=None)
        dr.backward(loss)
        grad = dr.grad(params[key])
        dr.eval(loss, grad)
        dr.sync_thread()
        dr.set_grad(params[key], 0.0)
    out = {"llvm_version": ".".join(map(str, dr.detail.llvm_version())),
           "mitsuba": mi.__version__, "drjit": dr.__version__}
    compile_s, median_s, _ = time_call(forward, repeats=args.repeats, warmup=WARMUP - 1)
    out["forward"] = {"compile_s": compile_s, "median_s": median_s}
    np.save(args.exchange.replace(".npz", "_mitsuba.npy"), np.asarray(last["image"]))
    dr.enable_grad(params[key])
    params.update()
    compile_s, median_s, _ = time_call(forward_backward, repeats=args.repeats,
                                       warmup=WARMUP - 1)
    out["forward_backward"] = {"compile_s": compile_s, "median_s": median_s}
    return out


def camera_check(diffshade_image, mitsuba_image):
    """(IoU of the coverage masks, largest |colour difference| inside both masks, eroded
    by 2 pixels so that no pixel cut by the outline counts)."""
    from fitting.model.cache import erode

    ours, theirs = diffshade_image[..., 3] > 0.5, mitsuba_image[..., 3] > 0.5
    iou = (ours & theirs).sum() / max(int((ours | theirs).sum()), 1)
    inside = erode(ours & theirs, 2)
    diff = np.abs(diffshade_image[..., :3] - mitsuba_image[..., :3])[inside]
    return float(iou), float(diff.max()) if diff.size else float("nan")


def spawn(worker, args, exchange):
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", worker, "--exchange",
           exchange, "--size", str(args.size), "--subdivisions", str(args.subdivisions),
           "--repeats", str(args.repeats), "--only", ",".join(args.only)]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [ROOT] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    if worker == "mitsuba":
        # Dr.Jit keeps compiled kernels in ~/.drjit: a fresh home makes its first call a
        # cold compile, as diffshade's is (JAX keeps no compilation cache on disk here)
        env["HOME"] = os.path.join(os.path.dirname(exchange), "mitsuba-home")
        os.makedirs(env["HOME"], exist_ok=True)
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env=env)
    if proc.returncode != 0:
        return {"error": proc.stderr[-3000:], "why": f"its process exited with status "
                f"{proc.returncode}: {error_line(proc.stderr)}"}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def error_line(stderr):
    """The last line of stderr that names an error (else its last line)."""
    lines = [line.strip() for line in stderr.splitlines() if line.strip()] or ["no output"]
    named = [line for line in lines if "error" in line.lower()]
    return (named or lines)[-1][:300]


def pooled(rounds):
    """One result from several rounds: compile time of the first, median of the medians."""
    first = rounds[0]
    return {key: ({"compile_s": first[key]["compile_s"],
                   "median_s": statistics.median(r[key]["median_s"] for r in rounds),
                   "round_medians_s": [r[key]["median_s"] for r in rounds]}
                  if isinstance(first[key], dict) else first[key]) for key in first}


def round_ratios(mine, peer):
    """The lowest and highest speed ratio of one round (round i of each engine: their
    processes alternate, so a round's two figures were measured one after the other),
    from the results' round_medians_s; None where either has no rounds."""
    pairs = list(zip(peer.get("round_medians_s", ()), mine.get("round_medians_s", ()),
                     strict=True))
    if not pairs:
        return None
    ratios = [theirs / ours for theirs, ours in pairs]
    return min(ratios), max(ratios)


def table(ours, theirs):
    """The markdown ratio table (Mitsuba's time over diffshade's), with the spread of the
    rounds' ratios (round_ratios)."""
    lines = ["| quantity | diffshade | Mitsuba | speed ratio | ratio per round |",
             "|---|---|---|---|---|"]
    for key, label, peer in ROWS:
        if key not in ours:
            continue
        mine = ours[key]["median_s"]
        cell, ratio, spread = "—", "—", "—"
        if theirs is not None and peer is not None:
            cell = f"{theirs[peer]['median_s'] * 1e3:.1f} ms"
            ratio = f"{theirs[peer]['median_s'] / mine:.2f}x"
            lowest_highest = round_ratios(ours[key], theirs[peer])
            if lowest_highest is not None:
                spread = "{:.2f}–{:.2f}x".format(*lowest_highest)
        lines.append(f"| {label} | {mine * 1e3:.1f} ms | {cell} | {ratio} | {spread} |")
    return "\n".join(lines)


def compile_line(name, result):
    return name + ": compile " + ", ".join(f"{k} {v['compile_s']:.1f} s" for k, v in
                                           result.items() if isinstance(v, dict))


def run_rounds(args, exchange):
    """(diffshade result, Mitsuba result or None, why Mitsuba did not run or None)."""
    ours, theirs, why = [], [], None
    for _ in range(args.rounds):
        ours.append(spawn("diffshade", args, exchange))
        if "error" in ours[-1]:
            raise SystemExit(f"diffshade worker failed:\n{ours[-1]['error']}")
        if why is None:
            result = spawn("mitsuba", args, exchange)
            why = result.get("unavailable") or result.get("why")
            if why is None:
                theirs.append(result)
    return pooled(ours), pooled(theirs) if theirs else None, why


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256, help="image width and height")
    parser.add_argument("--subdivisions", type=int, default=4, help="icosphere subdivisions")
    parser.add_argument("--repeats", type=int, default=20, help="timed calls per figure")
    parser.add_argument("--rounds", type=int, default=1,
                        help="alternate the two engines' processes this many times")
    parser.add_argument("--only", type=lambda text: text.split(","), default=KEYS,
                        help=f"comma-separated subset of {','.join(KEYS)}")
    parser.add_argument("--out", default=os.path.join(ROOT, "benchmarks/results/peers.json"))
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--exchange", help=argparse.SUPPRESS)
    args = parser.parse_args()
    unknown = sorted(set(args.only) - set(KEYS))
    if unknown:
        parser.error(f"--only: got {unknown}; expected names from {KEYS}")
    if args.worker:
        worker = diffshade_worker if args.worker == "diffshade" else mitsuba_worker
        print(json.dumps(worker(args)))
        return
    faces = 20 * 4 ** args.subdivisions
    print(f"judged scene: icosphere, {faces} faces, {args.size}^2, one directional light; "
          f"soft K = {SOFT_K}; Mitsuba {VARIANT}, {SPP} spp; median of {args.repeats} "
          f"calls, {args.rounds} round(s); loadavg {os.getloadavg()[0]:.1f}", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        exchange = os.path.join(tmp, "exchange.npz")
        ours, theirs, why = run_rounds(args, exchange)
        images = np.load(exchange)["diffshade"], None
        if theirs is not None:
            images = images[0], np.load(exchange.replace(".npz", "_mitsuba.npy"))
    print(table(ours, theirs))
    print(compile_line("diffshade", ours))
    results = {"diffshade": ours, "mitsuba": theirs, "size": args.size, "faces": faces,
               "repeats": args.repeats, "rounds": args.rounds, "cpus": os.cpu_count(),
               "loadavg": os.getloadavg()}
    if theirs is None:
        print(f"Mitsuba 3 did not run ({why}); "
              "pip install '.[peers]' and see docs/performance.md")
    else:
        iou, max_diff = camera_check(*images)
        results["camera_check"] = {"mask_iou": iou, "max_interior_colour_diff": max_diff}
        print(compile_line("Mitsuba", theirs))
        print(f"Mitsuba {theirs['mitsuba']} (Dr.Jit {theirs['drjit']}, LLVM "
              f"{theirs['llvm_version']}); camera check: mask IoU {iou:.4f}, largest colour "
              f"difference inside both masks {max_diff:.4f} (Lambert term)")
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

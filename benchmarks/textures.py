"""Cost of a kd texture: the judged scene rendered textured against untextured; and the
time to recover a kd map in closed form.

    python benchmarks/textures.py                 # both parts, as the issue sets them
    python benchmarks/textures.py --part render --size 128 --texels 64
    python benchmarks/textures.py --part fit      # a 256^2 kd map from 8 views at 256^2

render: the judged scene (benchmarks/peers.py: 5,120-face icosphere, one directional
light, specular) in soft raster with K = 8, Phong shading, at --size^2: untextured
(icosphere(4)) against the same sphere with UVs (icosphere(4, uv=True)) and a random kd
texture of --texels^2. Forward (render) and forward + backward (value_and_grad of an MSE
with respect to the material: the texture's texels, or the uniform kd) are each compiled
apart, warmed up until their times settle, then run --rounds rounds in an order shuffled
per round, so that a change in the machine's load hits both alike (common.time_settings);
the medians of wall and CPU time (time.process_time, all threads) and the textured /
untextured ratios are printed. The issue's target: a ratio <= 1.2 for both passes.

fit: a synthetic dataset (data_synth.make_dataset, icosphere, the procedural kd of
--texels^2 texels, --views views at --size^2, float targets) and fitting.texture_fit's
closed-form solve, timed cold (trace + compile + solve) and then warm (--fit-runs more
calls, the median); printed with the unknowns' count, the CG iterations (on the renders,
and on the probed stencil that gives their start) and the recovered map's PSNR against
the truth over the texels at least two views see. The issue's target: <= 10 s warm for a
256^2 map from 8 views at 256^2.

Both write benchmarks/results/textures.json ({"render": ..., "fit": ...}; a part not run
keeps what the file had), with the 1-minute load average before and after each part:
timings need an idle machine.
"""

import argparse
import json
import os
import statistics
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import time_settings, timed_cpu, write_results  # noqa: E402
from peers import SOFT_K, judged_scene  # noqa: E402

import diffshade as ds  # noqa: E402


def textured(scene, texels):
    """The judged scene on a sphere with UVs, its kd a random texture of texels^2."""
    rng = np.random.default_rng(0)
    kd = ds.texture(rng.uniform(0.2, 0.8, (texels, texels, 3)).astype(np.float32))
    return ds.replace(scene, mesh=ds.icosphere(4, uv=True),
                      material=ds.replace(scene.material, kd=kd))


def calls(scene, settings, target):
    """{'forward', 'forward+backward'}: zero-argument timed functions of the scene."""
    forward = jax.jit(lambda s: ds.render(s, settings))

    def loss(material, s):
        return jnp.mean((ds.render(ds.replace(s, material=material), settings) - target) ** 2)
    both = jax.jit(jax.value_and_grad(loss))
    return {"forward": lambda: forward(scene), "forward+backward": lambda: both(scene.material,
                                                                                  scene)}


def render_benchmark(args):
    """The render part (module docstring): prints and returns its record."""
    load_before = os.getloadavg()[0]
    settings = ds.RenderSettings(raster="soft", faces_per_pixel=SOFT_K)
    plain = judged_scene(args.size, 4)
    target = jnp.full((args.size, args.size, 4), 0.5, jnp.float32)
    scenes = {"untextured": plain, "textured": textured(plain, args.texels)}
    fns = {f"{name} {kind}": fn for name, scene in scenes.items()
           for kind, fn in calls(scene, settings, target).items()}
    stats = time_settings(fns, rounds=args.rounds)
    rows = []
    for kind in ("forward", "forward+backward"):
        base, tex = stats[f"untextured {kind}"], stats[f"textured {kind}"]
        rows.append({"pass": kind, "untextured_ms": base["median_ms"],
                     "textured_ms": tex["median_ms"], "ratio": tex["median_ms"] / base["median_ms"],
                     "untextured_cpu_ms": base["cpu_median_ms"],
                     "textured_cpu_ms": tex["cpu_median_ms"],
                     "cpu_ratio": tex["cpu_median_ms"] / base["cpu_median_ms"]})
        print(f"{kind:>17}: untextured {base['median_ms']:7.1f} ms (CPU "
              f"{base['cpu_median_ms']:7.1f})  textured {tex['median_ms']:7.1f} ms (CPU "
              f"{tex['cpu_median_ms']:7.1f})  ratio "
              f"{rows[-1]['ratio']:.2f} wall, {rows[-1]['cpu_ratio']:.2f} CPU (target <= 1.2)")
    print(f"{args.size}^2, soft K = {SOFT_K}, {args.texels}^2 kd texture, "
          f"{int(plain.mesh.faces.shape[0])} faces; loadavg {load_before:.1f} -> "
          f"{os.getloadavg()[0]:.1f}")
    return {"size": args.size, "texels": args.texels, "faces_per_pixel": SOFT_K,
            "faces": int(plain.mesh.faces.shape[0]), "rounds": args.rounds, "rows": rows,
            "stats": stats, "load_before": load_before, "load_after": os.getloadavg()[0]}


def fit_benchmark(args):
    """The fit part (module docstring): prints and returns its record."""
    from data_synth import make_dataset
    from fitting.texture_fit import fit_texture

    load_before = os.getloadavg()[0]
    data = make_dataset("icosphere", n_views=args.views, n_lights=1, size=args.size,
                        texture=args.texels, seed=0)
    solutions = []

    def solve():
        solutions.append(fit_texture(data, args.texels))
        return solutions[-1].texels
    times = [timed_cpu(solve) for _ in range(1 + args.fit_runs)]
    solution = solutions[-1]
    truth, texels = np.asarray(data.truth.kd.texels), np.asarray(solution.texels)
    twice = np.asarray(solution.coverage) >= 2
    mse = float(np.mean((texels[twice] - truth[twice]) ** 2))
    warm = times[1:]
    row = {"texels": args.texels, "views": args.views, "size": args.size,
           "unknowns": 3 * args.texels ** 2, "iterations": solution.iterations,
           "stencil_iterations": solution.stencil_iterations,
           "relative_residual": solution.residual, "cold_s": times[0][0],
           "cold_cpu_s": times[0][1], "warm_s": statistics.median(w for w, _ in warm),
           "warm_cpu_s": statistics.median(c for _, c in warm),
           "warm_runs_s": [round(w, 3) for w, _ in warm], "seen_twice": int(twice.sum()),
           "psnr_db": 10 * np.log10(1.0 / max(mse, 1e-20)), "load_before": load_before,
           "load_after": os.getloadavg()[0]}
    print(f"kd map {args.texels}^2 ({row['unknowns']} unknowns) from {args.views} views at "
          f"{args.size}^2: cold {row['cold_s']:.1f} s, warm {row['warm_s']:.2f} s (CPU "
          f"{row['warm_cpu_s']:.2f} s; target <= 10 s); {solution.iterations} CG iterations "
          f"on the renders after {solution.stencil_iterations} on the probed stencil "
          f"(relative residual {solution.residual:.1e}); PSNR {row['psnr_db']:.1f} dB over "
          f"the {row['seen_twice']} texels seen twice; loadavg {load_before:.1f} -> "
          f"{row['load_after']:.1f}")
    return row


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("render", "fit", "both"), default="both")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--texels", type=int, default=256, help="texture side (default 256)")
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--views", type=int, default=8, help="fit: views (default 8)")
    parser.add_argument("--fit-runs", type=int, default=3, help="fit: warm calls (default 3)")
    parser.add_argument("--out", default="benchmarks/results/textures.json")
    args = parser.parse_args(argv)
    record = {}
    if os.path.isfile(args.out):
        with open(args.out) as file:
            record = {key: value for key, value in json.load(file).items()
                      if key in ("render", "fit")}
    if args.part in ("render", "both"):
        record["render"] = render_benchmark(args)
    if args.part in ("fit", "both"):
        record["fit"] = fit_benchmark(args)
    write_results(args.out, {"benchmark": "textures", **record})


if __name__ == "__main__":
    main()

"""Cost of a kd texture: the judged scene rendered textured against untextured; and the
time to recover a kd map in closed form.

    python benchmarks/textures.py                 # 256^2, soft, K = 8, a 256^2 kd texture
    python benchmarks/textures.py --size 128 --texels 64
    python benchmarks/textures.py --fit           # a 256^2 kd map from 8 views at 256^2

The judged scene (benchmarks/peers.py: 5,120-face icosphere, one directional light,
specular) in soft raster with K = 8, Phong shading: untextured (icosphere(4)) against the
same sphere with UVs (icosphere(4, uv=True)) and a kd texture. Forward (render) and
forward + backward (value_and_grad of an MSE with respect to the material: the texture's
texels, or the uniform kd) are timed with common.time_settings (compile apart, warm-up
until settled, shuffled rounds), and the textured / untextured ratios are printed; the
issue's target is <= 1.2 for both. Timings need an idle machine.

--fit: a synthetic dataset (data_synth.make_dataset, icosphere, the procedural kd of
--texels^2 texels, --views views at --size^2, float targets) and fitting.texture_fit's
closed-form solve, timed cold (trace + compile + solve) and warm (a second call); printed
with the unknowns' count, the CG iterations and the recovered map's PSNR against the
truth over the texels at least two views see. The issue's target: <= 10 s warm for a
256^2 map from 8 views at 256^2.
"""

import argparse
import os
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import time_settings, write_results  # noqa: E402
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


def fit_benchmark(args):
    """--fit (module docstring): prints and returns the row."""
    import time

    from data_synth import make_dataset
    from fitting.texture_fit import fit_texture

    data = make_dataset("icosphere", n_views=args.views, n_lights=1, size=args.size,
                        texture=args.texels, seed=0)
    times = []
    for _ in range(2):
        start = time.perf_counter()
        solution = fit_texture(data, args.texels)
        jax.block_until_ready(solution.texels)
        times.append(time.perf_counter() - start)
    truth, texels = np.asarray(data.truth.kd.texels), np.asarray(solution.texels)
    twice = np.asarray(solution.coverage) >= 2
    mse = float(np.mean((texels[twice] - truth[twice]) ** 2))
    row = {"texels": args.texels, "views": args.views, "size": args.size,
           "unknowns": 3 * args.texels ** 2, "iterations": solution.iterations,
           "cold_s": times[0], "warm_s": times[1], "seen_twice": int(twice.sum()),
           "psnr_db": 10 * np.log10(1.0 / max(mse, 1e-20))}
    print(f"kd map {args.texels}^2 ({row['unknowns']} unknowns) from {args.views} views at "
          f"{args.size}^2: cold {times[0]:.1f} s, warm {times[1]:.1f} s (target <= 10 s), "
          f"{solution.iterations} CG iterations; PSNR {row['psnr_db']:.1f} dB over the "
          f"{row['seen_twice']} texels seen twice; loadavg {os.getloadavg()[0]:.1f}")
    return row


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--texels", type=int, default=256, help="texture side (default 256)")
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--fit", action="store_true", help="time the closed-form kd fit")
    parser.add_argument("--views", type=int, default=8, help="--fit: views (default 8)")
    parser.add_argument("--out", default="benchmarks/results/textures.json")
    args = parser.parse_args(argv)
    if args.fit:
        row = fit_benchmark(args)
        write_results(args.out.replace(".json", "_fit.json"), {"benchmark": "texture fit",
                                                               "rows": [row]})
        return
    settings = ds.RenderSettings(raster="soft", faces_per_pixel=SOFT_K)
    plain = judged_scene(args.size, 4)
    target = jnp.full((args.size, args.size, 4), 0.5, jnp.float32)
    scenes = {"untextured": plain, "textured": textured(plain, args.texels)}
    timed = {f"{name} {kind}": fn for name, scene in scenes.items()
             for kind, fn in calls(scene, settings, target).items()}
    stats = time_settings(timed, rounds=args.rounds)
    rows = []
    for kind in ("forward", "forward+backward"):
        base, tex = stats[f"untextured {kind}"], stats[f"textured {kind}"]
        rows.append({"pass": kind, "untextured_ms": base["median_ms"],
                     "textured_ms": tex["median_ms"],
                     "ratio": tex["median_ms"] / base["median_ms"]})
        print(f"{kind:>17}: untextured {base['median_ms']:8.1f} ms  textured "
              f"{tex['median_ms']:8.1f} ms  ratio {rows[-1]['ratio']:.2f} (target <= 1.2)")
    print(f"{args.size}^2, soft K = {SOFT_K}, {args.texels}^2 kd texture, "
          f"{int(plain.mesh.faces.shape[0])} faces; loadavg {os.getloadavg()[0]:.1f}")
    write_results(args.out, {"benchmark": "textures", "size": args.size,
                             "texels": args.texels, "rows": rows, "stats": stats})


if __name__ == "__main__":
    main()

"""Cost of a kd texture: the judged scene rendered textured against untextured.

    python benchmarks/textures.py                 # 256^2, soft, K = 8, a 256^2 kd texture
    python benchmarks/textures.py --size 128 --texels 64

The judged scene (benchmarks/peers.py: 5,120-face icosphere, one directional light,
specular) in soft raster with K = 8, Phong shading: untextured (icosphere(4)) against the
same sphere with UVs (icosphere(4, uv=True)) and a kd texture. Forward (render) and
forward + backward (value_and_grad of an MSE with respect to the material: the texture's
texels, or the uniform kd) are timed with common.time_settings (compile apart, warm-up
until settled, shuffled rounds), and the textured / untextured ratios are printed; the
issue's target is <= 1.2 for both. Timings need an idle machine.
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


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--texels", type=int, default=256, help="texture side (default 256)")
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--out", default="benchmarks/results/textures.json")
    args = parser.parse_args(argv)
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

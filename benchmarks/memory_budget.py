"""The memory budget's estimate against a render's measured peak memory (docs/cli.md,
"Sizes and memory"): the estimate must stay above the peak, by a margin that is not so
large that renders which fit are refused.

    PYTHONPATH=. python benchmarks/memory_budget.py [--quick]

Each configuration renders once in a fresh process (a subdivision-3 icosphere lit by a
point light, with or without its shadow maps); the peak is the growth of the process's
maximum resident set during that render (getrusage), so imports and the mesh are not
counted, compilation is. Rows: the configuration, diffshade.pipeline.cost.render_cost's
bytes, the peak, and their ratio (above 1: the estimate bounds the peak). Run it on an
otherwise idle machine: other processes do not change a process's own peak, but swapping
does.
"""

import argparse
import json
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import print_table  # noqa: E402

#: (side, raster, faces_per_pixel, kernels, shadow map side or 0)
CONFIGS = [(1024, "hard", 1, "auto", 0), (2048, "hard", 1, "auto", 0),
           (2048, "hard", 1, "jax", 0), (1024, "soft", 8, "auto", 0),
           (1024, "soft", 8, "jax", 0), (64, "hard", 1, "auto", 1024),
           (64, "hard", 1, "jax", 1024)]
QUICK = [(512, "hard", 1, "auto", 0), (256, "soft", 8, "jax", 0), (64, "hard", 1, "auto", 256)]

CHILD = """
import json, resource, sys
import numpy as np
import diffshade as ds
from diffshade.pipeline.cost import render_cost
side, raster, k, kernels, shadow = json.loads(sys.argv[1])
camera = ds.look_at((0, 0, 3), (0, 0, 0), width=side, height=side)
light = ds.point_light((2, 2, 4), 0.8, shadows=shadow > 0)
scene = ds.make_scene(ds.icosphere(3), camera, [light], ds.material(ks=0.5, shininess=50.0))
settings = ds.RenderSettings(raster=raster, faces_per_pixel=k, kernels=kernels,
                             shadow_map_size=max(shadow, 1))
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
np.asarray(ds.render(scene, settings))
after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"estimate": render_cost(scene, settings).bytes,
                  "peak": (after - before) * 1024}))
"""


def measure(config):
    """{config fields, estimate, peak, ratio} of one render in a fresh process."""
    done = subprocess.run([sys.executable, "-c", CHILD, json.dumps(config)],
                          capture_output=True, text=True, check=True)
    found = json.loads(done.stdout.strip().splitlines()[-1])
    side, raster, k, kernels, shadow = config
    return {"image": f"{side}x{side}", "raster": raster, "K": k, "kernels": kernels,
            "map": shadow or None, "estimate_mb": found["estimate"] / 1e6,
            "peak_mb": found["peak"] / 1e6, "ratio": found["estimate"] / max(found["peak"], 1)}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="three small configurations")
    args = parser.parse_args(argv)
    rows = [measure(config) for config in (QUICK if args.quick else CONFIGS)]
    print_table(rows, [("image", "image", "{}"), ("raster", "raster", "{}"), ("K", "K", "{}"),
                       ("kernels", "kernels", "{}"), ("map", "shadow map", "{}"),
                       ("estimate_mb", "estimate MB", "{:.0f}"), ("peak_mb", "peak MB", "{:.0f}"),
                       ("ratio", "estimate / peak", "{:.2f}")])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

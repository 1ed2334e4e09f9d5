"""Forward render time: icosphere subdivisions x resolutions x shading modes (hard raster).

    python benchmarks/forward.py            # full grid (subdivisions 1-5, 128/256/512 px)
    python benchmarks/forward.py --quick    # a few configurations

Prints compile time (first call: trace + compile + run) and the steady-state median over
repeated calls after warm-up, and writes JSON (default benchmarks/results/forward.json).
"""

import argparse
import sys
from pathlib import Path

import jax

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import print_table, time_call, write_results  # noqa: E402

import diffshade as ds  # noqa: E402

MODES = ("phong", "gouraud", "flat", "flat_last")


def make_scene(subdivisions, size):
    return ds.make_scene(
        ds.icosphere(subdivisions),
        ds.look_at((0.0, 0.0, 3.0), (0.0, 0.0, 0.0), width=size, height=size, fov_y=45.0),
        [ds.directional_light((-1.0, -1.0, -1.0)),
         ds.point_light((2.0, 2.0, 2.0), 0.5, attenuation=(1.0, 0.1, 0.01))],
        ds.material(ka=0.2, kd=(0.7, 0.3, 0.2), ks=0.5, shininess=40.0))


def measure(subdivisions, size, mode, repeats):
    scene = make_scene(subdivisions, size)
    settings = ds.RenderSettings(shading=mode)
    fn = jax.jit(lambda s: ds.render(s, settings))
    compile_s, median_s, _ = time_call(fn, scene, repeats=repeats)
    faces = int(scene.mesh.faces.shape[0])
    return {"subdivisions": subdivisions, "faces": faces, "size": size, "shading": mode,
            "compile_s": compile_s, "median_ms": 1e3 * median_s}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a few configurations only")
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--out", default="benchmarks/results/forward.json")
    args = parser.parse_args(argv)
    subdivisions, sizes = ((2, 4), (128, 256)) if args.quick else ((1, 2, 3, 4, 5), (128, 256, 512))
    rows = [measure(s, n, m, args.repeats) for s in subdivisions for n in sizes for m in MODES]
    print_table(rows, [("subdivisions", "subdiv", "{}"), ("faces", "faces", "{}"),
                       ("size", "size", "{}"), ("shading", "shading", "{}"),
                       ("compile_s", "compile s", "{:.2f}"), ("median_ms", "median ms", "{:.1f}")])
    write_results(args.out, {"benchmark": "forward", "rows": rows})


if __name__ == "__main__":
    main()

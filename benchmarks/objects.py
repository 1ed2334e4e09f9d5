"""What several objects cost: one mesh drawn as one object against the same mesh split into
O objects, each with its own material (the per-sample material gather).

    python benchmarks/objects.py [--size 128] [--repeats 10]

Geometry is identical in every row (O icospheres of subdivision 3 in a row, joined into
one mesh): only the material differs, one Material or O stacked. Prints compile time
(first call) and the median of the steady state for the forward render and for
forward + gradient with respect to the material, hard and soft raster; writes JSON
(default benchmarks/results/objects.json).
"""

import argparse
import sys
from pathlib import Path

import jax
import jax.numpy as jnp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import print_table, time_call, write_results  # noqa: E402

import diffshade as ds  # noqa: E402


def scenes(count, size):
    """(the objects' scene, the same joined mesh as one object with one material)."""
    objects = [ds.scene_object(ds.icosphere(3, 0.4),
                               ds.material(kd=(0.2 + 0.6 * i / count, 0.4, 0.5), ks=0.4,
                                           shininess=20.0),
                               transform=ds.model_matrix((0.9 * i - 0.45 * (count - 1), 0, 0)))
               for i in range(count)]
    cam = ds.look_at((0.0, 0.0, 2.5 + count), (0.0, 0.0, 0.0), width=size, height=size)
    lights = [ds.directional_light((-1.0, -1.0, -1.0)), ds.point_light((2.0, 2.0, 2.0), 0.5)]
    several = ds.make_scene(objects=objects, camera=cam, lights=lights)
    one = ds.make_scene(several.mesh, cam, lights, objects[0].material)
    return several, one


def measure(label, scene, raster, repeats):
    settings = ds.RenderSettings(raster=raster)
    forward = jax.jit(lambda s: ds.render(s, settings))
    loss = lambda m, s: jnp.sum(ds.render(ds.replace(s, material=m), settings))
    backward = jax.jit(jax.value_and_grad(loss))
    compile_f, fwd, _ = time_call(forward, scene, repeats=repeats)
    compile_b, bwd, _ = time_call(backward, scene.material, scene, repeats=repeats)
    return {"scene": label, "faces": int(scene.mesh.faces.shape[0]), "raster": raster,
            "compile_fwd_s": compile_f, "fwd_ms": 1e3 * fwd, "compile_bwd_s": compile_b,
            "fwd_bwd_ms": 1e3 * bwd}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--objects", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--out", default="benchmarks/results/objects.json")
    args = parser.parse_args(argv)
    several, one = scenes(args.objects, args.size)
    rows = [measure(label, scene, raster, args.repeats)
            for raster in ("hard", "soft")
            for label, scene in (("1 object", one), (f"{args.objects} objects", several))]
    print_table(rows, [("scene", "scene", "{}"), ("faces", "faces", "{}"),
                       ("raster", "raster", "{}"), ("compile_fwd_s", "compile fwd s", "{:.2f}"),
                       ("fwd_ms", "fwd ms", "{:.1f}"),
                       ("compile_bwd_s", "compile fwd+bwd s", "{:.2f}"),
                       ("fwd_bwd_ms", "fwd+bwd ms", "{:.1f}")])
    write_results(args.out, {"benchmark": "objects", "size": args.size, "rows": rows})


if __name__ == "__main__":
    main()

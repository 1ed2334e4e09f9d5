"""Shadow-map size against shadow-edge error against time (the shadows section of the
accuracy-versus-time study, docs/accuracy-vs-time.md).

    python benchmarks/accuracy_shadows.py            # the table (a few minutes)
    python benchmarks/accuracy_shadows.py --quick    # seconds-long subset

Scene: diffshade.analytic.SphereOverPlane (an icosphere of subdivision 3 over a floor of
8 x 8 squares), one white point light with shadows, ks = 0, hard raster, Phong shading.
Reference: the exact hard shadow per pixel centre (SphereOverPlane.shadow, NumPy
ray/sphere tests in float64). A floor pixel counts as shadowed in the render when its
colour equals the ambient-only colour ka * (global + light ambient) to 1e-5.

Columns: map (texels a side of each of the cube's six maps); wrong px (floor pixels whose
shadow state differs from the reference); edge px (the reference shadow's boundary
pixels, 4-neighbour); edge error px = wrong / edge (the mean displacement of the
rendered shadow edge, in image pixels); fwd ms (steady-state median render time after
warm-up, 15 runs by default); compile s (first call). The last row renders without
shadows: the cost of the shadow pass is the difference.
"""

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import print_table, time_call, write_results  # noqa: E402

import diffshade as ds  # noqa: E402
from diffshade.analytic import SphereOverPlane  # noqa: E402
from diffshade.pipeline.rendering import render  # noqa: E402

GEOMETRY = SphereOverPlane()
LIGHT = (-1.0, 1.8, -1.0)
KA, GLOBAL, LIGHT_AMBIENT = 0.3, 0.2, 0.1


def scene(size, shadows=True):
    camera = ds.look_at((0.0, 4.5, 3.2), (0.0, -1.0, 0.5), width=size, height=size,
                        fov_y=40.0)
    light = ds.point_light(LIGHT, 1.0, ambient=LIGHT_AMBIENT, shadows=shadows)
    return ds.make_scene(GEOMETRY.mesh(3, 8), camera, [light],
                         ds.material(ka=KA, kd=0.6, ks=None), global_ambient=GLOBAL)


def boundary(mask):
    """Pixels of `mask` with a 4-neighbour outside it."""
    m = np.pad(mask, 1, mode="edge")
    inner = m[:-2, 1:-1] & m[2:, 1:-1] & m[1:-1, :-2] & m[1:-1, 2:]
    return mask & ~inner


def edge_error(image, camera):
    """(wrong floor pixels, reference edge pixels) of a render against the exact shadow."""
    on_floor, shadow = GEOMETRY.shadow(camera, ("point", LIGHT))
    dark = np.abs(np.asarray(image, np.float64)[..., 0] - KA * (GLOBAL + LIGHT_AMBIENT)) < 1e-5
    wrong = on_floor & (dark != shadow)
    return int(wrong.sum()), int(boundary(shadow).sum())


def row(size, map_size, repeats):
    shadows = map_size is not None
    settings = ds.RenderSettings(shadow_map_size=map_size or 1)
    s = scene(size, shadows)
    compile_s, fwd_s, _ = time_call(render, s, settings, repeats=repeats)
    out = {"size": size, "map": map_size or "off", "compile_s": compile_s,
           "fwd_ms": 1e3 * fwd_s}
    if shadows:
        wrong, edge = edge_error(render(s, settings), s.camera)
        out |= {"wrong_px": wrong, "edge_px": edge, "edge_error_px": wrong / edge}
    return out


COLUMNS = [("size", "image", "{}"), ("map", "map", "{}"), ("wrong_px", "wrong px", "{}"),
           ("edge_px", "edge px", "{}"), ("edge_error", "edge error px", "{}"),
           ("fwd_ms", "fwd ms", "{:.1f}"), ("compile_s", "compile s", "{:.1f}")]


def printable(r):
    """The row with '-' for the error columns of the row without shadows."""
    error = r.get("edge_error_px")
    return {"wrong_px": "-", "edge_px": "-", **r,
            "edge_error": "-" if error is None else f"{error:.3f}"}


def run(quick=False, repeats=15):
    size, maps = (64, (32, 64)) if quick else (128, (32, 64, 128, 256, 512))
    repeats = 2 if quick else repeats
    # the row without shadows goes last: the first rows of a process measured several
    # times slower here than the same row after a shadowed one
    return [row(size, m, repeats) for m in maps] + [row(size, None, repeats)]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a seconds-long subset")
    parser.add_argument("--out", default="benchmarks/results/accuracy_shadows.json")
    parser.add_argument("--repeats", type=int, default=15, help="timed runs per row")
    args = parser.parse_args(argv)
    rows = run(args.quick, args.repeats)
    print("== shadows: shadow-map size vs the exact shadow of a sphere over a floor")
    print_table([printable(r) for r in rows], COLUMNS)
    write_results(args.out, {"shadows": rows})
    return rows


if __name__ == "__main__":
    main()

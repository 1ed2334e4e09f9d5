"""Shadow-map size against shadow-edge error against time (the shadows section of the
accuracy-versus-time study, docs/accuracy-vs-time.md).

    python benchmarks/accuracy_shadows.py            # the table (a few minutes)
    python benchmarks/accuracy_shadows.py --quick    # seconds-long subset
    python benchmarks/accuracy_study.py --docs       # the whole study, and the doc's tables

Scene: diffshade.analytic.SphereOverPlane (an icosphere of subdivision 3 over a floor of
8 x 8 squares), one white point light with shadows, ks = 0, hard raster, Phong shading.
Reference: the exact hard shadow per pixel centre (SphereOverPlane.shadow, NumPy
ray/sphere tests in float64). A floor pixel counts as shadowed in the render when its
colour equals the ambient-only colour ka * (global + light ambient) to 1e-5.

Columns: map (texels a side of each of the cube's six maps); wrong px (floor pixels whose
shadow state differs from the reference); edge px (the reference shadow's boundary
pixels, 4-neighbour); edge error px = wrong / edge (the mean displacement of the
rendered shadow edge, in image pixels); fwd ms and its spread (common.time_settings: all
rows of the table timed against each other in one interleaved run, each warmed up until
its time settles; median and quartiles); compile s (first call). The last row renders
without shadows: the cost of the shadow pass is the difference.
"""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import study_main, time_settings, timing_columns, with_spreads  # noqa: E402

import diffshade as ds  # noqa: E402
from diffshade.analytic import SphereOverPlane  # noqa: E402
from diffshade.pipeline.rendering import render  # noqa: E402

NAME = "shadows"
OUT = "benchmarks/results/accuracy_shadows.json"
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


def config(size, map_size):
    """(scene, settings) of one row; map_size None renders without shadows."""
    return (scene(size, map_size is not None),
            ds.RenderSettings(shadow_map_size=map_size or 1))


def calls(size, maps):
    """{map size or "off": zero-argument forward render} for common.time_settings."""
    configs = {m or "off": config(size, m) for m in maps}
    return {m: (lambda c=c: render(*c)) for m, c in configs.items()}


def row(size, map_size, stats):
    s, settings = config(size, map_size)
    out = {"size": size, "map": map_size or "off",
           **timing_columns(stats[map_size or "off"], "fwd", "compile_s")}
    if map_size is not None:
        wrong, edge = edge_error(render(s, settings), s.camera)
        out |= {"wrong_px": wrong, "edge_px": edge, "edge_error_px": wrong / edge}
    return out


COLUMNS = [("size", "image", "{}"), ("map", "map", "{}"), ("wrong_px", "wrong px", "{}"),
           ("edge_px", "edge px", "{}"), ("edge_error", "edge error px", "{}"),
           ("fwd_ms", "fwd ms", "{:.1f}"), ("fwd_spread", "fwd spread ms", "{}"),
           ("compile_s", "compile s", "{:.1f}")]


def printable(r):
    """The row with '–' for the error columns of the row without shadows."""
    error = r.get("edge_error_px")
    return {"wrong_px": "\u2013", "edge_px": "\u2013", **r,
            "edge_error": "\u2013" if error is None else f"{error:.3f}"}


def run(quick=False):
    """{"shadows": rows}: every map size and a render without shadows, timed together."""
    size, maps = (64, (32, 64)) if quick else (128, (32, 64, 128, 256, 512))
    timing = {"rounds": 3, "max_warmup": 6} if quick else {"rounds": 15}
    stats = time_settings(calls(size, maps + (None,)), **timing)
    return {"shadows": [row(size, m, stats) for m in maps + (None,)]}


def tables(results):
    from accuracy_tables import table
    return table(with_spreads([printable(r) for r in results["shadows"]]), COLUMNS)


def plots(results, folder):
    from accuracy_plots import draw_shadows
    return draw_shadows(results, folder)


def main(argv=None):
    return study_main(sys.modules[__name__], argv)


if __name__ == "__main__":
    main()

"""Penumbrae of area and sphere lights: light samples x shadow-map size against the
penumbra's error against time.

    python benchmarks/accuracy_penumbrae.py            # the table (several minutes)
    python benchmarks/accuracy_penumbrae.py --quick    # 4 and 16 samples, 64^2 maps

The scene of tests/test_shadows.py's penumbra test, at 48^2: a sphere (icosphere,
subdivision 2) over a floor, lit by one light with shadows, a disk (radius 0.5, facing
down) or a sphere light (radius 0.4), hard raster. Reference: the floor's irradiance with
the exact sphere's shadow, a 64^2-node midpoint quadrature over the light in NumPy
(diffshade.analytic.SphereOverPlane.floor_irradiance). Errors on the penumbra's pixels
(the floor pixels, a pixel away from the sphere's silhouette, where the visible fraction
is between 2% and 98%), per unit of the light's brightest unshadowed floor pixel: mean
and max. 'hard shadow' rows: the error a hard shadow from the light's centre would make
there (a penumbra-blind render). Times: the forward renders of every row timed against
each other in one interleaved run (common.time_settings: median and quartiles); 'first
call' is trace + compile + run. Kept apart from accuracy_area_lights.py (the unshadowed
terms' sample counts), which another study edits.
"""

import sys
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import study_main, time_settings, timing_columns, with_spreads  # noqa: E402

import diffshade as ds  # noqa: E402
from diffshade.analytic import SphereOverPlane  # noqa: E402

NAME = "penumbrae"
OUT = "benchmarks/results/accuracy_penumbrae.json"
SIZE = 48
GEOMETRY = SphereOverPlane()
LIGHTS = {"disk": ("disk", (-0.5, 2.0, -1.0), (0.0, -1.0, 0.0), 0.5),
          "sphere": ("sphere", (0.5, 2.0, -1.0), 0.4)}
POWER, KD = 4.0, 0.6


def camera():
    return ds.look_at((0.0, 4.5, 3.2), (0.0, -1.0, 0.5), width=SIZE, height=SIZE, fov_y=40.0)


def scene(kind, samples):
    ref = LIGHTS[kind]
    if kind == "disk":
        light = ds.area_light(ref[1], normal=ref[2], radius=ref[3], color=POWER,
                              samples=samples, shadows=True)
    else:
        light = ds.sphere_light(ref[1], ref[2], POWER, samples=samples, shadows=True)
    return ds.make_scene(GEOMETRY.mesh(2, 4), camera(), [light],
                         ds.material(ka=0.0, kd=KD, ks=None))


def penumbra(kind):
    """(penumbra mask [H, W], reference colour [H, W], scale, hard-shadow error mean)."""
    cam = camera()
    on_floor, _ = GEOMETRY.shadow(cam, ("point", LIGHTS[kind][1]))
    grown = np.pad(on_floor, 1, mode="edge")
    floor = on_floor & grown[:-2, 1:-1] & grown[2:, 1:-1] & grown[1:-1, :-2] & grown[1:-1, 2:]
    seen, unshadowed = GEOMETRY.floor_irradiance(GEOMETRY.floor_points(cam), LIGHTS[kind],
                                                 nodes=64)
    fraction = seen / np.where(unshadowed > 0, unshadowed, 1.0)
    mask = floor & (fraction > 0.02) & (fraction < 0.98)
    scale = KD * POWER * unshadowed[floor].max()
    _, hard = GEOMETRY.shadow(cam, ("point", LIGHTS[kind][1]))
    hard_error = np.abs(KD * POWER * (unshadowed * ~hard - seen))[mask].mean() / scale
    return mask, KD * POWER * seen, scale, hard_error


def config(kind, samples, map_size):
    """(jitted forward render, scene) of one row."""
    settings = ds.RenderSettings(shadow_map_size=map_size, clamp=False)
    return jax.jit(lambda s: ds.render(s, settings)), scene(kind, samples)


def measure(kind, samples_list, map_sizes, stats, configs):
    """The rows of one light: its hard-shadow row, then per samples and map size the
    penumbra's error (rendered after the timing, so that "first call" is one)."""
    mask, want, scale, hard_error = penumbra(kind)
    # columns that do not apply to the penumbra-blind estimate are None (an empty cell)
    rows = [{"light": kind, "samples": "hard shadow", "map": None, "mean_err": hard_error,
             "max_err": None, "pixels": int(mask.sum()), "fwd_ms": None, "compile_s": None}]
    for samples in samples_list:
        for size in map_sizes:
            render, s = configs[kind, samples, size]
            error = np.abs(np.asarray(render(s), np.float64)[..., 0] - want)[mask] / scale
            rows.append({"light": kind, "samples": samples, "map": size,
                         "mean_err": float(error.mean()), "max_err": float(error.max()),
                         "pixels": int(mask.sum()),
                         **timing_columns(stats[kind, samples, size], "fwd", "compile_s")})
    return rows


def run(quick=False):
    """{"rows": per light, sample count and map size, the penumbra's error and the
    forward time (all rows timed together), and a hard-shadow row per light}."""
    samples = (4, 16) if quick else (4, 16, 64)
    sizes = (64,) if quick else (32, 64, 128)
    timing = {"rounds": 3, "max_warmup": 6} if quick else {"rounds": 7}
    configs = {(kind, n, size): config(kind, n, size)
               for kind in LIGHTS for n in samples for size in sizes}
    stats = time_settings({key: (lambda c=c: c[0](c[1])) for key, c in configs.items()},
                          **timing)
    return {"rows": [row for kind in LIGHTS
                     for row in measure(kind, samples, sizes, stats, configs)]}


COLUMNS = [("light", "light", "{}"), ("samples", "samples", "{}"), ("map", "map", "{}"),
           ("mean_err", "mean err", "{:.3f}"), ("max_err", "max err", "{:.3f}"),
           ("fwd_ms", "fwd ms", "{:.1f}"), ("fwd_spread", "fwd spread ms", "{}"),
           ("compile_s", "first call s", "{:.1f}")]


def tables(results):
    from accuracy_tables import table
    return table(with_spreads(results["rows"]), COLUMNS)


def plots(results, folder):
    from accuracy_plots import draw_penumbrae
    return draw_penumbrae(results, folder)


def main(argv=None):
    return study_main(sys.modules[__name__], argv)


if __name__ == "__main__":
    main()

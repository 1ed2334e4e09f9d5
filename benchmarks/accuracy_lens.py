"""Lens distortion: photos undistorted on load, or the distortion ignored, against the
fitted material's error against time (the lens section of the accuracy-versus-time
study, docs/accuracy-vs-time.md).

    python benchmarks/accuracy_lens.py            # the table (a few minutes)
    python benchmarks/accuracy_lens.py --quick    # seconds-long subset
    python benchmarks/accuracy_study.py --only lens --docs   # and the page's tables

The capture of benchmarks/undistortion.py: the exact sphere (diffshade.analytic) of
material TRUTH (ka, kd; no specular), seen by its three calibrated cameras (fx != fy, the
principal point off the centre, barrel distortion k1 = -0.12, k2 = 0.03 and tangential
terms) at `size` px wide (3/4 of it high); each photo pixel is the mean of 4 x 4 rays
through the lens, the photo float or 8-bit sRGB. The linear solver fits ka and kd on an
icosphere of subdivision 5, as `diffshade fit` does, with `handling`:

- undistorted on load: each photo and its mask resampled into the pinhole image that
  diffshade renders (diffshade.io.undistort_image, undistort_mask: what a dataset with
  `dist` gets on load), silhouette margin `margin` px (--edge-margin);
- distortion ignored: the photos as they are, the cameras without `dist`;
- no lens: photos of the same cameras without distortion (what the lens costs at best).

Columns: the largest relative error of kd and of ka against TRUTH (and of both:
`max_rel_error`); `fit ms`, the time
from the photos to the fitted material (the undistortion, where there is one, and the
fit: cache building and solve), every row timed against the others
(common.time_settings: median and quartiles), the first call apart; `load ms`, the
undistortion alone.
"""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import study_main, time_settings, timing_columns, with_spreads  # noqa: E402
from undistortion import EYES, TRUTH, calibrated_camera, exact_image, sub_pixels  # noqa: E402

import diffshade as ds  # noqa: E402
from diffshade.io import decode, encode, pinhole, undistort_image, undistort_mask  # noqa: E402
from fitting import Dataset, FitSpec, View, fit  # noqa: E402

NAME = "lens"
OUT = "benchmarks/results/accuracy_lens.json"
SUPERSAMPLE = 4
LIGHTS = [ds.directional_light((-0.5, -0.6, -1.0), color=0.8),
          ds.point_light((1.5, 2.0, 3.0), color=0.6)]
START = ds.material(ka=0.5, kd=0.5, ks=0.0)  # no specular, as the truth
#: (handling, silhouette margin px)
HANDLINGS = (("undistorted on load", 1), ("undistorted on load", 2),
             ("distortion ignored", 1), ("no lens", 1))


def photos(size, eight_bit, lens):
    """[(camera with its dist, photo [H, W, 3])] per eye: the exact sphere through the
    lens (lens False: the same cameras without distortion)."""
    out = []
    for eye in EYES:
        camera = calibrated_camera(eye, size)
        if not lens:
            camera = pinhole(camera)
        scene = ds.make_scene(ds.icosphere(1), camera, LIGHTS, TRUTH)
        photo = exact_image(scene, ds.RenderSettings(), sub_pixels(camera, SUPERSAMPLE),
                            undistort=lens)[..., :3]
        if eight_bit:
            photo = decode(np.round(encode(photo, "srgb") * 255) / 255, "srgb")
        out.append((camera, photo.astype(np.float32)))
    return out


def loaded(shots, handling):
    """The Views a fit sees of `shots` under `handling` (module docstring)."""
    if handling == "undistorted on load":
        views = []
        for camera, photo in shots:
            mask = undistort_mask(None, camera)
            views.append(View(pinhole(camera), LIGHTS, undistort_image(photo, camera), mask))
        return views
    return [View(pinhole(camera), LIGHTS, photo) for camera, photo in shots]


def fitted(shots, handling, margin):
    """The material the linear solver fits from the photos (undistorting them first)."""
    dataset = Dataset(ds.icosphere(5), loaded(shots, handling), truth=TRUTH,
                      settings=ds.RenderSettings())
    return fit(dataset, FitSpec(ks=None, shininess=None), START, method="linear",
               with_uncertainty=False, edge_margin=margin).material


def rel_errors(material):
    out = {}
    for name in ("kd", "ka"):
        truth = np.asarray(getattr(TRUTH, name), np.float64)
        got = np.asarray(getattr(material, name), np.float64)
        out[f"{name}_rel_error"] = float(np.max(np.abs(got - truth) / truth))
    out["max_rel_error"] = max(out["kd_rel_error"], out["ka_rel_error"])
    return out


def cases(sizes, targets):
    """{(size, targets, handling, margin): photos} of every row."""
    out = {}
    for size in sizes:
        for eight_bit in targets:
            label = "8-bit sRGB" if eight_bit else "float"
            with_lens, without = photos(size, eight_bit, True), photos(size, eight_bit, False)
            for handling, margin in HANDLINGS:
                out[size, label, handling, margin] = (without if handling == "no lens"
                                                      else with_lens)
    return out


def timed_calls(rows_of):
    """{(row key, "fit" | "load"): zero-argument call} for common.time_settings."""
    calls = {}
    for key, shots in rows_of.items():
        _, _, handling, margin = key
        calls[key, "fit"] = lambda s=shots, h=handling, m=margin: fitted(s, h, m).kd
        if handling == "undistorted on load":
            calls[key, "load"] = lambda s=shots, h=handling: [v.target for v in loaded(s, h)]
    return calls


def run(quick=False):
    """{"rows": per image size, photo kind and handling: the fitted material's errors and
    the time from the photos to it (all rows timed together)}."""
    sizes, targets = ((64,), (True,)) if quick else ((64, 128, 256), (False, True))
    timing = {"rounds": 3, "max_warmup": 6} if quick else {"rounds": 7}
    rows_of = cases(sizes, targets)
    stats = time_settings(timed_calls(rows_of), **timing)
    rows = []
    for key, shots in rows_of.items():
        size, label, handling, margin = key
        row = {"size": size, "photos": label, "handling": handling, "margin": margin,
               **rel_errors(fitted(shots, handling, margin)),
               **timing_columns(stats[key, "fit"], "fit", "compile_s")}
        if (key, "load") in stats:
            row |= timing_columns(stats[key, "load"], "load")
        rows.append(row)
    return {"rows": rows}


COLUMNS = [("size", "px", "{}"), ("photos", "photos", "{}"), ("handling", "lens", "{}"),
           ("margin", "margin px", "{}"), ("kd_rel_error", "kd max rel err", "{:.1e}"),
           ("ka_rel_error", "ka max rel err", "{:.1e}"), ("fit_ms", "fit ms", "{:.1f}"),
           ("fit_spread", "fit spread ms", "{}"), ("load_ms", "of which load ms", "{:.1f}"),
           ("compile_s", "first call s", "{:.1f}")]


def tables(results):
    from accuracy_tables import table
    return table(with_spreads(results["rows"], ("fit", "load")), COLUMNS)


def plot(axes, rows):
    """The material's largest relative error against the time from the photos to it: left
    float photos, right 8-bit; colour the handling (and margin), marker the image size."""
    from accuracy_plots import plot_generic

    kinds = [k for k in ("float", "8-bit sRGB") if any(r["photos"] == k for r in rows)]
    for ax, kind in zip(axes, kinds, strict=True):
        chosen = [{**r, "lens": f"{r['handling']}, margin {r['margin']} px"} for r in rows
                  if r["photos"] == kind]
        plot_generic(ax, chosen, ("lens", "size"), f"lens distortion, {kind} photos",
                     "max_rel_error", "fit_ms", legend=ax is axes[-1], front=False)
        ax.set_xlabel("time from the photos to the material (ms)")
        ax.set_ylabel("largest relative error of ka and kd")


def plots(results, folder):
    from accuracy_plots import _draw

    count = len({r["photos"] for r in results["rows"]})
    return [_draw(folder, "lens", count,
                  lambda axes: plot(axes if count > 1 else [axes], results["rows"]),
                  width=5.5 * count + 2.5)]


def main(argv=None):
    return study_main(sys.modules[__name__], argv)


if __name__ == "__main__":
    main()

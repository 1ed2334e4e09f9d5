"""Why 8-bit targets do not improve with more views (docs/accuracy-vs-time.md, fitting).

    PYTHONPATH=. python benchmarks/quantization_bias.py [--size 128] [--views 1,8]

The fitting study's noise rows (benchmarks/accuracy_fitting.py, noise_rows): the linear
solver on make_dataset targets (subdivision-4 sphere, Phong, 2 lights per camera,
seeds 3-7) rounded to 8 bits, against the number of views. Per seed and view count this
prints every parameter's largest relative error and, as an independent prediction, the
relative error that rounding makes of the unlit pixels' value: a pixel that no light
reaches shows ka * GLOBAL_AMBIENT exactly, the same value in every view, so rounding
shifts it by the same amount everywhere; that shift divided by the value is a bias of ka
that no number of views averages out. The 'dither' rows add uniform noise of one code
step (1/255) before the rounding: the rounding error is then independent from pixel to
pixel and falls with the number of views. 'pixels unlike camera 0's': the fraction of
the later cameras' pixels whose target differs from the first camera's image under the
same light (the sphere is symmetric and the layout's lights turn with the camera, so the
views are nearly copies). Errors are deterministic (fixed seeds).
"""

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy_fitting import NOISE_SEEDS, material_errors  # noqa: E402
from common import print_table, write_results  # noqa: E402

from data_synth import GLOBAL_AMBIENT, make_dataset  # noqa: E402
from fitting import fit  # noqa: E402


def ka_rounding_bias(ka):
    """Relative error of ka implied by rounding the unlit value ka * GLOBAL_AMBIENT to
    8 bits (per channel, the largest)."""
    value = np.asarray(ka, np.float64) * GLOBAL_AMBIENT
    return float(np.max(np.abs(np.round(value * 255.0) / 255.0 - value) / value))


def dithered(dataset, seed):
    """The float targets of `dataset` with uniform noise of one code step, then rounded."""
    rng = np.random.default_rng(1000 + seed)
    views = []
    for view in dataset.views:
        noisy = view.target + rng.uniform(-0.5, 0.5, view.target.shape) / 255.0
        views.append(view.__class__(view.camera, view.lights,
                                    np.round(np.clip(noisy, 0.0, 1.0) * 255.0) / 255.0))
    return dataset.__class__(**{**dataset.__dict__, "views": views})


def differing(dataset, n_lights=2):
    """The fraction of pixels of the views after the first camera's whose target differs
    from the first camera's image under the same light (0 when all views are copies)."""
    targets = [np.asarray(v.target) for v in dataset.views]
    later = [np.any(t != targets[k % n_lights], axis=-1)
             for k, t in enumerate(targets) if k >= n_lights]
    return float(np.mean(later)) if later else None


def rows_for(size, n_views, seed, mode):
    clean = make_dataset(n_views=n_views, size=size, seed=seed,
                         quantize_8bit=(mode == "8-bit"))
    dataset = dithered(clean, seed) if mode == "dither" else clean
    result = fit(dataset, method="linear", with_uncertainty=False)
    errors = material_errors(result.material, dataset.truth)
    worst = max(errors, key=errors.get)
    return {"mode": mode, "views": n_views, "seed": seed, "worst": worst,
            "max_rel_error": errors[worst], **{f"{k}_err": v for k, v in errors.items()},
            "ka_bias_predicted": ka_rounding_bias(dataset.truth.ka),
            "differing": differing(dataset)}


COLUMNS = [("mode", "targets", "{}"), ("views", "views", "{}"), ("seed", "seed", "{}"),
           ("max_rel_error", "max rel err", "{:.1e}"), ("worst", "worst", "{}"),
           ("ka_err", "ka err", "{:.1e}"), ("ka_bias_predicted", "ka rounding bias", "{:.1e}"),
           ("kd_err", "kd err", "{:.1e}"), ("ks_err", "ks err", "{:.1e}"),
           ("shininess_err", "n err", "{:.1e}"),
           ("differing", "pixels unlike camera 0's", "{:.2%}")]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--views", default="1,8")
    parser.add_argument("--modes", default="8-bit,dither")
    parser.add_argument("--out", default=None, help="also write the rows as JSON")
    args = parser.parse_args(argv)
    rows = []
    for mode in args.modes.split(","):
        for n_views in (int(v) for v in args.views.split(",")):
            for seed in NOISE_SEEDS:
                rows.append(rows_for(args.size, n_views, seed, mode))
                print(f"{mode}, {n_views} views, seed {seed}: done", flush=True)
    print()
    print_table(rows, COLUMNS)
    if args.out:
        write_results(args.out, {"size": args.size, "rows": rows})


if __name__ == "__main__":
    main()

"""Material recovery: relative error of every fitted value over many random materials.

For `--n` random materials (data_synth.random_material, seeded: RGB ka, kd, ks, shininess
log-uniform in [2, 500]), the data_synth icosphere seen in 3 views x 2 lights at 128 x 128
is fitted from one fixed initial guess (fitting.DEFAULT_INIT) in three configurations:
- the default method ('linear') on noise-free float targets;
- the default method on 8-bit quantized targets;
- plain Adam (per-group learning rates, `--adam-steps` steps) on the float targets.
For every coefficient channel and shininess it prints the median and the worst relative
error over the fits, and the wall time per fit after compilation (median): before the
timed fits one warm-up fit on another material compiles everything, and its time is
reported apart. The bars of the issue: median < 0.5 % and worst < 2 % (float targets),
worst < 3 % (8-bit targets). Writes JSON (default benchmarks/results/fit_recovery.json).

    python benchmarks/fit_recovery.py [--quick] [--n 30] [--no-adam]

With `--srgb`, instead, for each built-in shape (icosphere, torus, box) it compares the
targets a user would have: linear float .npy files against 8-bit sRGB PNGs (written with
diffshade.write_png and read back with diffshade.read_image, so decoded to linear), and
the same PNGs wrongly read as linear; for the PNGs it also prints the rounding bound of
the uncertainty report (relative to the true value; median and worst over the fits).
Writes results/fit_recovery_srgb.json by default.

    python benchmarks/fit_recovery.py --srgb [--n 10]

Timings on a shared machine are noisy; errors are deterministic.
"""

import argparse
import dataclasses
import json
import os
import sys
import tempfile
import time
import warnings

import numpy as np

from data_synth import SHAPES, make_dataset, random_material
from diffshade.io.images import read_image, write_png
from fitting import DEFAULT_INIT, fit
from fitting.spec import value_names

BARS = {"float": (0.005, 0.02), "8-bit": (None, 0.03)}


def png_targets(dataset, color_space):
    """The dataset with every target written as an 8-bit sRGB PNG and read back, decoded
    as `color_space` ('srgb': right; 'linear': the mistake the PNGs' tag prevents)."""
    views = []
    with tempfile.TemporaryDirectory() as folder:
        for i, view in enumerate(dataset.views):
            path = write_png(os.path.join(folder, f"view_{i}.png"), view.target)
            views.append(dataclasses.replace(view, target=read_image(path, color_space)))
    return dataclasses.replace(dataset, views=views)


def _flat(values):
    return np.concatenate([np.ravel(np.asarray(values[k], np.float64)) for k in sorted(values)])


def run_config(materials, warmup_material, *, quantize, method, steps, size, shape="icosphere",
               png=None):
    """(per-fit errors [n, p], per-fit seconds [n], per-fit CPU seconds [n] (this
    process, all threads: less sensitive to other jobs on the machine than the wall time),
    warm-up seconds, parameter names, and the rounding bounds relative to the truth [n, p]
    for PNG targets, else None).
    png: None (float or linearly quantized targets) or the colour space the 8-bit sRGB
    PNG targets are decoded as."""
    def one(mat):
        dataset = make_dataset(shape, material=mat, size=size, quantize_8bit=quantize)
        if png:
            dataset = png_targets(dataset, png)
        start, cpu = time.perf_counter(), time.process_time()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = fit(dataset, method=method, steps=steps, with_uncertainty=png == "srgb")
        seconds = (time.perf_counter() - start, time.process_time() - cpu)
        names = value_names(result.errors)
        truth = _flat({k: getattr(mat, k) for k in result.errors})
        bound = result.uncertainty.rounding_bound if result.uncertainty else None
        return _flat(result.errors), seconds, names, (
            None if bound is None else np.broadcast_to(bound, truth.shape) / np.abs(truth))

    _, warm_seconds, names, _ = one(warmup_material)
    errors, seconds, bounds = [], [], []
    for i, mat in enumerate(materials):
        err, sec, _, bound = one(mat)
        errors.append(err)
        seconds.append(sec)
        bounds.append(bound)
        print(f"  fit {i + 1}/{len(materials)}: worst {100 * err.max():.3f} % "
              f"({names[int(err.argmax())]}), {sec[0]:.2f} s ({sec[1]:.2f} s CPU)",
              file=sys.stderr)
    bounds = None if any(b is None for b in bounds) else np.array(bounds)
    seconds = np.array(seconds)
    return np.array(errors), seconds[:, 0], seconds[:, 1], warm_seconds[0], names, bounds


def passes(label, errors):
    median_bar, worst_bar = BARS.get(label, (None, None))
    ok = worst_bar is None or errors.max() < worst_bar
    return ok and (median_bar is None or np.median(errors, 0).max() < median_bar)


def print_table(configs, names, n):
    print(f"\nmaterial recovery: {n} random materials, 6 images (3 views x 2 lights), "
          "init ka 0.3, kd 0.5, ks 0.3, shininess 20")
    print("relative error in %: median / worst over the fits")
    header = f"{'parameter':<12}" + "".join(f"{c['title']:>24}" for c in configs)
    print(header)
    for j, name in enumerate(names):
        cells = [f"{100 * np.median(c['errors'][:, j]):.3f} / {100 * c['errors'][:, j].max():.3f}"
                 for c in configs]
        print(f"{name:<12}" + "".join(f"{cell:>24}" for cell in cells))
    rows = [("time/fit (s)", lambda c: f"{np.median(c['seconds']):.2f}"),
            ("CPU/fit (s)", lambda c: f"{np.median(c['cpu_seconds']):.2f}"),
            ("compile+fit (s)", lambda c: f"{c['warmup_seconds']:.1f}"),
            ("bar", lambda c: c["bar"])]
    for label, cell in rows:
        print(f"{label:<12}" + "".join(f"{cell(c):>24}" for c in configs))


def parse_args(argv):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=30, help="number of random materials")
    parser.add_argument("--seed", type=int, default=2024)
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--method", default="linear", help="the default method's name")
    parser.add_argument("--adam-steps", type=int, default=2000)
    parser.add_argument("--no-adam", action="store_true", help="skip the Adam comparison")
    parser.add_argument("--quick", action="store_true", help="5 materials, 500 Adam steps")
    parser.add_argument("--srgb", action="store_true",
                        help="compare linear .npy with 8-bit sRGB PNG targets (docstring)")
    parser.add_argument("--out", default=None,
                        help="JSON output (default benchmarks/results/fit_recovery.json, or "
                             "benchmarks/results/fit_recovery_srgb.json with --srgb)")
    args = parser.parse_args(argv)
    if args.quick:
        args.n, args.adam_steps = 5, 500
    results = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")
    args.out = args.out or os.path.join(results, "fit_recovery_srgb.json" if args.srgb
                                        else "fit_recovery.json")
    return args


SRGB_PLAN = (("linear .npy", None), ("sRGB PNG", "srgb"), ("sRGB PNG read as linear", "linear"))


def srgb_cell(errors, j):
    return f"{100 * np.median(errors[:, j]):.3f} / {100 * errors[:, j].max():.3f}"


def main_srgb(args, warmup, materials):
    """The --srgb comparison: per shape, a table of median / worst relative error in %."""
    out = {"n": args.n, "seed": args.seed, "size": args.size, "shapes": {}}
    for shape in SHAPES:
        rows = {}
        for title, png in SRGB_PLAN:
            print(f"{shape}, {title}:", file=sys.stderr)
            errors, seconds, _, _, names, bounds = run_config(
                materials, warmup, quantize=False, method=args.method, steps=None,
                size=args.size, shape=shape, png=png)
            rows[title] = {"errors": errors, "bounds": bounds, "seconds": seconds}
        print(f"\n{shape}: {args.n} random materials, 6 images of {args.size}^2; relative "
              "error in %, median / worst over the fits")
        titles = [t for t, _ in SRGB_PLAN] + ["PNG rounding bound"]
        print(f"{'parameter':<12}" + "".join(f"{t:>26}" for t in titles))
        for j, name in enumerate(names):
            cells = [srgb_cell(rows[t]["errors"], j) for t, _ in SRGB_PLAN]
            cells.append(srgb_cell(rows["sRGB PNG"]["bounds"], j))
            print(f"{name:<12}" + "".join(f"{c:>26}" for c in cells))
        out["shapes"][shape] = {"parameters": names} | {t: {
            "median": np.median(r["errors"], 0).tolist(), "worst": r["errors"].max(0).tolist(),
            "median_seconds_per_fit": float(np.median(r["seconds"])),
            "rounding_bound_median": None if r["bounds"] is None
            else np.median(r["bounds"], 0).tolist(),
            "rounding_bound_worst": None if r["bounds"] is None else r["bounds"].max(0).tolist()}
            for t, r in rows.items()}
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w", encoding="utf-8") as file:
        json.dump(out, file, indent=2)
    print(f"wrote {args.out}")


def main(argv=None):
    args = parse_args(argv)
    rng = np.random.default_rng(args.seed)
    warmup, *materials = [random_material(rng) for _ in range(args.n + 1)]
    if args.srgb:
        return main_srgb(args, warmup, materials)
    plan = [(f"{args.method} float", "float", False, args.method, None),
            (f"{args.method} 8-bit", "8-bit", True, args.method, None)]
    if not args.no_adam:
        plan.append((f"adam float ({args.adam_steps})", "adam", False, "adam", args.adam_steps))
    configs = []
    for title, label, quantize, method, steps in plan:
        print(f"{title}:", file=sys.stderr)
        errors, seconds, cpu, warm, names, _ = run_config(
            materials, warmup, quantize=quantize, method=method, steps=steps, size=args.size)
        ok = passes(label, errors)
        configs.append({"title": title, "label": label, "method": method, "steps": steps,
                        "quantize_8bit": quantize, "errors": errors, "seconds": seconds,
                        "cpu_seconds": cpu,
                        "warmup_seconds": warm,
                        "bar": ("PASS" if ok else "FAIL") if label in BARS else "-"})
    print_table(configs, names, args.n)
    write_json(args, configs, names, materials)


def write_json(args, configs, names, materials):
    out = {"n": args.n, "seed": args.seed, "size": args.size, "init": {
        "ka": 0.3, "kd": 0.5, "ks": 0.3, "shininess": float(DEFAULT_INIT.shininess)},
        "parameters": names, "bars": BARS, "configs": [
            {**{k: v for k, v in c.items() if k not in ("errors", "seconds", "cpu_seconds")},
             "median": dict(zip(names, np.median(c["errors"], 0).tolist(), strict=True)),
             "worst": dict(zip(names, c["errors"].max(0).tolist(), strict=True)),
             "errors": c["errors"].tolist(), "seconds_per_fit": c["seconds"].tolist(),
             "median_seconds_per_fit": float(np.median(c["seconds"])),
             "cpu_seconds_per_fit": c["cpu_seconds"].tolist(),
             "median_cpu_seconds_per_fit": float(np.median(c["cpu_seconds"]))}
            for c in configs],
        "materials": [{"ka": np.asarray(m.ka).tolist(), "kd": np.asarray(m.kd).tolist(),
                       "ks": np.asarray(m.ks).tolist(), "shininess": float(m.shininess)}
                      for m in materials]}
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w", encoding="utf-8") as file:
        json.dump(out, file, indent=2)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    sys.exit(main())

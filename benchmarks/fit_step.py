"""Per-step time of a material fit, with and without the rasterization cache.

Scene: the data_synth icosphere, 3 views x 2 lights = 6 images at 128 x 128 (options
change it). Both steps are the same jitted Adam step (fitting.solve.make_step) on the same
parameters; they differ only in the loss:
- cached: `diffshade.shade` on the kept pixels cached by fitting.model.build_cache;
- full render: `diffshade.render` of every view every step (rasterization included),
  compared at the same pixels;
- cached, unguarded: the cached step without optax.apply_if_finite (the guard against
  non-finite steps that every fit uses), to measure the guard's cost.
The first call (compile + run) is reported separately; then `--warmup` untimed steps, and
the median (and quartiles) over `--runs` timed steps, each waited for with
block_until_ready. Writes JSON (default results/fit_step.json).

    python benchmarks/fit_step.py [--size 128] [--runs 100] [--quick]

Timings on a shared machine are noisy: compare medians, and rerun when in doubt.
"""

import argparse
import json
import os
import platform
import sys
import time

import jax
import numpy as np

from data_synth import make_dataset
from fitting import DEFAULT_INIT, FitSpec
from fitting.model import build_cache, make_loss, make_render_loss, render_data
from fitting.solve import make_optimizer, make_step
from fitting.spec import to_unconstrained


def time_step(step, params, state, data, runs, warmup):
    """(first call seconds, [runs] per-step seconds) of step on data."""
    start = time.perf_counter()
    params, state, loss = step(params, state, data)
    jax.block_until_ready(loss)
    first = time.perf_counter() - start
    for _ in range(warmup):
        params, state, loss = step(params, state, data)
    jax.block_until_ready(loss)
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        params, state, loss = step(params, state, data)
        jax.block_until_ready((params, loss))
        times.append(time.perf_counter() - start)
    return first, np.array(times)


def summary(first, times):
    q1, median, q3 = np.percentile(times, [25, 50, 75]) * 1e3
    return {"first_call_s": first, "median_ms": median, "q1_ms": q1, "q3_ms": q3,
            "min_ms": float(times.min() * 1e3), "runs": len(times)}


def parse_args(argv):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=128, help="image width and height")
    parser.add_argument("--views", type=int, default=3)
    parser.add_argument("--lights", type=int, default=2, help="lights per view (one image each)")
    parser.add_argument("--runs", type=int, default=100, help="timed steps per path")
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--quick", action="store_true", help="20 runs, 3 warm-up steps")
    parser.add_argument("--out", default="results/fit_step.json")
    args = parser.parse_args(argv)
    if args.quick:
        args.runs, args.warmup = 20, 3
    return args


def main(argv=None):
    args = parse_args(argv)
    dataset = make_dataset(n_views=args.views, n_lights=args.lights, size=args.size)
    spec, optimizer = FitSpec(), make_optimizer()
    params = to_unconstrained(DEFAULT_INIT, spec)
    cached_data = build_cache(dataset, DEFAULT_INIT)
    full_data = render_data(dataset, cached_data)
    results = {}
    unguarded = make_optimizer(guard=False)
    for name, loss, data, opt in (
            ("cached", make_loss(spec), cached_data, optimizer),
            ("full_render", make_render_loss(spec), full_data, optimizer),
            ("cached_unguarded", make_loss(spec), cached_data, unguarded)):
        first, times = time_step(make_step(loss, opt), params, opt.init(params), data,
                                 args.runs, args.warmup)
        results[name] = summary(first, times)
    pixels = int(sum(v.pixels.shape[0] for v in cached_data.views))
    report = {"images": len(dataset.views), "size": args.size, "kept_pixels": pixels,
              "device": str(jax.devices()[0]), "cpu_count": os.cpu_count(),
              "machine": platform.machine(), "results": results,
              "speedup": results["full_render"]["median_ms"] / results["cached"]["median_ms"]}
    print_table(report)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w", encoding="utf-8") as file:
        json.dump(report, file, indent=2)
    print(f"wrote {args.out}")


def print_table(report):
    print(f"fit step: {report['images']} images at {report['size']}x{report['size']}, "
          f"{report['kept_pixels']} kept pixels, Adam, {report['device']}, "
          f"{report['cpu_count']} CPUs")
    print(f"{'path':<14} {'median ms':>10} {'q1-q3 ms':>14} {'min ms':>8} {'first call s':>13}")
    for name, r in report["results"].items():
        print(f"{name:<14} {r['median_ms']:>10.2f} {r['q1_ms']:>6.2f}-{r['q3_ms']:<7.2f} "
              f"{r['min_ms']:>8.2f} {r['first_call_s']:>13.2f}")
    print(f"speed-up of the cache: {report['speedup']:.1f}x")


if __name__ == "__main__":
    sys.exit(main())

"""Compile time of a cached-fragments loss: arrays passed as arguments vs closed over.

    python benchmarks/fragment_cache_compile.py [--size 256] [--runs 3] [--quick]

The loss of docs/soft-rasterization.md ("Caching fragments"): the soft-rasterized
built-in sphere (--size² pixels) is rasterized once, and `jax.value_and_grad` of the mean
squared error of `render_fragments` against a target is jitted two ways:
- arguments: loss(material, scene, frags, target), as the document shows;
- closure: loss(material), reading scene, frags and target from the enclosing scope, so
  that they are constants of the compiled program.
Each is traced, lowered and compiled afresh (a new function object per run), and the
median over --runs of the seconds to the first result is printed with the median of 10
later calls. The closure variant makes XLA constant-fold the arrays and print
"Constant folding an instruction is taking > 1s" on stderr.
"""

import argparse
import os
import statistics
import time

import jax
import jax.numpy as jnp

import diffshade as ds


def make_losses(scene, settings, frags, target):
    """(arguments, closure) versions of the value-and-gradient of the loss, freshly jitted."""
    def loss_args(material, scene, frags, target):
        image = ds.render_fragments(ds.replace(scene, material=material), frags, settings)
        return jnp.mean((image - target) ** 2)

    def loss_closure(material):
        image = ds.render_fragments(ds.replace(scene, material=material), frags, settings)
        return jnp.mean((image - target) ** 2)

    with_args = jax.jit(jax.value_and_grad(loss_args))
    closure = jax.jit(jax.value_and_grad(loss_closure))
    return (lambda m: with_args(m, scene, frags, target)), closure


def first_and_steady(fn, material):
    """(seconds to the first result, median seconds of 10 later calls)."""
    start = time.perf_counter()
    jax.block_until_ready(fn(material))
    first = time.perf_counter() - start
    runs = []
    for _ in range(10):
        start = time.perf_counter()
        jax.block_until_ready(fn(material))
        runs.append(time.perf_counter() - start)
    return first, statistics.median(runs)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="one run at 64 x 64")
    opts = parser.parse_args()
    size, runs = (64, 1) if opts.quick else (opts.size, opts.runs)
    scene = ds.builtin_scene("sphere", size, size)
    settings = ds.RenderSettings(raster="soft")
    target = ds.render(scene, settings)
    frags = ds.rasterize_scene(scene, settings)
    material = ds.replace(scene.material, kd=jnp.full(3, 0.5))
    times = {"arguments": [], "closure": []}
    for _ in range(runs):
        for name, fn in zip(times, make_losses(scene, settings, frags, target), strict=True):
            times[name].append(first_and_steady(fn, material))
    print(f"soft sphere {size}x{size}, value_and_grad of the cached-fragments loss "
          f"(median of {runs}; load average {os.getloadavg()[0]:.1f})", end="")
    for name, rows in times.items():
        first = statistics.median(r[0] for r in rows)
        steady = statistics.median(r[1] for r in rows)
        print(f"\n  {name:9s}: first call (trace + compile + run) {first:6.2f} s, "
              f"then {steady * 1e3:7.2f} ms per call", end="")
    print()


if __name__ == "__main__":
    main()

"""Shared benchmark helpers: timing with compile time separated, tables, JSON output."""

import os
import platform
import statistics
import time

import jax


def time_call(fn, *args, repeats=10, warmup=2):
    """(compile_s, median_s, runs) for a jitted fn: the first call (trace + compile + run)
    is timed on its own, then `warmup` untimed calls, then the median of `repeats` runs."""
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - start
    for _ in range(warmup):
        jax.block_until_ready(fn(*args))
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        runs.append(time.perf_counter() - start)
    return compile_s, statistics.median(runs), runs


def machine_info():
    """What the figures were measured on."""
    return {"platform": platform.platform(), "processor": platform.processor(),
            "cpu_count": os.cpu_count(), "python": platform.python_version(),
            "jax": jax.__version__, "backend": jax.default_backend(),
            "devices": [str(d) for d in jax.devices()]}


def print_table(rows, columns):
    """Print rows (dicts) as an aligned text table with the given (key, header, fmt) columns;
    a cell whose value is None (the column does not apply to the row) prints as an em dash."""
    cells = [["\u2014" if row[key] is None else fmt.format(row[key]) for key, _, fmt in columns]
             for row in rows]
    widths = [max(len(h), *(len(c[i]) for c in cells)) for i, (_, h, _) in enumerate(columns)]
    print("  ".join(h.rjust(w) for (_, h, _), w in zip(columns, widths, strict=True)))
    for c in cells:
        print("  ".join(v.rjust(w) for v, w in zip(c, widths, strict=True)))


def write_results(path, payload):
    """Write the benchmark JSON (with machine info) atomically."""
    from diffshade.io.images import write_json
    payload = {"machine": machine_info(), **payload}
    write_json(path, payload)
    print(f"wrote {path}")

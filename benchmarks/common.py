"""Shared benchmark helpers: timing with compile time separated, tables, JSON output."""

import os
import platform
import random
import statistics
import subprocess
import tempfile
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


def _timed(fn):
    return timed_cpu(fn)[0]


def timed_cpu(fn):
    """(wall s, CPU s of the process, all threads) of one call, its results ready."""
    wall, cpu = time.perf_counter(), time.process_time()
    jax.block_until_ready(fn())
    return time.perf_counter() - wall, time.process_time() - cpu


def _settled(times, settle):
    last = times[-3:]
    middle = statistics.median(last)
    return len(last) == 3 and all(abs(t - middle) <= settle * middle for t in last)


def time_settings(calls, *, rounds=7, settle=0.15, min_warmup=2, max_warmup=20, seed=0):
    """Time several settings against each other: {name: zero-argument fn} ->
    {name: {"compile_s", "warmup_calls", "median_ms", "q1_ms", "q3_ms", "min_ms", "max_ms",
    "runs_ms", "cpu_median_ms", "cpu_min_ms"}} (cpu: the process's CPU time, all threads).

    The protocol: (1) each fn's first call (trace, compile and run) is timed apart, as
    compile_s; (2) each fn is then called until its time settles (the last three calls
    within `settle` of their median; at least `min_warmup`, at most `max_warmup` calls),
    which keeps a slow first run of a warm program (page faults, a cold cache) out of the
    figures; (3) `rounds` rounds follow, in each of which every setting runs once, in an
    order shuffled per round (fixed seed), so that a change in the machine's speed hits
    every setting alike; the median and the quartiles of those runs are reported."""
    compile_s = {name: _timed(fn) for name, fn in calls.items()}
    warmups = {}
    for name, fn in calls.items():
        times = [_timed(fn) for _ in range(min_warmup)]
        while len(times) < max_warmup and not _settled(times, settle):
            times.append(_timed(fn))
        warmups[name] = len(times)
    runs = {name: [] for name in calls}
    order, shuffle = list(calls), random.Random(seed).shuffle
    for _ in range(rounds):
        shuffle(order)
        for name in order:
            runs[name].append(timed_cpu(calls[name]))
    out = {}
    for name, pairs in runs.items():
        times, cpu = [w for w, _ in pairs], [c for _, c in pairs]
        q1, median, q3 = statistics.quantiles(times, n=4, method="inclusive")
        out[name] = {"compile_s": compile_s[name], "warmup_calls": warmups[name],
                     "median_ms": 1e3 * median, "q1_ms": 1e3 * q1, "q3_ms": 1e3 * q3,
                     "min_ms": 1e3 * min(times), "max_ms": 1e3 * max(times),
                     "runs_ms": [round(1e3 * t, 2) for t in times],
                     "cpu_median_ms": 1e3 * statistics.median(cpu),
                     "cpu_min_ms": 1e3 * min(cpu)}
    return out


def run_record():
    """What a measurement ran on and under: the commit (with '+dirty' when the work tree
    has changes), the UTC start and the 1-minute load average; `finish_record` adds the end."""
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                                text=True, check=True).stdout.strip()
        # the code measured: a study's own outputs (JSON, plots, the page) leave it clean
        code = ["diffshade", "fitting", "data_synth", "benchmarks", ":!benchmarks/results"]
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--",
                                *code], cwd=root, capture_output=True, text=True).stdout.strip()
        commit += "+dirty" if dirty else ""
    except (OSError, subprocess.CalledProcessError):
        commit = None
    return {"commit": commit, "start_utc": time.strftime("%Y-%m-%d %H:%M", time.gmtime()),
            "load_before": round(os.getloadavg()[0], 2), "_start": time.perf_counter()}


def finish_record(record):
    """The record of run_record with the minutes taken and the load average at the end."""
    done = {k: v for k, v in record.items() if k != "_start"}
    done["minutes"] = round((time.perf_counter() - record["_start"]) / 60, 1)
    done["load_after"] = round(os.getloadavg()[0], 2)
    return done


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


def timing_columns(stats, prefix, compile_key=None):
    """One setting's time_settings entry as flat row columns: `{prefix}_ms` (the median),
    `{prefix}_q1_ms` and `{prefix}_q3_ms` (its spread), the warm-up calls it took, and the
    first call's time under `compile_key` (default `{prefix}_compile_s`)."""
    return {f"{prefix}_ms": stats["median_ms"], f"{prefix}_q1_ms": stats["q1_ms"],
            f"{prefix}_q3_ms": stats["q3_ms"], f"{prefix}_warmup_calls": stats["warmup_calls"],
            compile_key or f"{prefix}_compile_s": stats["compile_s"]}


def spread(row, prefix):
    """The "q1–q3" text of a timed column (an empty cell where the row has no quartiles:
    results measured before time_settings)."""
    q1, q3 = row.get(f"{prefix}_q1_ms"), row.get(f"{prefix}_q3_ms")
    return "" if q1 is None or q3 is None else f"{q1:.1f}\u2013{q3:.1f}"


def with_spreads(rows, prefixes=("fwd", "fwd_bwd", "grad", "step")):
    """The rows with a `{prefix}_spread` text column ("q1–q3") beside each timed column."""
    return [{**row, **{f"{p}_spread": spread(row, p) for p in prefixes if f"{p}_ms" in row}}
            for row in rows]


def run_study(module, quick=False, out=None, plots=None):
    """Run a study module of the accuracy-versus-time study (its NAME, OUT, run, tables,
    plots: benchmarks/accuracy_study.py) and write its JSON to `out` (default module.OUT;
    for a quick run, a file of that name in the temporary folder) with the run record
    (commit, start, minutes, load before and after); draw its plots into the folder `plots`
    when given. Returns the written payload."""
    record = run_record()
    results = module.run(quick=quick)
    payload = {"benchmark": module.NAME, "quick": quick, **results,
               "run": finish_record(record)}
    if out is None:
        # a quick run never replaces the published JSON unless asked to
        out = (os.path.join(tempfile.gettempdir(), os.path.basename(module.OUT)) if quick
               else module.OUT)
    write_results(out, payload)
    if plots:
        module.plots(payload, plots)
    return payload


def study_main(module, argv=None):
    """The command line of one study module: --quick, --out, --plots FOLDER; prints its
    tables."""
    import argparse
    parser = argparse.ArgumentParser(description=module.__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a seconds-long subset (CI)")
    parser.add_argument("--out", default=None, help=f"the JSON (default {module.OUT})")
    parser.add_argument("--plots", default=None, help="folder for the PNG plots")
    args = parser.parse_args(argv)
    payload = run_study(module, args.quick, args.out, args.plots)
    print(module.tables(payload))
    return payload

"""Time to first result: the README's commands, wall time for the whole process, cold and warm.

    python benchmarks/time_to_first_result.py [--runs 3] [--quick] [--out PATH]

The README's first line runs `diffshade synth -o out/data` and then `diffshade fit
out/data -o out/fit`. Each is run here as its own fresh process (`python -m diffshade`,
this checkout first on PYTHONPATH) in a temporary folder:
- cold: an empty persistent compilation cache (DIFFSHADE_COMPILE_CACHE_DIR, a new
  temporary folder per run) and an empty numba cache (NUMBA_CACHE_DIR, likewise: numba
  otherwise keeps its compiled kernels beside the installed package), so everything is
  compiled, as on the first run after installing;
- after warm-up: the same command again once the background compilation a cold run
  starts (diffshade.host.warmup) is done: it runs on the host kernels the cold run did
  not have, so it compiles their programs (the programs of the JAX kernels are others);
- warm: the same command once more, every cache filled for the kernels it runs on;
- off: DIFFSHADE_COMPILE_CACHE=0 with a warm numba cache (what every run after the
  first cost before the compilation cache).
Each figure is the median over --runs such processes (interpreter start included), as
wall time and as CPU time (user + system, all threads): on a machine shared with other
jobs the wall time grows with the load, the CPU time much less; on an idle machine the
wall time lies between the CPU time divided by the cores XLA keeps busy and the CPU time.

Then one more cold and one warm `fit` run inside an instrumented process break the time
down: imports (diffshade.cli and the command modules), JAX tracing, lowering to MLIR,
XLA compilation (or loading from the cache), and the rest (running the fit, rendering
and writing the result files), read from JAX's compile log (JAX_LOG_COMPILES). Tracing
of a jitted function nested in another is counted in both, so the tracing figure is an
upper bound; in the cold run, "rest" includes numba compiling the host kernels. It also
counts the programs loaded from the cache, the programs in diffshade's program store
(diffshade.io.compile_cache.stored_jit: a warm run loads them whole, so they are not in
JAX's log, and their tracing and lowering are gone from the breakdown), and those JAX refuses to
cache because they contain host callbacks (diffshade.io.compile_cache explains why), and
lists the seconds per program (by its name in the log; wall seconds, so they grow with
the machine's load).
Writes JSON (default benchmarks/results/time_to_first_result.json).

With --fresh-install it measures what a new user meets instead, each run with empty numba
and JAX caches (new temporary folders) and the compilation cache on, as after `pip
install`: the first image (`diffshade render --builtin sphere -o out/first.png`) and the
README's main job (`diffshade synth -o out/data`, then `diffshade fit out/data -o out/fit`:
two processes, timed together), each the median over --runs. The CPU time is that of
those processes: it leaves out the background compilations they start (the host kernels',
and synth's compilation of the fit's programs, data_synth.background, whose programs the
fit waits for). On a fresh install a run
takes the JAX kernels, compiled for a quick start, while the host kernels compile in the
background (diffshade.host.warmup); the benchmark waits for that warm-up after each run (it is not
part of the figure, but it shares the machine with the run it was started by), then times
the same render once more: the run after the warm-up. Writes
benchmarks/results/time_to_first_result_fresh_install.json by default.

    python benchmarks/time_to_first_result.py --fresh-install [--runs 3]
"""

import argparse
import json
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SYNTH = ["synth", "-o", "out/data"]
FIT = ["fit", "out/data", "-o", "out/fit", "--quiet"]

# Runs the command line in this process, timing the imports and capturing JAX's log.
_INSTRUMENTED = """
import json, logging, sys, time
start = time.perf_counter()
records = []
class Keep(logging.Handler):
    def emit(self, record):
        records.append(record.getMessage())
logging.getLogger("jax").addHandler(Keep())
logging.getLogger("jax").setLevel(logging.WARNING)
import diffshade.cli
diffshade.cli.build_parser()
imported = time.perf_counter()
status = diffshade.cli.main(sys.argv[2:])
end = time.perf_counter()
json.dump({"status": status, "imports_s": imported - start, "total_s": end - start,
           "log": records}, open(sys.argv[1], "w"))
"""

_SECONDS = r" in ([0-9.eE+-]+) sec"
_PHASES = {"tracing_s": "Finished tracing " + ".*" + _SECONDS,
           "lowering_s": "Finished jaxpr to MLIR module conversion .*" + _SECONDS,
           "compile_or_load_s": "Finished XLA compilation of .*" + _SECONDS}

# The same, per program (its name in the log): tracing, lowering, compilation seconds.
_PER_PROGRAM = {"tracing_s": r"Finished tracing (\S+) for jit" + _SECONDS,
                "lowering_s": r"Finished jaxpr to MLIR module conversion jit\((\S+)\)" + _SECONDS,
                "compile_s": r"Finished XLA compilation of jit\((\S+)\)" + _SECONDS}


RENDER = ["render", "--builtin", "sphere", "-o", "out/first.png"]
#: what a user's environment may set that would change a fresh install's run (XLA_FLAGS:
#: a first run adds its own, diffshade.host.warmup.COLD_XLA_FLAGS, unless they name them)
_USER_CHOICES = ("DIFFSHADE_WARMUP", "DIFFSHADE_KERNELS", "JAX_COMPILATION_CACHE_DIR",
                 "XLA_FLAGS")


def _env(cache_dir, numba_dir):
    env = {k: v for k, v in os.environ.items() if k not in _USER_CHOICES}
    env = dict(env, PYTHONPATH=os.pathsep.join(
        [ROOT] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]),
        NUMBA_CACHE_DIR=numba_dir)
    if cache_dir is None:
        env["DIFFSHADE_COMPILE_CACHE"] = "0"
    else:
        env["DIFFSHADE_COMPILE_CACHE"] = "1"
        env["DIFFSHADE_COMPILE_CACHE_DIR"] = cache_dir
    return env


def _children_cpu():
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def run_wall(args, cwd, cache_dir, numba_dir):
    """(wall seconds, CPU seconds) of `python -m diffshade ARGS` as a fresh process."""
    start, cpu = time.perf_counter(), _children_cpu()
    subprocess.run([sys.executable, "-m", "diffshade", *args], cwd=cwd,
                   env=_env(cache_dir, numba_dir),
                   check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - start, _children_cpu() - cpu


def run_instrumented(args, cwd, cache_dir, numba_dir):
    """The breakdown of one run of the command line (see the module docstring)."""
    report = os.path.join(cwd, "instrumented.json")
    env = _env(cache_dir, numba_dir) | {"JAX_LOG_COMPILES": "1", "JAX_EXPLAIN_CACHE_MISSES": "1"}
    start, cpu = time.perf_counter(), _children_cpu()
    subprocess.run([sys.executable, "-c", _INSTRUMENTED, report, *args], cwd=cwd, env=env,
                   check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wall, cpu = time.perf_counter() - start, _children_cpu() - cpu
    store = os.path.join(cache_dir, "programs")
    stored = sum(name.endswith(".bin") for _, _, names in os.walk(store) for name in names)
    with open(report) as f:
        run = json.load(f)
    log = run["log"]
    phases = {name: sum(float(m.group(1)) for line in log if (m := re.search(pattern, line)))
              for name, pattern in _PHASES.items()}
    per_program = {}
    for line in log:
        for key, pattern in _PER_PROGRAM.items():
            if m := re.search(pattern, line):
                row = per_program.setdefault(m.group(1), {"count": 0, "tracing_s": 0.0,
                                                          "lowering_s": 0.0, "compile_s": 0.0})
                row[key] += float(m.group(2))
                row["count"] += key == "compile_s"
    no_cache = sorted({m.group(1) for line in log if "because it uses host callbacks" in line
                       and (m := re.search(r"entry for '([^']+)'", line))})
    return {"wall_s": wall, "process_cpu": cpu, "interpreter_start_s": wall - run["total_s"],
            "imports_s": run["imports_s"], **phases,
            "rest_s": run["total_s"] - run["imports_s"] - sum(phases.values()),
            "programs": sum("Finished XLA compilation" in line for line in log),
            "by_program": dict(sorted(per_program.items(),
                                      key=lambda item: -item[1]["compile_s"])),
            "cache_hits": sum("Persistent compilation cache hit" in line for line in log),
            "programs_in_store": stored,
            "not_cacheable_host_callbacks": no_cache}


def wait_for_warmup(cache_dir, numba_dir):
    """Until the background compilation a fresh install's run started is done."""
    subprocess.run([sys.executable, "-c", "from diffshade.host import warmup; warmup.wait()"],
                   env=_env(cache_dir, numba_dir), check=True)


def fresh_install(cwd, runs):
    """{first_image, main_job, synth, fit, after_warmup: [(wall, CPU) seconds]} of `runs`
    fresh installs (module docstring)."""
    rows = {"first_image": [], "synth": [], "fit": [], "main_job": [], "after_warmup": []}
    for i in range(runs):
        for name, commands in (("first_image", [RENDER]), ("main_job", [SYNTH, FIT])):
            cache_dir = os.path.join(cwd, f"fresh_{name}_{i}")
            numba_dir = cache_dir + "_numba"
            times = [run_wall(args, cwd, cache_dir, numba_dir) for args in commands]
            rows[name].append(tuple(map(sum, zip(*times, strict=True))))
            if name == "main_job":
                rows["synth"].append(times[0])
                rows["fit"].append(times[1])
            wait_for_warmup(cache_dir, numba_dir)
            if name == "first_image":
                rows["after_warmup"].append(run_wall(RENDER, cwd, cache_dir, numba_dir))
    return rows


def fresh_install_main(runs, out):
    results = {"load_average_before": os.getloadavg(), "commands": {
        "first_image": "diffshade " + " ".join(RENDER),
        "main_job": f"diffshade {' '.join(SYNTH)} && diffshade {' '.join(FIT)}"}}
    with tempfile.TemporaryDirectory() as cwd:
        rows = fresh_install(cwd, runs)
    results["load_average_after"] = os.getloadavg()
    for name, times in rows.items():
        wall, cpu = (statistics.median(t[i] for t in times) for i in (0, 1))
        results[name] = {"runs": times, "median_wall_s": wall, "median_cpu_s": cpu}
        print(f"{name} (median of {runs}): {wall:.1f} s wall / {cpu:.1f} s CPU")
    print("load average before / after:", results["load_average_before"],
          results["load_average_after"])
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from common import write_results
    write_results(out, results)


def cold_warm(args, cwd, runs):
    """{cold, after_warmup, warm, off: [(wall, CPU) seconds]} of `runs` processes each."""
    walls = {"cold": [], "after_warmup": [], "warm": [], "off": []}
    for i in range(runs):
        cache_dir = os.path.join(cwd, f"cache_{args[0]}_{i}")
        numba_dir = cache_dir + "_numba"
        walls["cold"].append(run_wall(args, cwd, cache_dir, numba_dir))
        wait_for_warmup(cache_dir, numba_dir)
        walls["after_warmup"].append(run_wall(args, cwd, cache_dir, numba_dir))
        walls["warm"].append(run_wall(args, cwd, cache_dir, numba_dir))
        walls["off"].append(run_wall(args, cwd, None, numba_dir))
    return walls


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="one run of each")
    parser.add_argument("--fit-only", action="store_true",
                        help="time only `fit` (synth runs once, untimed, to make the data)")
    parser.add_argument("--fresh-install", action="store_true",
                        help="time the first image and the README's main job on a fresh "
                             "install instead")
    parser.add_argument("--out", help="the JSON to write (default: benchmarks/results/"
                                      "time_to_first_result.json, or "
                                      "time_to_first_result_fresh_install.json)")
    opts = parser.parse_args()
    runs = 1 if opts.quick else opts.runs
    name = "time_to_first_result" + ("_fresh_install" if opts.fresh_install else "")
    out = opts.out or os.path.join(ROOT, "benchmarks", "results", name + ".json")
    if opts.fresh_install:
        return fresh_install_main(runs, out)
    results = {"load_average_before": os.getloadavg()}
    with tempfile.TemporaryDirectory() as cwd:
        if opts.fit_only:
            run_wall(SYNTH, cwd, None, os.path.join(cwd, "numba"))
        for name, args in (("synth", SYNTH), ("fit", FIT))[opts.fit_only:]:
            walls = cold_warm(args, cwd, runs)
            medians = {kind: [statistics.median(r[i] for r in rows) for i in (0, 1)]
                       for kind, rows in walls.items()}
            results[name] = {"command": "diffshade " + " ".join(args), "runs": walls,
                             **{f"{k}_median_wall_s": m[0] for k, m in medians.items()},
                             **{f"{k}_median_cpu_s": m[1] for k, m in medians.items()}}
            print(f"{results[name]['command']} (median of {runs}): " + ", ".join(
                f"{k} {m[0]:.1f} s wall / {m[1]:.1f} s CPU" for k, m in medians.items()))
        cache_dir = os.path.join(cwd, "cache_breakdown")
        results["fit_breakdown"] = {kind: run_instrumented(FIT, cwd, cache_dir,
                                                           cache_dir + "_numba")
                                    for kind in ("cold", "warm")}
    results["load_average_after"] = os.getloadavg()
    for kind, row in results["fit_breakdown"].items():
        print(f"fit {kind}: " + ", ".join(f"{k[:-2]} {v:.2f} s" for k, v in row.items()
                                           if k.endswith("_s")))
        print(f"  process CPU {row['process_cpu']:.2f} s; {row['programs']} programs "
              f"through JAX, {row['cache_hits']} from its cache; {row['programs_in_store']} "
              "entries in the program store (executables loaded whole on a warm run, not in "
              "JAX's log, or 'plain jit' marks); "
              f"not cacheable (host callbacks): "
              f"{', '.join(row['not_cacheable_host_callbacks']) or 'none'}")
        print("  per program (name x count: compile, lowering, tracing seconds): " + "; ".join(
            f"{name} x{p['count']}: {p['compile_s']:.2f}, {p['lowering_s']:.2f}, "
            f"{p['tracing_s']:.2f}" for name, p in row["by_program"].items()
            if p["compile_s"] + p["lowering_s"] + p["tracing_s"] >= 0.05))
    print("load average before / after:", results["load_average_before"],
          results["load_average_after"])
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from common import write_results
    write_results(out, results)


if __name__ == "__main__":
    main()

"""XLA compilation of the README's fit, per program, in CPU seconds (persistent cache off).

    python benchmarks/fit_compile.py [DATASET] [--out PATH]

Runs `diffshade fit DATASET -o <temp> --quiet` inside this process with
DIFFSHADE_COMPILE_CACHE=0, and times every call of JAX's `compile_or_get_cached` (the XLA
compilation of one program; tracing and lowering are not in it) with
`time.process_time()` (user + system CPU of all threads) and wall time, keyed by the
program's name. Without DATASET, the README's dataset (`diffshade synth`: 3 views x 2
lights, 128², icosphere of 5,120 faces) is written to a temporary folder first, by a
separate process, so that its programs are not counted. Prints one row per program
(calls, CPU s, wall s), the total, and the whole process's CPU and wall time; writes the
same as JSON (default benchmarks/results/fit_compile.json). Single runs: on a loaded
machine the CPU figures vary by about ±0.3 s per program from run to run.
"""

import argparse
import collections
import json
import os
import subprocess
import sys
import tempfile
import time

os.environ["DIFFSHADE_COMPILE_CACHE"] = "0"
HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def _instrument(stats):
    from jax._src import compiler
    from jax._src.interpreters import pxla

    original = compiler.compile_or_get_cached

    def timed(backend, computation, *args, **kwargs):
        name = str(computation.operation.attributes["sym_name"]).strip('"')
        cpu, wall = time.process_time(), time.perf_counter()
        try:
            return original(backend, computation, *args, **kwargs)
        finally:
            entry = stats[name]
            entry[0] += 1
            entry[1] += time.process_time() - cpu
            entry[2] += time.perf_counter() - wall

    pxla.compiler.compile_or_get_cached = timed


def _synth(folder):
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")]))
    subprocess.run([sys.executable, "-m", "diffshade", "synth", "-o", folder], check=True,
                   env=env, stdout=subprocess.DEVNULL)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", nargs="?")
    parser.add_argument("--out", default=os.path.join(HERE, "results", "fit_compile.json"))
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        dataset = args.dataset or os.path.join(tmp, "data")
        if args.dataset is None:
            _synth(dataset)
        stats = collections.defaultdict(lambda: [0, 0.0, 0.0])
        _instrument(stats)
        from diffshade.cli import main as cli

        cpu, wall = time.process_time(), time.perf_counter()
        code = cli(["fit", dataset, "-o", os.path.join(tmp, "fit"), "--quiet"])
        cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    rows = sorted(stats.items(), key=lambda kv: -kv[1][1])
    print(f"{'program':<32} {'calls':>5} {'CPU s':>7} {'wall s':>7}")
    for name, (calls, c, w) in rows:
        print(f"{name[:32]:<32} {calls:>5} {c:>7.2f} {w:>7.2f}")
    total = [sum(v[i] for v in stats.values()) for i in range(3)]
    print(f"{'all XLA compilation':<32} {total[0]:>5} {total[1]:>7.2f} {total[2]:>7.2f}")
    print(f"exit {code}; the fit process: {cpu:.1f} s CPU, {wall:.1f} s wall; load average "
          f"{os.getloadavg()[0]:.1f}")
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump({"programs": {n: {"calls": v[0], "cpu_s": v[1], "wall_s": v[2]}
                                for n, v in rows},
                   "total_cpu_s": total[1], "total_wall_s": total[2], "process_cpu_s": cpu,
                   "process_wall_s": wall, "load_average": os.getloadavg()[0]}, f, indent=1)


if __name__ == "__main__":
    main()

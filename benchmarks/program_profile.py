"""Where a compiled soft forward + backward spends its time, piece by piece (XLA's thunks).

benchmarks/soft_stages.py times each stage on its own; this script times the pieces of
the one compiled program that peers.py times (the judged scene, soft K = 8, Phong): the
value_and_grad of the MSE w.r.t. the material, or the material and the vertices, or the
soft forward alone (--program). It traces --calls calls with jax.profiler, reads the XLA
CPU runtime's events (one per thunk: a fusion, a custom call such as a host kernel, a
copy), and prints each thunk's minimum and median over the calls with what the compiled
HLO says of it: its shape, its custom-call target (the host kernels: diffshade_*) and its
JAX op name (`transpose(...)` marks the reverse pass). Conditionals (on_active's tiers)
are listed too, but their events span the thunks run inside them, which are listed on
their own: the totals leave them out and split the other thunks into host kernels,
forward XLA code and reverse XLA code.

--diff prints, instead, the material + vertices program against the material one: per
(thunk kind, shape, op name), the difference of the minima, largest first: what the
vertices' gradient adds, thunk by thunk.

    python benchmarks/program_profile.py [--program vertices] [--calls 15] [--top 40]
    python benchmarks/program_profile.py --diff
"""

import argparse
import collections
import glob
import gzip
import json
import os
import re
import statistics
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

#: thunk events of the runtime, not leaf work
_NOT_LEAVES = ("ThunkExecutor", "block_until_ready", "PjitFunction", "Execute", "end:",
               "ThreadpoolListener")


def program(size, with_vertices):
    """(jitted function, its arguments): peers.py's soft f+b on the judged scene, or its
    soft forward (with_vertices None)."""
    import jax
    import jax.numpy as jnp
    from peers import SOFT_K, judged_scene, mse_grad

    import diffshade as ds

    scene = judged_scene(size, 4)
    soft = ds.RenderSettings(raster="soft", faces_per_pixel=SOFT_K, shading="phong")
    if with_vertices is None:
        return jax.jit(lambda s: ds.render(s, soft)), (scene,)
    target = jnp.full((size, size, 4), 0.5, jnp.float32)
    fn, args = mse_grad(scene, soft, target, with_vertices)
    return jax.jit(fn), args


def hlo_table(text):
    """Per HLO instruction name: (shape, custom-call target, op name) from the compiled
    program's text."""
    table = {}
    for line in text.splitlines():
        found = re.match(r"\s*(?:ROOT )?%(\S+) = (\(.*?\)|\S+) ", line)
        if found:
            target = re.search(r'custom_call_target="([^"]*)"', line)
            op = re.search(r'op_name="([^"]*)"', line)
            table[found.group(1)] = (found.group(2)[:48], target.group(1) if target else "",
                                     op.group(1) if op else "")
    return table


def thunk_times(fn, args, calls):
    """Per thunk name: its durations in ms over `calls` traced calls (after a warm-up)."""
    import jax

    jax.block_until_ready(fn(*args))
    with tempfile.TemporaryDirectory() as folder:
        jax.profiler.start_trace(folder)
        for _ in range(calls):
            jax.block_until_ready(fn(*args))
        jax.profiler.stop_trace()
        path = glob.glob(os.path.join(folder, "**", "*.trace.json.gz"), recursive=True)[0]
        with gzip.open(path) as trace:
            events = json.load(trace)["traceEvents"]
    times = collections.defaultdict(list)
    for event in events:
        if event.get("ph") == "X" and not event["name"].startswith(_NOT_LEAVES):
            times[event["name"]].append(event["dur"] / 1e3)
    return times


def profile(size, with_vertices, calls):
    """Rows (name, min ms, median ms, shape, target, op name, kind) of the program's
    thunks that ran once per call, slowest first; kind: 'cond', 'host', 'forward' or
    'reverse'."""
    fn, args = program(size, with_vertices)
    table = hlo_table(fn.lower(*args).compile().as_text())
    rows = []
    for name, times in thunk_times(fn, args, calls).items():
        if name not in table or len(times) != calls:
            continue
        shape, target, op = table[name]
        kind = ("cond" if name.startswith("cond") else "host" if target.startswith("diffshade")
                else "reverse" if "transpose(" in op else "forward")
        rows.append((name, min(times), statistics.median(times), shape, target, op, kind))
    return sorted(rows, key=lambda row: -row[1])


def _short(op):
    """The op name without the jitted function's own name (loss or <lambda>)."""
    return re.sub(r"^jit\([^)]*\)/", "", op)[-70:]


def print_profile(rows, top):
    print(f"{'min ms':>7s} {'med ms':>7s}  {'thunk':30s} {'shape':30s} target / op")
    for name, low, mid, shape, target, op, _ in rows[:top]:
        print(f"{low:7.2f} {mid:7.2f}  {name[:30]:30s} {shape[:30]:30s} "
              f"{target or _short(op)}")
    sums = collections.Counter()
    for row in rows:
        sums[row[6]] += row[1]
    print("sums of the minima (ms): " + ", ".join(
        f"{kind} {sums[kind]:.2f}" for kind in ("host", "forward", "reverse")) +
        f"; all leaf thunks {sums['host'] + sums['forward'] + sums['reverse']:.2f}")


def print_diff(material, vertices, top):
    """The vertices' program against the material's, per (thunk kind, shape, op name)."""
    def keyed(rows):
        out = collections.defaultdict(float)
        for name, low, _, shape, target, op, kind in rows:
            if kind != "cond":
                out[(re.sub(r"\.\d+$", "", name), shape, target or _short(op))] += low
        return out
    before, after = keyed(material), keyed(vertices)
    deltas = sorted(((after.get(k, 0.0) - before.get(k, 0.0), k) for k in set(before) | set(after)),
                    key=lambda d: -abs(d[0]))
    print(f"{'+ms':>7s}  {'thunk kind':28s} {'shape':30s} target / op")
    for delta, (name, shape, what) in deltas[:top]:
        print(f"{delta:+7.2f}  {name[:28]:28s} {shape[:30]:30s} {what}")
    print(f"in all: {sum(d for d, _ in deltas):+.2f} ms (sums of per-thunk minima)")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--program", choices=("forward", "material", "vertices"),
                        default="vertices")
    parser.add_argument("--calls", type=int, default=15)
    parser.add_argument("--top", type=int, default=40)
    parser.add_argument("--diff", action="store_true")
    args = parser.parse_args()
    print(f"judged scene at {args.size}^2; loadavg {os.getloadavg()[0]:.1f}; "
          f"{args.calls} traced calls")
    if args.diff:
        print_diff(profile(args.size, False, args.calls), profile(args.size, True, args.calls),
                   args.top)
    else:
        with_vertices = {"forward": None, "material": False, "vertices": True}[args.program]
        print_profile(profile(args.size, with_vertices, args.calls), args.top)


if __name__ == "__main__":
    main()

"""Peak memory of a cached fit against the number of views, with and without chunking.

Each point is one fresh process: a synthetic dataset of N views (data_synth.make_dataset:
an icosphere(3), one directional light per view, targets of SIZE^2 held in host memory),
then the fit as `fitting.fit` runs it (build_cache, fitting.solve.distribute.for_options,
start_run, advance, finish, fit_result), --method 'adam' or 'linear' (the default
method: a closed-form start, then Levenberg-Marquardt) for --steps steps, then the
report (standard errors and the misfit check), float32, on the CPU's one device:
- chunk 'none': today's path (one compiled loss over every view's cached pixels, a
  program that grows with the number of views);
- chunk 'all': the views stacked (fitting.solve.distribute) and taken in one chunk: all at
  once through one batched program;
- chunk C: the views streamed through that program C at a time, each chunk stacked
  from its own views when it is used, the gradient summed over chunks, then one update.
Measured, from /proc/self/status: VmRSS after the dataset is made (the targets and the
interpreter: the same for every mode), then the peak (VmHWM, reset with
/proc/self/clear_refs before each phase) while the cache is built, while the fit starts
(start_run: for 'linear' the closed-form start), while the steps run (their first step
compiles) and while the report is made (fitting.driver.fit_result: the uncertainty report and
the misfit check); the time of each phase, the step time (median of the steps after the
first) and the compile + first step. The parent watches every point's resident memory and ends
it above --max-gib (reported as such), so that a loaded, shared machine is not pushed
into swap or the OOM killer.

    python benchmarks/memory_views.py [--views 10,50,100,200] [--size 512]
        [--chunks none,all,8] [--steps 4] [--method adam|linear]
        [--json benchmarks/results/memory_views.json]
"""

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _status(field):
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024  # kB -> bytes
    raise RuntimeError(f"{field} not in /proc/self/status")


def _reset_peak():
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # resets VmHWM to the current RSS (Linux >= 4.0)


def point(views, size, chunk, steps, method="adam"):
    """Run one point in this process; returns its measurements (dict)."""
    import jax

    import diffshade as ds
    from data_synth import make_dataset
    from fitting import FitOptions, FitSpec
    from fitting.driver import fit_result
    from fitting.model import build_cache
    from fitting.run import advance, finish, start_run
    from fitting.solve.distribute import fit_data, for_options
    from fitting.spec.params import DEFAULT_INIT

    truth = ds.material(ka=0.15, kd=(0.55, 0.35, 0.25), ks=0.35, shininess=25.0)
    dataset = make_dataset(ds.icosphere(3), truth, n_views=views, n_lights=1, size=size)
    rss_dataset = _status("VmRSS")
    options = FitOptions(method=method, steps=steps, tol=0.0, chunk=chunk)
    _reset_peak()
    start = time.perf_counter()
    data = build_cache(dataset, DEFAULT_INIT, edge_margin=options.edge_margin)
    work = for_options(data, options)
    data = fit_data(work)
    jax.block_until_ready(jax.tree.leaves(data.views))
    cache_s = time.perf_counter() - start
    peak_cache = _status("VmHWM")
    rss_cache = _status("VmRSS")
    _reset_peak()
    start = time.perf_counter()
    state = start_run(work, FitSpec(), DEFAULT_INIT, options)
    start_s = time.perf_counter() - start
    peak_start = _status("VmHWM")
    _reset_peak()
    stamps = [time.perf_counter()]
    advance(state, work, on_step=lambda s: stamps.append(time.perf_counter()))
    finish(state, work)
    steps_s = time.perf_counter() - stamps[0]
    peak_steps = _status("VmHWM")
    times = [b - a for a, b in zip(stamps, stamps[1:], strict=False)]
    _reset_peak()
    start = time.perf_counter()
    result = fit_result(state, dataset, work)  # as fitting.fit: the views as the fit ran
    report_s = time.perf_counter() - start
    peak_report = _status("VmHWM")
    return {"views": views, "size": size, "chunk": chunk, "method": method,
            "steps": state.step, "peak_start": peak_start, "start_s": start_s,
            "peak_report": peak_report, "report_s": report_s,
            "misfit_rms": result.misfit.rms,
            "kept_pixels": int(sum(v.pixels.shape[0] for v in data.views)),
            "rss_dataset": rss_dataset, "peak_cache": peak_cache, "rss_cache": rss_cache,
            "peak_steps": peak_steps, "cache_s": cache_s,
            "first_step_s": times[0] if times else None,
            "steps_s": steps_s,
            "step_s": statistics.median(times[1:]) if len(times) > 1 else None,
            "loss": state.history[-1]}


def run_point(views, size, chunk, steps, max_bytes, timeout, method="adam"):
    """One point in a fresh process, its resident memory watched; returns its dict, or
    one saying why it has none."""
    argv = [sys.executable, os.path.abspath(__file__), "--point", str(views), str(size),
            str(chunk), str(steps), method]
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=env)
    start, high = time.monotonic(), 0
    while proc.poll() is None:
        try:
            with open(f"/proc/{proc.pid}/status") as f:
                rss = next(int(x.split()[1]) * 1024 for x in f if x.startswith("VmRSS:"))
        except (OSError, StopIteration):
            rss = 0
        high = max(high, rss)
        over = "memory" if rss > max_bytes else "time" if time.monotonic() - start > timeout \
            else None
        if over:
            proc.kill()
            proc.wait()
            return {"views": views, "size": size, "chunk": chunk, "stopped": over,
                    "seen_rss": high}
        time.sleep(0.2)
    out, err = proc.communicate()
    if proc.returncode != 0:
        return {"views": views, "size": size, "chunk": chunk,
                "stopped": f"exit {proc.returncode}: {err.strip().splitlines()[-1:]}"}
    return json.loads(out.strip().splitlines()[-1])


def _gib(x):
    return "—" if x is None else f"{x / 2**30:.2f}"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", default="10,50,100,200")
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--chunks", default="none,all,8",
                        help="comma-separated: none, all or C (module docstring)")
    parser.add_argument("--steps", type=int, default=4)
    parser.add_argument("--method", default="adam", choices=("adam", "linear"))
    parser.add_argument("--max-gib", type=float, default=9.0)
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds per point")
    parser.add_argument("--json", default=None)
    parser.add_argument("--point", nargs=5, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.point:
        views, size, chunk, steps, method = args.point
        chunk = None if chunk == "None" else int(views) if chunk == "all" else int(chunk)
        print(json.dumps(point(int(views), int(size), chunk, int(steps), method)))
        return
    rows = []
    for views in map(int, args.views.split(",")):
        for chunk in args.chunks.split(","):
            chunk = None if chunk == "none" else chunk if chunk == "all" else int(chunk)
            row = run_point(views, args.size, chunk, args.steps, args.max_gib * 2**30,
                            args.timeout, args.method)
            row["mode"] = "none" if chunk is None else chunk
            rows.append(row)
            print(json.dumps(row), flush=True)
    print(f"\n{args.size}^2, {args.method} {args.steps} steps, float32, 1 CPU device; GiB")
    print("| views | chunk | kept pixels | RSS with dataset | peak building cache | "
          "peak starting | peak in steps | peak in report | most - dataset | cache s | "
          "start s | steps s (compile + 1st) | step ms | report s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        chunk = r.get("mode", r["chunk"])
        if "stopped" in r:
            print(f"| {r['views']} | {chunk} | stopped ({r['stopped']}, RSS seen "
                  f"{_gib(r.get('seen_rss'))} GiB) |" + " |" * 11)
            continue
        step = "—" if r["step_s"] is None else f"{1e3 * r['step_s']:.0f}"
        first = "—" if r["first_step_s"] is None else f"{r['first_step_s']:.1f}"
        most = max(r["peak_cache"], r["peak_start"], r["peak_steps"], r["peak_report"])
        print(f"| {r['views']} | {chunk} | {r['kept_pixels']:,} | {_gib(r['rss_dataset'])} | "
              f"{_gib(r['peak_cache'])} | {_gib(r['peak_start'])} | {_gib(r['peak_steps'])} | "
              f"{_gib(r['peak_report'])} | {_gib(most - r['rss_dataset'])} | "
              f"{r['cache_s']:.1f} | {r['start_s']:.1f} | {r['steps_s']:.1f} ({first}) | {step} | "
              f"{r['report_s']:.1f} |")
    if args.json:
        sys.path.insert(0, ROOT)
        from benchmarks.common import write_results
        write_results(args.json, {"args": vars(args), "rows": rows})


if __name__ == "__main__":
    main()

"""The figure tables of README.md and the performance pages, printed from benchmarks/results.

Each table sits in its page between `<!-- figures:NAME:begin -->` and
`<!-- figures:NAME:end -->`, and is nothing but what this script prints from the newest
JSON each benchmark wrote, so a page cannot quote a figure its benchmark no longer gives:
tests/test_doc_figures.py checks every block against this script's output. After a
benchmark run, refresh the pages with

    python benchmarks/doc_figures.py --write          # rewrite every block
    python benchmarks/doc_figures.py [NAME ...]       # print blocks, change nothing

The tables state current values only; each benchmark's JSON also keeps the machine and
load it ran under, and benchmarks/results/history/ the dated record of earlier runs.
"""

import argparse
import contextlib
import io
import json
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RESULTS = os.path.join(ROOT, "benchmarks", "results")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import peers  # noqa: E402  (benchmarks/peers.py: its own table, beside this script)
import scaling  # noqa: E402  (benchmarks/scaling.py: its own table and cost model)


def load(name):
    """The parsed JSON of benchmarks/results/NAME."""
    with open(os.path.join(RESULTS, name)) as f:
        return json.load(f)


def ms(seconds):
    return f"{seconds * 1e3:.1f} ms"


def gib(nbytes):
    return f"{nbytes / 2**30:.2f}"


def percent(fraction):
    return f"{100 * fraction:.2g} %"


def ratio(theirs, ours):
    return f"{theirs / ours:.2f}×"


def cite(name):
    return f"[`{name}`](benchmarks/results/{name})"


# --- README.md ------------------------------------------------------------------------

def readme_rows(data):
    """[(what, figure, command)] of the README's table."""
    ours, theirs = data["peers.json"]["diffshade"], data["peers.json"]["mitsuba"]
    fwd, fb = theirs["forward"]["median_s"], theirs["forward_backward"]["median_s"]
    recovery = {c["label"]: c for c in data["fit_recovery.json"]["configs"]}
    first = data["time_to_first_result.json"]["fit"]
    fresh = data["time_to_first_result_fresh_install.json"]
    adam, linear = data["memory_views.json"]["rows"], data["memory_views_linear.json"]["rows"]
    views = " / ".join(str(r["views"]) for r in adam)
    peer_cmd = (f"`python benchmarks/peers.py --rounds {data['peers.json']['rounds']}` "
                "(needs `pip install '.[peers]'`), ")
    texture = data["texture_capture.json"]
    return [
        ("hard render of the judged scene (256², 5,120 faces, one directional light) "
         "against Mitsuba 3 (`llvm_ad_rgb`, 4 spp)",
         f"{ms(ours['hard_forward']['median_s'])}; Mitsuba {ms(fwd)} "
         f"({ratio(fwd, ours['hard_forward']['median_s'])} faster)",
         peer_cmd + cite("peers.json")),
        ("soft render (SoftRas, K = 8) of the same scene",
         f"{ms(ours['soft_forward']['median_s'])}; Mitsuba {ms(fwd)} "
         f"({ratio(fwd, ours['soft_forward']['median_s'])})", peer_cmd + cite("peers.json")),
        ("soft render + gradient: material / material and vertices",
         f"{ms(ours['soft_fb_material']['median_s'])} / "
         f"{ms(ours['soft_fb_material_vertices']['median_s'])}; Mitsuba's material gradient "
         f"{ms(fb)}", peer_cmd + cite("peers.json")),
        ("fit step on cached pixels (material, Adam): hard / soft geometry",
         f"{ms(ours['cached_step']['median_s'])} / {ms(ours['soft_cached_step']['median_s'])}",
         peer_cmd + cite("peers.json")),
        (f"recovery of {data['fit_recovery.json']['n']} random materials, "
         f"{data['fit_recovery.json']['size']}², 3 views × 2 lights, default method",
         f"worst error {percent(max(recovery['float']['worst'].values()))} (float targets), "
         f"{percent(max(recovery['8-bit']['worst'].values()))} (8-bit targets); "
         f"{recovery['float']['median_seconds_per_fit']:.2f} s per fit",
         "`python benchmarks/fit_recovery.py`, " + cite("fit_recovery.json")),
        ("time to first result: the first line above's `diffshade fit` as a fresh process, "
         "compilation cache warm / cold / off",
         f"{first['warm_median_wall_s']:.1f} / {first['cold_median_wall_s']:.1f} / "
         f"{first['off_median_wall_s']:.1f} s",
         "`python benchmarks/time_to_first_result.py --fit-only`, "
         + cite("time_to_first_result.json")),
        ("on a fresh install (empty numba and JAX caches): the first image (`diffshade render "
         "--builtin sphere`) / the first line above's `synth` and `fit` together",
         f"{fresh['first_image']['median_wall_s']:.1f} / "
         f"{fresh['main_job']['median_wall_s']:.1f} s (CPU "
         f"{fresh['first_image']['median_cpu_s']:.1f} / {fresh['main_job']['median_cpu_s']:.1f} s)",
         "`python benchmarks/time_to_first_result.py --fresh-install`, "
         + cite("time_to_first_result_fresh_install.json")),
        (f"peak memory of a fit against views ({views}), {adam[0]['size']}², chunks of "
         f"{adam[0]['chunk']}: Adam / default method",
         " / ".join(gib(r["peak_steps"]) for r in adam) + " GiB / "
         + " / ".join(gib(max(r["peak_start"], r["peak_report"])) for r in linear) + " GiB",
         "`python benchmarks/memory_views.py` (`--method linear`), "
         + cite("memory_views.json") + ", " + cite("memory_views_linear.json")),
        (f"a {texture['res']}² kd texture recovered (`fit --texture`) from Mitsuba 3's 8-bit "
         f"photos of a textured sphere, {len(texture['views'])} views, one held out",
         f"map PSNR {texture['map_psnr']['twice_wide']:.1f} dB over the texels seen twice and "
         f"two pixels wide; held-out view {texture['holdout']['psnr_linear']:.1f} dB "
         f"(8-bit allows {texture['holdout']['psnr_linear_8bit']:.1f} dB)",
         "`python benchmarks/texture_capture.py` (needs `pip install '.[peers]'`), "
         + cite("texture_capture.json")),
    ]


def readme(data):
    lines = ["| what | current figure | measure it yourself |", "|---|---|---|"]
    lines += [f"| {what} | {figure} | {command} |" for what, figure, command in readme_rows(data)]
    return "\n".join(lines)


# --- docs/performance.md ---------------------------------------------------------------

def peers_table(data):
    """peers.py's own table, and the compile times and versions it prints."""
    run = data["peers.json"]
    ours, theirs = run["diffshade"], run["mitsuba"]
    check = run["camera_check"]
    compile_s = ", ".join(f"{label} {ours[key]['compile_s']:.1f} s"
                          for key, label, _ in peers.ROWS if key in ours)
    return "\n".join([
        peers.table(ours, theirs), "",
        f"Compile (first call): diffshade {compile_s}; Mitsuba forward "
        f"{theirs['forward']['compile_s']:.1f} s, forward + backward "
        f"{theirs['forward_backward']['compile_s']:.1f} s. Mitsuba {theirs['mitsuba']} "
        f"(Dr.Jit {theirs['drjit']}, LLVM {theirs['llvm_version']}); camera check: mask IoU "
        f"{check['mask_iou']:.4f}, largest colour difference inside both masks "
        f"{check['max_interior_colour_diff']:.4f}. Median of the {run['rounds']} rounds' "
        f"medians of {run['repeats']} calls ([`peers.json`](../benchmarks/results/peers.json))."])


def scaling_table(data):
    """What `python benchmarks/scaling.py --from-json benchmarks/results/scaling.json`
    prints: its table and its cost model."""
    results = data["scaling.json"]["results"]
    model = io.StringIO()
    with contextlib.redirect_stdout(model):
        scaling.print_model(results)
    loads = [r["loadavg_1min"] for r in results if "loadavg_1min" in r]
    return "\n".join([
        scaling.table(results), "", "```text", model.getvalue().rstrip(), "```", "",
        f"{len(results)} points, one process each, at a load average of {min(loads):.0f}–"
        f"{max(loads):.0f} on {data['scaling.json']['meta']['cpus']} cores "
        "([`scaling.json`](../benchmarks/results/scaling.json), `loadavg_1min` per point)."])


def first_result(data):
    fit, compiled = data["time_to_first_result.json"]["fit"], data["fit_compile.json"]
    lines = ["| `diffshade fit out/data -o out/fit`, a fresh process | wall s | CPU s |",
             "|---|---|---|"]
    for key, label in (("warm", "warm: persistent cache and program store filled"),
                       ("cold", "cold: both empty, numba's kernels compiled too"),
                       ("off", "cache off: `DIFFSHADE_COMPILE_CACHE=0`")):
        lines.append(f"| {label} | {fit[f'{key}_median_wall_s']:.1f} | "
                     f"{fit[f'{key}_median_cpu_s']:.1f} |")
    lines.append(f"| XLA compilation alone, cold ({len(compiled['programs'])} programs) | "
                 f"{compiled['total_wall_s']:.2f} | {compiled['total_cpu_s']:.2f} |")
    biggest = sorted(compiled["programs"].items(), key=lambda p: -p[1]["cpu_s"])[:3]
    lines += ["", "Largest compilations: " + ", ".join(
        f"`{name.removeprefix('jit_')}` {p['cpu_s']:.2f} s" for name, p in biggest)
        + " of CPU ([`time_to_first_result.json`](../benchmarks/results/time_to_first_result.json),"
        " [`fit_compile.json`](../benchmarks/results/fit_compile.json))."]
    return "\n".join(lines)


# --- docs/many-views.md -----------------------------------------------------------------

def memory_adam(data):
    lines = ["| views | kept pixels | cache (56 B per kept pixel) | RSS with the dataset | "
             "peak while building | peak while stepping | step s |",
             "|---|---|---|---|---|---|---|"]
    for r in data["memory_views.json"]["rows"]:
        lines.append(f"| {r['views']} | {r['kept_pixels'] / 1e6:.2f} M | "
                     f"{gib(56 * r['kept_pixels'])} | {gib(r['rss_dataset'])} | "
                     f"{gib(r['peak_cache'])} | **{gib(r['peak_steps'])}** | {r['step_s']:.2f} |")
    return "\n".join(lines)


def memory_linear(data):
    lines = ["| views | RSS with the dataset | peak while building | peak in the closed-form "
             "start | peak in the report | start s | report s |", "|---|---|---|---|---|---|---|"]
    for r in data["memory_views_linear.json"]["rows"]:
        lines.append(f"| {r['views']} | {gib(r['rss_dataset'])} | {gib(r['peak_cache'])} | "
                     f"**{gib(r['peak_start'])}** | **{gib(r['peak_report'])}** | "
                     f"{r['start_s']:.0f} | {r['report_s']:.0f} |")
    return "\n".join(lines)


# --- docs/transforms.md -----------------------------------------------------------------

def kernel_paths(data):
    judged = data["transforms.json"]["judged"]
    baseline = data["transforms.json"]["meta"]["baseline"]
    labels = (("host", "default path (`kernels=\"host\"` on CPU)"),
              ("baseline", f"the code before the transform rules ({baseline}, custom VJPs)"),
              ("jax", "JAX path (`kernels=\"jax\"`) on CPU"))
    lines = ["| judged scene, soft | forward | forward + backward | compile (forward / f+b) |",
             "|---|---|---|---|"]
    for key, label in labels:
        f, b = judged[key]["forward"], judged[key]["forward_backward"]
        lines.append(f"| {label} | {ms(f['median_s'])} | {ms(b['median_s'])} | "
                     f"{f['compile_s']:.1f} s / {b['compile_s']:.1f} s |")
    return "\n".join(lines)


def batched_views(data):
    views = data["transforms.json"]["views"]
    parts = (("forward", "forward"), ("forward_backward", "forward + backward, vertices and kd"),
             ("material_forward_backward", "forward + backward, material (kd, ks)"))
    lines = ["| 4 views, 128² | Python loop | loop in one jit | batched | batched vs Python "
             "loop (each process) | work on one CPU | ceiling |", "|---|---|---|---|---|---|---|"]
    for key, label in parts:
        fastest = min(views["runs"], key=lambda r: r["batched"][key]["median_s"])
        work = min(r[form][key]["median_s"] for r in views["one_cpu_runs"] for form in r)
        speedups = " / ".join(f"{s['wall']:.2f}×" for s in views["speedup"][key]["python_loop"])
        lines.append(f"| {label} | {ms(fastest['python_loop'][key]['median_s'])} | "
                     f"{ms(fastest['loop'][key]['median_s'])} | "
                     f"{ms(fastest['batched'][key]['median_s'])} | {speedups} | {ms(work)} | "
                     f"{views['speedup'][key]['ceiling']:.2f}× |")
    return "\n".join(lines)


def search_batched(data):
    def cells(key):
        return " / ".join(f"{s['wall']:.2f}×" for s in
                          data["transforms.json"][key]["speedup"]["search"]["loop"])
    return (f"The host face search alone (`--only search`), one batched call against 4 calls: "
            f"{cells('search_default')} (each process), {cells('search_passive')} with "
            f"`OMP_WAIT_POLICY=passive`.")


# --- docs/textures.md ------------------------------------------------------------------

def texture_capture(data):
    """texture_capture.py's figures: the forward check, coverage, the map, the held-out
    view, times."""
    run = data["texture_capture.json"]
    check, c, held = run["forward_check"], run["coverage"], run["holdout"]
    ours, own = run["map_psnr"], run["map_psnr_own_8bit"]

    def span(key):
        values = [v[key] for v in check]
        return f"{min(values):.1f}–{max(values):.1f} dB"
    return "\n".join([
        "| figure | value |", "|---|---|",
        f"| forward check: diffshade's render with the true map against each photo, PSNR "
        f"linear (what 8-bit rounding allows) | {span('psnr_linear')} "
        f"({span('psnr_linear_8bit')}) |",
        f"| the same with the map upside down (the other v convention) | "
        f"{min(run['forward_check_v_flipped']):.1f}–{max(run['forward_check_v_flipped']):.1f} dB |",
        f"| texels of the {run['res']}² map seen by ≥ 2 / 1 / 0 fitted views | "
        f"{c['twice_or_more']:,} / {c['once']:,} / {c['unseen']:,} |",
        f"| recovered map against the truth, PSNR linear: texels seen by ≥ 2 views / those "
        f"of them at least two pixels wide ({c['twice_wide']:,}) | {ours['twice']:.1f} / "
        f"{ours['twice_wide']:.1f} dB |",
        f"| the same fit on diffshade's own 8-bit renders of the views | {own['twice']:.1f} / "
        f"{own['twice_wide']:.1f} dB |",
        f"| held-out view {held['view']} ({held['pixels']:,} pixels; {held['unseen_pixels']:,} "
        f"reading an unseen texel left out): PSNR linear / sRGB | {held['psnr_linear']:.1f} / "
        f"{held['psnr_srgb']:.1f} dB |",
        f"| what 8-bit rounding allows on those pixels: linear / sRGB | "
        f"{held['psnr_linear_8bit']:.1f} / {held['psnr_srgb_8bit']:.1f} dB |",
        f"| Mitsuba's {len(run['views'])} photos; "
        f"`diffshade fit --texture kd={run['res']} --fit kd` "
        f"(start to files written, {run['fit'].get('stencil_iterations', 0)} CG iterations "
        f"on the stencil, {run['fit']['iterations']} on the renders) | "
        f"{run['times']['photos_s']:.1f} s; {run['times']['fit_s']:.1f} s |"])


def texture_speed(data):
    record = data["textures.json"]
    fit, render = record["fit"], record["render"]
    lines = ["| | time | the issue's target |", "|---|---|---|",
             f"| a {fit['texels']}² kd map ({fit['unknowns']:,} unknowns) from {fit['views']} "
             f"views at {fit['size']}², warm | {fit['warm_s']:.1f} s (CPU {fit['warm_cpu_s']:.1f}"
             f" s): {fit['stencil_iterations']} CG iterations on the stencil, "
             f"{fit['iterations']} on the renders | ≤ 10 s |"]
    for row in render["rows"]:
        lines.append(f"| judged scene ({render['faces']:,} faces, {render['size']}², soft, K = "
                     f"{render['faces_per_pixel']}), {row['pass']}: with a {render['texels']}² kd "
                     f"texture / without | {row['textured_ms']:.1f} / {row['untextured_ms']:.1f}"
                     f" ms = {row['ratio']:.2f} (CPU {row['cpu_ratio']:.2f}) | ≤ 1.2 |")
    lines += ["", f"Load average {fit['load_before']:.1f} (fit) and {render['load_before']:.1f} "
              "(renders) at the start ([`textures.json`](../benchmarks/results/textures.json); "
              "`python benchmarks/textures.py`)."]
    return "\n".join(lines)


#: name: (page, function, the JSON files it reads)
BLOCKS = {
    "readme": ("README.md", readme, ("peers.json", "fit_recovery.json",
                                     "time_to_first_result.json",
                                     "time_to_first_result_fresh_install.json",
                                     "memory_views.json", "memory_views_linear.json",
                                     "texture_capture.json")),
    "peers": ("docs/performance.md", peers_table, ("peers.json",)),
    "scaling": ("docs/performance.md", scaling_table, ("scaling.json",)),
    "first-result": ("docs/performance.md", first_result,
                     ("time_to_first_result.json", "fit_compile.json")),
    "memory-adam": ("docs/many-views.md", memory_adam, ("memory_views.json",)),
    "memory-linear": ("docs/many-views.md", memory_linear, ("memory_views_linear.json",)),
    "kernel-paths": ("docs/transforms.md", kernel_paths, ("transforms.json",)),
    "batched-views": ("docs/transforms.md", batched_views, ("transforms.json",)),
    "search-batched": ("docs/transforms.md", search_batched, ("transforms.json",)),
    "texture-capture": ("docs/textures.md", texture_capture, ("texture_capture.json",)),
    "textures": ("docs/textures.md", texture_speed, ("textures.json",)),
}


def render(name, data=None):
    """The text of block NAME, from `data` ({file name: parsed JSON}) or the files."""
    _, make, files = BLOCKS[name]
    return make(data if data is not None else {f: load(f) for f in files})


def markers(name):
    return f"<!-- figures:{name}:begin -->", f"<!-- figures:{name}:end -->"


def block_in(text, name):
    """The text between block NAME's markers in a page (ValueError if they are missing)."""
    begin, end = markers(name)
    if text.count(begin) != 1 or text.count(end) != 1 or text.index(begin) > text.index(end):
        raise ValueError(f"page: expected one {begin} before one {end}")
    return text[text.index(begin) + len(begin):text.index(end)].strip("\n")


def replace_block(text, name, body):
    begin, end = markers(name)
    block_in(text, name)
    return text[:text.index(begin) + len(begin)] + "\n" + body + "\n" + text[text.index(end):]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*",
                        help=f"blocks to print (default: all of {list(BLOCKS)})")
    parser.add_argument("--write", action="store_true", help="rewrite the blocks in their pages")
    args = parser.parse_args(argv)
    unknown = sorted(set(args.names) - set(BLOCKS))
    if unknown:
        parser.error(f"names: got {unknown}; expected names from {list(BLOCKS)}")
    for name in args.names or BLOCKS:
        page, body = BLOCKS[name][0], render(name)
        if not args.write:
            print(f"{page} {markers(name)[0]}\n{body}\n")
            continue
        path = os.path.join(ROOT, page)
        with open(path) as f:
            text = f.read()
        updated = replace_block(text, name, body)
        if updated != text:
            with open(path, "w") as f:
                f.write(updated)
            print(f"wrote {page} ({name})")


if __name__ == "__main__":
    main()

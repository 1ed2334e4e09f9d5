"""The choices a user makes, each measured as error against time (issue 30, item 4).

    python benchmarks/accuracy_choices.py                      # every section
    python benchmarks/accuracy_choices.py --quick              # a subset, under a minute idle
    python benchmarks/accuracy_choices.py --sections kernels,gradients --plots docs/img

One section per choice (SECTIONS), each a list of rows with deterministic error columns
and time columns from common.time_settings (compile apart, warm-up until the time
settles, rounds interleaved across the section's settings; medians and quartiles). The
sections live in accuracy_choices_render.py and accuracy_choices_fitting.py, the plots in
accuracy_choices_plots.py; `tables` gives the markdown of docs/accuracy-vs-time.md's
"More choices" block (<!-- study:choices:begin --> ... <!-- study:choices:end -->).
"""

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy_choices_fitting as fitting_part  # noqa: E402
import accuracy_choices_plots as plots_part  # noqa: E402
import accuracy_choices_render as render_part  # noqa: E402
from common import finish_record, run_record, write_results  # noqa: E402

NAME = "choices"
OUT = "benchmarks/results/accuracy_choices.json"

SECTIONS = {
    "soft_overlap": render_part.soft_overlap,
    "kernels": render_part.kernels,
    "supersample_levels": render_part.supersample_levels,
    "gradients": render_part.gradients,
    "highlight_front": render_part.highlight_front,
    "soft_shadows": fitting_part.soft_shadows,
    "fit_effects": fitting_part.fit_effects,
    "fit_resolution": fitting_part.fit_resolution,
}

E = "{:.1e}"
TIME = "{:.1f}"
# per section: (title, one-line caption, [(key, header, format)])
TABLES = {
    "soft_overlap": (
        "Soft raster where faces overlap",
        "A torus (2,304 faces, 128², seen 35° above its plane), gamma 1e-4 (the default): "
        "each soft setting against the hard render of the same scene; times of the forward "
        "render and of the gradient of an MSE loss with respect to the material and to the "
        "vertices.",
        [("raster", "raster", "{}"), ("sigma", "sigma px²", "{}"), ("K", "K", "{}"),
         ("vs_hard_rmse_255", "vs hard RMSE /255", "{:.2f}"),
         ("vs_hard_highlight_rmse_255", "vs hard highlight RMSE /255", "{:.2f}"),
         ("fwd_ms", "fwd ms", TIME), ("fwd_bwd_ms", "grad material ms", TIME),
         ("fwd_bwd_vertices_ms", "grad vertices ms", TIME)]),
    "kernels": (
        "The kernels path",
        "The study's sphere (subdivision 4) rendered with kernels='host' and kernels='jax'; "
        "differing px: pixels whose colour differs from the host image's by more than "
        "1e-5.",
        [("size", "px", "{}"), ("raster", "raster", "{}"), ("kernels", "kernels", "{}"),
         ("differing_px", "differing px", "{}"), ("vs_host_max_abs", "max abs diff", "{:.1e}"),
         ("fwd_ms", "fwd ms", TIME), ("fwd_bwd_ms", "grad material ms", TIME),
         ("fwd_bwd_vertices_ms", "grad vertices ms", TIME)]),
    "supersample_levels": (
        "Supersampling at subdivisions 3 and 4",
        "render_supersampled (Phong) against the analytic sphere.",
        [("subdivisions", "subdiv", "{}"), ("faces", "faces", "{:,}"), ("size", "px", "{}"),
         ("factor", "factor", "{}"), ("rmse_255", "RMSE /255", "{:.2f}"),
         ("max_255", "max /255", "{:.1f}"),
         ("highlight_rmse_255", "highlight RMSE /255", "{:.2f}"), ("fwd_ms", "fwd ms", TIME)]),
    "gradients": (
        "Gradient accuracy",
        "The gradient of an MSE image loss (icosphere of subdivision 1, 32², against a "
        "perturbed material and mesh) against central differences in float64 (step "
        "1e-6): the relative error of the gradient vector, and the time of one gradient.",
        [("raster", "raster", "{}"), ("wrt", "with respect to", "{}"), ("dtype", "dtype", "{}"),
         ("parameters", "parameters", "{}"), ("rel_error", "relative error", E),
         ("grad_ms", "gradient ms", "{:.2f}")]),
    "highlight_front": (
        "The highlight-error frontier",
        "The mesh and supersample rows of the tables above that no other row beats in "
        "both highlight RMSE and forward time (their published times).",
        [("study", "table", "{}"), ("subdivisions", "subdiv", "{}"),
         ("shading", "shading", "{}"), ("size", "px", "{}"), ("factor", "factor", "{}"),
         ("highlight_rmse_255", "highlight RMSE /255", "{:.2f}"),
         ("rmse_255", "RMSE /255", "{:.2f}"), ("fwd_ms", "fwd ms", TIME)]),
    "soft_shadows": (
        "Soft-raster shadows",
        "The shadows section's sphere over a floor (128²): a floor pixel counts as "
        "shadowed when less than half its light reaches it; edge error px = wrong px / "
        "edge px, against the exact shadow.",
        [("raster", "raster", "{}"), ("sigma", "sigma px²", "{}"),
         ("shadow_softness", "shadow softness texels", "{}"), ("map", "map", "{}"),
         ("wrong_px", "wrong px", "{}"), ("edge_px", "edge px", "{}"),
         ("edge_error_px", "edge error px", "{:.3f}"), ("fwd_ms", "fwd ms", TIME)]),
    "fit_effects": (
        "Inside a fit: shadows, an area light, transparency, views and lights",
        "The linear solver (64²). shadows, area light: 2 views of the shadows section's "
        "sphere over a floor lit by the sun and a point light casting shadows (or a disk "
        "light of radius 0.5 in its place, targets with 64 samples), the model as given; "
        "transparency: 2 views of a box over a table (sun and a point light casting "
        "shadows), kd fitted from 0.5 with the rest known, the box opaque or of kt "
        "(0.35, 0.5, 0.65), kt known or fitted from 0.5 (the table's from 0.05); "
        "views × lights: the data_synth sphere under noise σ = 0.01 (seed 3).",
        [("case", "case", "{}"), ("model", "model", "{}"),
         ("n_views", "views", "{}"), ("n_lights", "lights per view", "{}"),
         ("images", "images", "{}"), ("max_rel_error", "max rel err", E),
         ("fit_ms", "fit ms", TIME)]),
    "fit_resolution": (
        "Image resolution for fitting",
        "The linear solver on the data_synth sphere (3 views × 2 lights) under noise "
        "σ = 0.01 or 8-bit rounding: median and largest error over the seeds; the time "
        "of one fit.",
        [("size", "px", "{}"), ("noise_std", "noise std", "{}"), ("quantized", "8-bit", "{}"),
         ("seeds", "seeds", "{}"), ("median_rel_error", "median rel err", E),
         ("max_rel_error", "max rel err", E), ("fit_ms", "fit ms", TIME)]),
}


def run(quick: bool = False, sections=tuple(SECTIONS)) -> dict:
    """{section: rows} for the sections named (quick: a subset of each, fewer rounds)."""
    rounds = 3 if quick else 7
    return {name: SECTIONS[name](quick, rounds) for name in sections}


def _cell(row, key, fmt):
    value = row.get(key)
    return "–" if value is None else fmt.format(value)


def table(rows, columns):
    """A markdown table; a column that no row has is left out, a missing cell is '–'."""
    columns = [c for c in columns if any(r.get(c[0]) is not None for r in rows)]
    lines = ["| " + " | ".join(h for _, h, _ in columns) + " |",
             "|" + "|".join("---:" for _ in columns) + "|"]
    lines += ["| " + " | ".join(_cell(r, k, f) for k, _, f in columns) + " |" for r in rows]
    return "\n".join(lines)


def tables(results: dict) -> str:
    """The markdown of the doc block: per section present, a title, its caption and table."""
    parts = []
    for name, (title, caption, columns) in TABLES.items():
        if name in results:
            parts.append(f"#### {title}\n\n{caption}\n\n{table(results[name], columns)}")
    return "\n\n".join(parts)


def plots(results: dict, folder: str) -> list:
    """The PNG of each section present: folder/accuracy_choices_<section>.png."""
    return plots_part.draw_all(results, folder)


def _kept(path, quick, sections):
    """(the sections of an earlier run at `path`, same --quick, that this run does not
    redo; the run records of the runs they come from, which the JSON keeps in
    "earlier_runs")."""
    old = json.loads(Path(path).read_text()) if Path(path).exists() else {}
    if old.get("quick") != quick:
        return {}, []
    kept = {name: old[name] for name in SECTIONS if name in old and name not in sections}
    return kept, (old.get("earlier_runs", []) + [old["run"]]) if kept else []


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a subset of every section")
    parser.add_argument("--out", default=OUT)
    parser.add_argument("--plots", default=None, help="folder for the PNG plots")
    parser.add_argument("--sections", default=",".join(SECTIONS),
                        help=f"comma-separated, from {', '.join(SECTIONS)}")
    args = parser.parse_args(argv)
    sections = [s for s in args.sections.split(",") if s]
    unknown = [s for s in sections if s not in SECTIONS]
    if unknown:
        parser.error(f"--sections: got {unknown}; expected names from {list(SECTIONS)}")
    record = run_record()
    results = run(args.quick, sections)
    kept, earlier = _kept(args.out, args.quick, sections)
    write_results(args.out, {"benchmark": NAME, "quick": args.quick, **kept, **results,
                             "run": {**finish_record(record), "sections": sections},
                             "earlier_runs": earlier})
    print(tables(results))
    if args.plots:
        for path in plots(results, args.plots):
            print(f"wrote {path}")
    return results


if __name__ == "__main__":
    main()

"""Markdown tables of the accuracy-versus-time results, for docs/accuracy-vs-time.md.

    python benchmarks/accuracy_tables.py benchmarks/results/accuracy_vs_time.json
"""

import json
import sys

from accuracy_vs_time import FITTING_TABLES, cheapest_within

MESH = [("subdivisions", "subdiv", "{}"), ("faces", "faces", "{:,}"), ("shading", "shading", "{}"),
        ("size", "px", "{}"),
        ("rmse_255", "RMSE /255", "{:.2f}"), ("max_255", "max /255", "{:.1f}"),
        ("highlight_rmse_255", "highlight RMSE /255", "{:.2f}"), ("fwd_ms", "fwd ms", "{:.1f}"),
        ("fwd_bwd_ms", "fwd+bwd ms", "{:.1f}"), ("compile_s", "compile s", "{:.1f}")]


FITTING_TITLES = {
    "steps": "Adam against its step count (no stopping rule; 128², 3 views × 2 lights)",
    "method": "Adam to its stopping rule against the linear solver (same data)",
    "scaling": "the linear solver against resolution and views (noise-free targets)",
    "noise": ("the linear solver on noisy or 8-bit targets against views (median and "
              "largest error over the seeds)"),
    "mismatch": ("targets from a finer mesh and Phong shading than the fit's (linear "
                 "solver, 128², 3 views × 2 lights)"),
    "cache": "the fragment cache (one Adam step, 128², 6 images)",
    "fresh": ("compile time in a fresh process (DIFFSHADE_COMPILE_CACHE=0; 128², 3 views × "
              "2 lights)"),
}


def table(rows, columns):
    head = "| " + " | ".join(h for _, h, _ in columns) + " |"
    rule = "|" + "|".join("---:" for _ in columns) + "|"
    body = ["| " + " | ".join(f.format(r[k]) if k in r else "" for k, _, f in columns) + " |"
            for r in rows]
    return "\n".join([head, rule, *body])


def with_faces(rows):
    """The rows with the icosphere's face count (20 * 4**subdivisions)."""
    return [{**r, "faces": 20 * 4 ** r["subdivisions"]} for r in rows]


def sections(results):
    measured = results.get("measured", {})
    if measured:
        yield "When each section was measured:\n\n" + "\n".join(
            f"- {name}: " + (m["note"] if "note" in m else
                             f"{m['start_utc']} UTC, {m['minutes']} min, load average "
                             f"{m['load_before']} before and {m['load_after']} after")
            for name, m in measured.items())
    mesh = with_faces(sorted(results["mesh"],
                             key=lambda r: (r["size"], r["shading"], r["subdivisions"])))
    yield "### Mesh vs analytic sphere\n\n" + table(mesh, MESH + [("pareto", "Pareto", "{}")])
    yield ("### Supersampling (Phong, subdivision 5: 20,480 faces)\n\n"
           + table(results["supersample"], [
               ("size", "px", "{}"), ("factor", "factor", "{}"),
               ("silhouette_rmse_255", "silhouette RMSE /255", "{:.2f}")] + MESH[4:]))
    yield ("### Soft rasterization (Phong, subdivision 4: 5,120 faces)\n\n"
           + table(results["soft"], [
               ("size", "px", "{}"), ("sigma", "sigma px²", "{}"), ("gamma", "gamma", "{}"),
               ("K", "K", "{}"), ("vs_hard_rmse_255", "vs hard RMSE /255", "{:.2f}")]
               + MESH[4:]))
    yield ("### float32 vs float64 (Phong, subdivision 5: 20,480 faces)\n\n"
           + table(results["precision"], [("dtype", "dtype", "{}")] + MESH[3:]))
    if "fitting" in results:
        for title, columns in FITTING_TABLES:
            chosen = [r for r in results["fitting"] if r["study"] == title]
            if chosen:
                yield f"### Fitting: {FITTING_TITLES[title]}\n\n" + table(chosen, columns)
    for bound in (0.5, 1.0, 2.0):
        best = cheapest_within(results["mesh"] + results["supersample"], bound)
        yield (f"Cheapest within {bound}/255 RMSE: " + ("none" if best is None else
               f"{best['study']}, subdivision {best['subdivisions']}, {best['shading']}, "
               f"{best['size']} px, supersampling x{best.get('factor', 1)}: "
               f"{best['fwd_ms']:.1f} ms forward, RMSE {best['rmse_255']:.2f}/255"))


if __name__ == "__main__":
    with open(sys.argv[1], encoding="utf-8") as file:
        print("\n\n".join(sections(json.load(file))))

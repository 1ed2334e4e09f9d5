"""Markdown tables of the accuracy-versus-time results, for docs/accuracy-vs-time.md.

    python benchmarks/accuracy_tables.py benchmarks/results/accuracy_vs_time.json
"""

import json
import sys

from accuracy_vs_time import cheapest_within

MESH = [("subdivisions", "subdiv", "{}"), ("shading", "shading", "{}"), ("size", "px", "{}"),
        ("rmse_255", "RMSE /255", "{:.2f}"), ("max_255", "max /255", "{:.1f}"),
        ("highlight_rmse_255", "highlight RMSE /255", "{:.2f}"), ("fwd_ms", "fwd ms", "{:.1f}"),
        ("fwd_bwd_ms", "fwd+bwd ms", "{:.1f}"), ("compile_s", "compile s", "{:.1f}")]


def table(rows, columns):
    head = "| " + " | ".join(h for _, h, _ in columns) + " |"
    rule = "|" + "|".join("---:" for _ in columns) + "|"
    body = ["| " + " | ".join(f.format(r[k]) if k in r else "" for k, _, f in columns) + " |"
            for r in rows]
    return "\n".join([head, rule, *body])


def sections(results):
    mesh = sorted(results["mesh"], key=lambda r: (r["size"], r["shading"], r["subdivisions"]))
    yield "### Mesh vs analytic sphere\n\n" + table(mesh, MESH + [("pareto", "Pareto", "{}")])
    yield "### Supersampling\n\n" + table(results["supersample"], [
        ("size", "px", "{}"), ("factor", "factor", "{}"),
        ("silhouette_rmse_255", "silhouette RMSE /255", "{:.2f}")] + MESH[3:])
    yield "### Soft rasterization (Phong, subdivision 4)\n\n" + table(results["soft"], [
        ("size", "px", "{}"), ("sigma", "sigma px²", "{}"), ("gamma", "gamma", "{}"),
        ("K", "K", "{}"), ("vs_hard_rmse_255", "vs hard RMSE /255", "{:.2f}")] + MESH[3:])
    yield "### float32 vs float64 (Phong, subdivision 5)\n\n" + table(results["precision"], [
        ("dtype", "dtype", "{}")] + MESH[2:])
    if "fitting" in results:
        rows = results["fitting"]
        pick = lambda s: [r for r in rows if r["study"] == s]
        yield "### Fitting\n\n" + table(pick("steps") + pick("method"), [
            ("study", "study", "{}"), ("method", "method", "{}"), ("steps", "steps", "{}"),
            ("wall_s", "wall s", "{:.2f}"), ("max_rel_error", "max rel. error", "{:.1e}")])
        yield table(pick("scaling"), [
            ("size", "px", "{}"), ("views", "views", "{}"), ("quantized", "8-bit", "{}"),
            ("wall_s", "wall s", "{:.2f}"), ("compile_s", "compile s", "{:.1f}"),
            ("max_rel_error", "max rel. error", "{:.1e}")])
        yield table(pick("cache"), [("path", "loss path", "{}"), ("step_ms", "step ms", "{:.2f}"),
                                    ("compile_s", "compile s", "{:.1f}")])
    for bound in (0.5, 1.0, 2.0):
        best = cheapest_within(results["mesh"] + results["supersample"], bound)
        yield (f"Cheapest within {bound}/255 RMSE: " + ("none" if best is None else
               f"{best['study']}, subdivision {best['subdivisions']}, {best['shading']}, "
               f"{best['size']} px, supersampling x{best.get('factor', 1)}: "
               f"{best['fwd_ms']:.1f} ms forward, RMSE {best['rmse_255']:.2f}/255"))


if __name__ == "__main__":
    with open(sys.argv[1], encoding="utf-8") as file:
        print("\n\n".join(sections(json.load(file))))

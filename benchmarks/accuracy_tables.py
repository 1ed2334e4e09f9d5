"""Markdown tables of the accuracy-versus-time study, for docs/accuracy-vs-time.md.

    python benchmarks/accuracy_tables.py benchmarks/results/accuracy_vs_time.json
    python benchmarks/accuracy_tables.py --choose     # the "choose your settings" table

The page's generated blocks are written by `python benchmarks/accuracy_study.py --docs`;
this module holds the accuracy_vs_time tables and the "choose your settings" table, which
reads every study's JSON. Time columns give the median ("fwd ms") and the quartiles of the
interleaved rounds ("fwd spread ms": q1–q3; empty for rows measured before that protocol).
"""

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import spread, with_spreads  # noqa: E402

MESH = [("subdivisions", "subdiv", "{}"), ("faces", "faces", "{:,}"), ("shading", "shading", "{}"),
        ("size", "px", "{}"),
        ("rmse_255", "RMSE /255", "{:.2f}"), ("max_255", "max /255", "{:.1f}"),
        ("highlight_rmse_255", "highlight RMSE /255", "{:.2f}"), ("fwd_ms", "fwd ms", "{:.1f}"),
        ("fwd_spread", "fwd spread ms", "{}"),
        ("fwd_bwd_ms", "fwd+bwd ms", "{:.1f}"), ("fwd_bwd_spread", "fwd+bwd spread ms", "{}"),
        ("compile_s", "compile s", "{:.1f}")]


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
    """A markdown table of `rows` (dicts); a key a row lacks, or None, is an empty cell."""
    head = "| " + " | ".join(h for _, h, _ in columns) + " |"
    rule = "|" + "|".join("---:" for _ in columns) + "|"
    body = ["| " + " | ".join("" if r.get(k) is None else f.format(r[k])
                              for k, _, f in columns) + " |" for r in rows]
    return "\n".join([head, rule, *body])


def with_faces(rows):
    """The rows with the icosphere's face count (20 * 4**subdivisions)."""
    return [{**r, "faces": 20 * 4 ** r["subdivisions"]} for r in rows]


def sections(results):
    """The accuracy_vs_time tables, one markdown section each."""
    from accuracy_vs_time import FITTING_TABLES
    mesh = with_faces(sorted(results["mesh"],
                             key=lambda r: (r["size"], r["shading"], r["subdivisions"])))
    yield ("### Mesh vs analytic sphere\n\n"
           + table(with_spreads(mesh), MESH + [("pareto", "Pareto", "{}")]))
    yield ("### Supersampling (Phong, subdivision 5: 20,480 faces)\n\n"
           + table(with_spreads(results["supersample"]), [
               ("size", "px", "{}"), ("factor", "factor", "{}"),
               ("silhouette_rmse_255", "silhouette RMSE /255", "{:.2f}")] + MESH[4:]))
    yield ("### Soft rasterization (Phong, subdivision 4: 5,120 faces)\n\n"
           + table(with_spreads(results["soft"]), [
               ("size", "px", "{}"), ("sigma", "sigma px²", "{}"), ("gamma", "gamma", "{}"),
               ("K", "K", "{}"), ("vs_hard_rmse_255", "vs hard RMSE /255", "{:.2f}")]
               + MESH[4:]))
    yield ("### float32 vs float64 (Phong, subdivision 5: 20,480 faces)\n\n"
           + table(with_spreads(results["precision"]), [("dtype", "dtype", "{}")] + MESH[3:]))
    if "fitting" in results:
        for title, columns in FITTING_TABLES:
            chosen = [r for r in results["fitting"] if r["study"] == title]
            if chosen:
                yield (f"### Fitting: {FITTING_TITLES[title]}\n\n"
                       + table(with_spreads(chosen), columns))


def vs_time_tables(results):
    """The doc block of accuracy_vs_time: every table of its JSON."""
    return "\n\n".join(sections(results))


# "Choose your settings": per target, candidate rows from the studies' JSON ({study NAME:
# results}). A candidate is {"setting", "from" (the table it is a row of), "time_ms",
# "time" (its text), and the error keys}. A study that measures more settings for a target
# adds a function to that target's list.

def _render_setting(row):
    factor = row.get("factor", 1)
    setting = (f"subdivision {row['subdivisions']}, {row.get('shading', 'phong')}, "
               f"{row['size']} px")
    if row["study"] == "soft":
        setting += f", soft raster σ {row['sigma']} γ {row['gamma']} K {row['K']}"
    return setting + (f", {factor}× supersampling" if factor > 1 else "")


RENDER_TABLES = {"mesh": "Mesh vs analytic sphere", "supersample": "Supersampling",
                 "soft": "Soft rasterization"}


def _forward_time(row):
    quartiles = spread(row, "fwd")
    return f"{row['fwd_ms']:.1f} ms forward" + (f" ({quartiles})" if quartiles else "")


def render_candidates(studies):
    """Every hard, supersampled and soft render of the study's sphere scene, the
    supersampling rows of "More choices" (subdivisions 3 and 4) included."""
    results = studies.get("vs_time", {})
    rows = [{**row, "from": RENDER_TABLES[study]}
            for study in RENDER_TABLES for row in results.get(study, [])]
    rows += [{**row, "study": "supersample", "from": "Supersampling at subdivisions 3 and 4",
              "fwd_q1_ms": row["fwd_iqr_ms"][0], "fwd_q3_ms": row["fwd_iqr_ms"][1]}
             for row in studies.get("choices", {}).get("supersample_levels", [])]
    return [{**row, "setting": _render_setting(row), "time_ms": row["fwd_ms"],
             "time": _forward_time(row)} for row in rows]


def fit_8bit_candidates(studies):
    """The linear solver on noise-free 8-bit targets (error: the largest over the seeds)."""
    rows = studies.get("vs_time", {}).get("fitting", [])
    return [{**row, "setting": f"linear solver, {row['size']} px, {row['views']} views",
             "from": "Fitting: noisy or 8-bit targets", "time_ms": 1e3 * row["wall_s"],
             "time": f"{row['wall_s']:.2f} s per fit"}
            for row in rows if row["study"] == "noise" and row["quantized"]
            and row["noise_std"] == 0.0]


TARGETS = [
    ("highlight within 1/255 (RMSE inside the highlight)", "highlight_rmse_255", 1.0,
     "{:.2f}/255", [render_candidates]),
    ("whole image within 2/255 (RMSE)", "rmse_255", 2.0, "{:.2f}/255", [render_candidates]),
    ("whole image within 1/255 (RMSE)", "rmse_255", 1.0, "{:.2f}/255", [render_candidates]),
    ("whole image within 0.5/255 (RMSE)", "rmse_255", 0.5, "{:.2f}/255", [render_candidates]),
    ("material within 1e-3 from 8-bit targets (largest relative error over the seeds)",
     "max_rel_error", 1e-3, "{:.1e}", [fit_8bit_candidates]),
]


def cheapest(candidates, error_key, bound):
    """The fastest candidate whose error is within `bound`, or None."""
    ok = [c for c in candidates if c[error_key] <= bound]
    return min(ok, key=lambda c: c["time_ms"]) if ok else None


def choose_table(studies):
    """The "choose your settings" table: per target error, the cheapest measured settings
    that meet it, their time and the table the row comes from ("none measured" where no
    row meets it)."""
    rows = []
    for label, key, bound, fmt, sources in TARGETS:
        best = cheapest([c for source in sources for c in source(studies)], key, bound)
        rows.append({"target": label, "setting": "none measured"} if best is None else
                    {"target": label, "setting": best["setting"], "time": best["time"],
                     "error": fmt.format(best[key]), "from": best["from"]})
    return table(rows, [("target", "target", "{}"), ("setting", "cheapest measured settings",
                                                     "{}"),
                        ("time", "time: median (q1–q3)", "{}"), ("error", "its error", "{}"),
                        ("from", "row of the table", "{}")])


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv == ["--choose"]:
        from accuracy_study import load_published
        print(choose_table(load_published()))
        return
    with open(argv[0], encoding="utf-8") as file:
        print(vs_time_tables(json.load(file)))


if __name__ == "__main__":
    main()

"""Plots of the accuracy-versus-time study: error against time on log axes, Pareto front
marked. Used by accuracy_vs_time.py --plots and notebooks/03_accuracy_vs_time.ipynb."""

from pathlib import Path

from matplotlib.figure import Figure

MARKERS = {"flat": "s", "gouraud": "^", "phong": "o"}


def _front(points):
    """The Pareto front (lower-left staircase) of (time, error) points, sorted by time."""
    front, best = [], float("inf")
    for t, e in sorted(points):
        if e < best:
            front.append((t, e))
            best = e
    return front


def _axes(ax, title, xlabel, ylabel):
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_title(title)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both", alpha=0.3)


def plot_mesh(ax, rows, time_key="fwd_ms"):
    """RMSE vs forward time per (shading, size), subdivision as the line's points."""
    for mode in sorted({r["shading"] for r in rows}):
        for size in sorted({r["size"] for r in rows}):
            sel = sorted((r for r in rows if r["shading"] == mode and r["size"] == size),
                         key=lambda r: r["subdivisions"])
            ax.plot([r[time_key] for r in sel], [r["rmse_255"] for r in sel],
                    marker=MARKERS.get(mode, "o"), alpha=0.7, label=f"{mode} {size}px")
    front = _front([(r[time_key], r["rmse_255"]) for r in rows])
    ax.plot(*zip(*front, strict=True), "k--", lw=1.5, label="Pareto front")
    ax.axhline(1.0, color="gray", lw=0.8)
    _axes(ax, "mesh vs analytic sphere", f"{time_key} (ms)", "RMSE (1/255)")
    ax.legend(fontsize=6, ncol=2)


def plot_generic(ax, rows, label_keys, title, error_key="rmse_255", time_key="fwd_ms"):
    for r in rows:
        ax.scatter(r[time_key], r[error_key], s=18)
        ax.annotate(" ".join(f"{k}={r[k]}" for k in label_keys), (r[time_key], r[error_key]),
                    fontsize=5)
    front = _front([(r[time_key], r[error_key]) for r in rows])
    ax.plot(*zip(*front, strict=True), "k--", lw=1.2)
    _axes(ax, title, f"{time_key} (ms)", f"{error_key}")


def plot_fitting(ax, rows):
    """Adam's error at its checkpoints (iterate and best loss) and the linear solver's."""
    steps = sorted((r for r in rows if r["study"] == "steps"), key=lambda r: r["wall_s"])
    if steps:
        ax.plot([r["wall_s"] for r in steps], [r["max_rel_error"] for r in steps], "o-",
                label="Adam, current iterate")
        ax.plot([r["wall_s"] for r in steps], [r["best_rel_error"] for r in steps], "s--",
                label="Adam, lowest loss so far (what fit returns)")
    linear = [r for r in rows if r["study"] in ("method", "scaling") and r["method"] == "linear"]
    ax.scatter([r["wall_s"] for r in linear], [r["max_rel_error"] for r in linear], marker="*",
               s=120, color="C3", label="linear solver (noise-free targets)")
    _axes(ax, "fitting: parameter error vs wall time", "wall time (s)",
          "max relative error")
    ax.legend(fontsize=7)


def plot_noise(ax, rows):
    """The linear solver's median error against the number of views, per target kind."""
    for key in sorted({(r["size"], r["noise_std"], r["quantized"]) for r in rows
                       if r["study"] == "noise"}):
        sel = sorted((r for r in rows if r["study"] == "noise"
                      and (r["size"], r["noise_std"], r["quantized"]) == key),
                     key=lambda r: r["views"])
        size, noise, quantized = key
        label = f"{size}px " + ("8-bit" if quantized else f"noise {noise}")
        ax.plot([r["views"] for r in sel], [r["median_rel_error"] for r in sel], "o-",
                label=label)
    clean = sorted((r for r in rows if r["study"] == "scaling" and r["size"] == 128),
                   key=lambda r: r["views"])
    if clean:
        ax.plot([r["views"] for r in clean], [r["max_rel_error"] for r in clean], "k:",
                label="128px noise-free")
    _axes(ax, "fitting: error vs views (linear solver)", "views (× 2 lights)",
          "median max relative error")
    ax.legend(fontsize=7)


def draw_all(results, folder):
    """Write accuracy_*.png into folder; returns the paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    panels = [("mesh", lambda ax: plot_mesh(ax, results["mesh"])),
              ("mesh_grad", lambda ax: plot_mesh(ax, results["mesh"], "fwd_bwd_ms")),
              ("supersample", lambda ax: plot_generic(ax, results["supersample"],
                                                      ("size", "factor"), "supersampling")),
              ("soft", lambda ax: plot_generic(ax, results["soft"], ("sigma", "gamma", "K"),
                                               "soft rasterization", "rmse_255",
                                               "fwd_bwd_ms"))]
    if "fitting" in results:
        panels.append(("fitting", lambda ax: plot_fitting(ax, results["fitting"])))
        panels.append(("noise", lambda ax: plot_noise(ax, results["fitting"])))
    for name, draw in panels:
        # a bare Figure needs no GUI backend (scripts, CI, notebooks alike)
        fig = Figure(figsize=(6, 4.5), dpi=120)
        draw(fig.add_subplot())
        fig.tight_layout()
        path = folder / f"accuracy_{name}.png"
        fig.savefig(path)
        paths.append(str(path))
    return paths

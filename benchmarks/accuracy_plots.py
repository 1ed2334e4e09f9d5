"""Plots of the accuracy-versus-time study: error against time on log axes, Pareto front
dashed. Used by accuracy_vs_time.py --plots and notebooks/03_accuracy_vs_time.ipynb.

Settings are told apart by colour, marker and fill, each explained once in a legend beside
the axes, not by text at every point (which overlaps where points crowd) nor by a colour
per line (the colour cycle has ten)."""

import math
from pathlib import Path

from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

AXIS_LABELS = {"fwd_ms": "time per render, forward (ms)",
               "fwd_bwd_ms": "time per render, forward + backward (ms)",
               "rmse_255": "RMSE against the reference (1/255 units)"}
# how one value of a setting reads in a legend
VALUE_LABELS = {"size": "{} px image", "factor": "{}×{} samples per pixel",
                "sigma": "σ = {} px²", "gamma": "γ = {}", "K": "K = {} faces per pixel",
                "shading": "{} shading"}
COLOURS = ["C0", "C1", "C2", "C3", "C4", "C5"]
MARKERS = ["o", "s", "^", "D", "v", "P"]
FILLS = [True, False]
SHADING_NAMES = {"flat": "flat", "gouraud": "Gouraud", "phong": "Phong"}


def _front(points):
    """The Pareto front (lower-left staircase) of (time, error) points, sorted by time."""
    front, best = [], float("inf")
    for t, e in sorted(points):
        if e < best:
            front.append((t, e))
            best = e
    return front


def _value_label(key, value):
    text = SHADING_NAMES.get(value, value) if key == "shading" else value
    return VALUE_LABELS.get(key, f"{key} = {{}}").format(text, text)


def _plain_log_ticks(axis, low, high):
    """Ticks at 1, 2, 5 × 10^k written as plain numbers, where the range is under three
    decades (beyond, the default 10^k labels read better) and holds at least two of them
    (in a narrower one matplotlib's default labels its minor ticks)."""
    decades = range(math.floor(math.log10(low)), math.ceil(math.log10(high)) + 1)
    ticks = [m * 10.0**k for k in decades for m in (1, 2, 5) if low <= m * 10.0**k <= high]
    if high / low < 1e3 and len(ticks) >= 2:
        axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        axis.set_minor_formatter(NullFormatter())


def _axes(ax, title, xlabel, ylabel):
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_title(title)
    ax.set_xlabel(AXIS_LABELS.get(xlabel, xlabel))
    ax.set_ylabel(AXIS_LABELS.get(ylabel, ylabel))
    ax.grid(True, which="both", alpha=0.3)
    _plain_log_ticks(ax.xaxis, *ax.get_xlim())
    _plain_log_ticks(ax.yaxis, *ax.get_ylim())


def _legend(ax, handles):
    """The legend beside the axes, where it hides no point."""
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=8,
              frameon=False)


def _key(handles, label, **style):
    handles.append(Line2D([], [], label=label, **style))


def _front_line(ax, rows, time_key, error_key):
    front = _front([(r[time_key], r[error_key]) for r in rows])
    ax.plot(*zip(*front, strict=True), "k--", lw=1.2, zorder=3)
    return Line2D([], [], color="k", ls="--", lw=1.2, label="Pareto front")


def plot_mesh(ax, rows, time_key="fwd_ms"):
    """RMSE vs time per (shading, size): colour the image size, marker the shading mode;
    the points of a line are the icosphere's subdivisions, coarsest (slowest-moving) first."""
    modes = sorted({r["shading"] for r in rows})
    sizes = sorted({r["size"] for r in rows})
    for mode, marker in zip(modes, MARKERS, strict=False):
        for size, colour in zip(sizes, COLOURS, strict=False):
            sel = sorted((r for r in rows if r["shading"] == mode and r["size"] == size),
                         key=lambda r: r["subdivisions"])
            ax.plot([r[time_key] for r in sel], [r["rmse_255"] for r in sel], color=colour,
                    marker=marker, ms=5, lw=1.0, alpha=0.8)
    handles = [_front_line(ax, rows, time_key, "rmse_255")]
    ax.axhline(1.0, color="gray", lw=0.8)
    _key(handles, "1/255: one 8-bit step", color="gray", lw=0.8)
    for size, colour in zip(sizes, COLOURS, strict=False):
        _key(handles, _value_label("size", size), color=colour, lw=2)
    for mode, marker in zip(modes, MARKERS, strict=False):
        _key(handles, _value_label("shading", mode), color="k", marker=marker, ls="none")
    _axes(ax, "mesh against the analytic sphere", time_key, "rmse_255")
    _legend(ax, handles)


def _styles(rows, keys):
    """Per key, value -> how its points look: the first key's values get colours, the
    second's markers, the third's filled or open markers."""
    kinds = ([{"color": c} for c in COLOURS], [{"marker": m} for m in MARKERS],
             [{"filled": f} for f in FILLS])
    if len(keys) > len(kinds):
        raise ValueError(f"label_keys: got {keys}; expected at most {len(kinds)} keys")
    styles = {}
    for key, kind in zip(keys, kinds, strict=False):
        values = sorted({r[key] for r in rows})
        if len(values) > len(kind):
            raise ValueError(f"rows: {len(values)} values of {key!r} ({values}); this plot "
                             f"tells apart at most {len(kind)}")
        styles[key] = dict(zip(values, kind, strict=False))
    return styles


def _look(style):
    """Line2D keywords of a point: black filled circle unless the style says otherwise."""
    colour = style.get("color", "k")
    return {"ls": "none", "ms": 7, "color": colour, "marker": style.get("marker", "o"),
            "mfc": colour if style.get("filled", True) else "white"}


def plot_generic(ax, rows, label_keys, title, error_key="rmse_255", time_key="fwd_ms"):
    """Error vs time of every row; label_keys name the settings told apart by colour,
    marker and (for a third) filled or open markers, in that order."""
    styles = _styles(rows, label_keys)
    for r in rows:
        style = {}
        for key, values in styles.items():
            style.update(values[r[key]])
        ax.plot(r[time_key], r[error_key], **_look(style))
    handles = [_front_line(ax, rows, time_key, error_key)]
    for key, values in styles.items():
        for value, style in values.items():
            _key(handles, _value_label(key, value), **_look(style))
    _axes(ax, title, time_key, error_key)
    _legend(ax, handles)


def plot_fitting(ax, rows):
    """Adam's error at its checkpoints (iterate and best loss) and the linear solver's."""
    steps = sorted((r for r in rows if r["study"] == "steps"), key=lambda r: r["wall_s"])
    if steps:
        ax.plot([r["wall_s"] for r in steps], [r["max_rel_error"] for r in steps], "o-",
                label="Adam, current iterate")
        ax.plot([r["wall_s"] for r in steps], [r["best_rel_error"] for r in steps], "s--",
                label="Adam, lowest loss so far\n(what fit returns)")
    linear = [r for r in rows if r["study"] in ("method", "scaling") and r["method"] == "linear"]
    ax.scatter([r["wall_s"] for r in linear], [r["max_rel_error"] for r in linear], marker="*",
               s=120, color="C3", label="linear solver\n(noise-free targets)")
    _axes(ax, "fitting: parameter error vs wall time", "wall time of the fit (s)",
          "largest relative parameter error")
    _legend(ax, ax.get_legend_handles_labels()[0])


def plot_noise(ax, rows):
    """The linear solver's median error against the number of views, per target kind."""
    keys = sorted({(r["size"], r["noise_std"], r["quantized"]) for r in rows
                   if r["study"] == "noise"})
    for i, (key, marker) in enumerate(zip(keys, MARKERS, strict=False)):
        sel = sorted((r for r in rows if r["study"] == "noise"
                      and (r["size"], r["noise_std"], r["quantized"]) == key),
                     key=lambda r: r["views"])
        size, noise, quantized = key
        label = f"{size} px, " + ("8-bit" if quantized else f"noise σ = {noise}")
        # each marker smaller than the one before, so that coinciding points all show
        ax.plot([r["views"] for r in sel], [r["median_rel_error"] for r in sel], "-",
                marker=marker, ms=10 - 1.5 * i, mfc="white", label=label)
    clean = sorted((r for r in rows if r["study"] == "scaling" and r["size"] == 128),
                   key=lambda r: r["views"])
    if clean:
        ax.plot([r["views"] for r in clean], [r["max_rel_error"] for r in clean], "k:",
                label="128 px, noise-free")
    _axes(ax, "fitting: error vs views (linear solver)", "views (each lit by 2 lights)",
          "largest relative parameter error\n(median over seeds)")
    views = sorted({r["views"] for r in rows if r["study"] in ("noise", "scaling")})
    ax.set_xticks(views, [str(v) for v in views])
    ax.xaxis.set_minor_formatter(NullFormatter())
    _legend(ax, ax.get_legend_handles_labels()[0])


def draw_all(results, folder):
    """Write accuracy_*.png into folder; returns the paths."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    panels = [("mesh", lambda ax: plot_mesh(ax, results["mesh"])),
              ("mesh_grad", lambda ax: plot_mesh(ax, results["mesh"], "fwd_bwd_ms")),
              ("supersample", lambda ax: plot_generic(ax, results["supersample"],
                                                      ("size", "factor"), "supersampling")),
              ("soft", lambda ax: plot_generic(ax, results["soft"], ("sigma", "K", "gamma"),
                                               "soft rasterization", "rmse_255",
                                               "fwd_bwd_ms"))]
    if "fitting" in results:
        panels.append(("fitting", lambda ax: plot_fitting(ax, results["fitting"])))
        panels.append(("noise", lambda ax: plot_noise(ax, results["fitting"])))
    for name, draw in panels:
        # a bare Figure needs no GUI backend (scripts, CI, notebooks alike); the constrained
        # layout makes room for the legend beside the axes
        fig = Figure(figsize=(8, 4.5), dpi=100, layout="constrained")
        draw(fig.add_subplot())
        path = folder / f"accuracy_{name}.png"
        fig.savefig(path)
        paths.append(str(path))
    return paths

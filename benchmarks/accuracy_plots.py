"""Plots of the accuracy-versus-time study: error against time on log axes, the Pareto
front a grey band. Used by accuracy_vs_time.py --plots, the study modules' plots() and
notebooks/03_accuracy_vs_time.ipynb; draw_* write PNGs, plot_* draw onto given axes.

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
               "rmse_255": "RMSE against the reference (1/255 units)",
               "vs_hard_rmse_255": "RMSE against the hard render (1/255 units)",
               "highlight_rmse_255": "highlight RMSE against the reference (1/255 units)"}
# how one value of a setting reads in a legend
VALUE_LABELS = {"size": "{} px image", "factor": "{}×{} samples per pixel",
                "sigma": "σ = {} px²", "gamma": "γ = {}", "K": "K = {} faces per pixel",
                "shading": "{} shading", "dtype": "{}", "sampling": "{}",
                "texels": "{}² texture", "lens": "{}"}
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
    plain = FuncFormatter(lambda v, _: f"{v:g}")
    if high / low < 1e3 and len(ticks) >= 2:
        axis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        axis.set_major_formatter(plain)
        axis.set_minor_formatter(NullFormatter())
    elif len(ticks) < 2:
        # a range within about a decade: every integer multiple, written plainly
        axis.set_major_locator(LogLocator(subs=tuple(range(1, 10))))
        axis.set_major_formatter(plain)
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
    # a broad grey band under the points, so that it is not read as one of the settings'
    # dashed or dotted lines
    ax.plot(*zip(*front, strict=True), color="0.6", lw=6, alpha=0.4, zorder=0,
            solid_capstyle="round")
    return Line2D([], [], color="0.6", lw=6, alpha=0.4, label="Pareto front")


SHADING_LINES = {"flat": ":", "gouraud": "--", "phong": "-"}


def plot_mesh(ax, rows, time_key="fwd_ms"):
    """RMSE vs time per (shading, size): colour the image size, line style the shading
    mode; each point is drawn as its icosphere subdivision level (1 to 6), so the levels
    read off the plot without labels that could collide."""
    sizes = sorted({r["size"] for r in rows})
    for mode, style in SHADING_LINES.items():
        for size, colour in zip(sizes, COLOURS, strict=False):
            sel = sorted((r for r in rows if r["shading"] == mode and r["size"] == size),
                         key=lambda r: r["subdivisions"])
            ax.plot([r[time_key] for r in sel], [r["rmse_255"] for r in sel], color=colour,
                    ls=style, lw=1.0, alpha=0.7)
            for r in sel:
                ax.plot(r[time_key], r["rmse_255"], color=colour, ls="none", ms=8,
                        marker=f"${r['subdivisions']}$")
    handles = [_front_line(ax, rows, time_key, "rmse_255")]
    ax.axhline(1.0, color="gray", lw=0.8)
    _key(handles, "1/255: one 8-bit step", color="gray", lw=0.8)
    for size, colour in zip(sizes, COLOURS, strict=False):
        _key(handles, _value_label("size", size), color=colour, lw=2)
    for mode, style in SHADING_LINES.items():
        _key(handles, _value_label("shading", mode), color="k", ls=style, lw=1.2)
    _key(handles, "digit: subdivision level", color="k", marker="$3$", ls="none", ms=8)
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


def plot_generic(ax, rows, label_keys, title, error_key="rmse_255", time_key="fwd_ms",
                 legend=True, front=True):
    """Error vs time of every row; label_keys name the settings told apart by colour,
    marker and (for a third) filled or open markers, in that order; front: draw the
    Pareto front."""
    styles = _styles(rows, label_keys)
    for r in rows:
        style = {}
        for key, values in styles.items():
            style.update(values[r[key]])
        ax.plot(r[time_key], r[error_key], **_look(style))
    handles = [_front_line(ax, rows, time_key, error_key)] if front else []
    for key, values in styles.items():
        for value, style in values.items():
            _key(handles, _value_label(key, value), **_look(style))
    _axes(ax, title, time_key, error_key)
    if legend:
        _legend(ax, handles)


def plot_soft(axes, rows):
    """Soft rasterization against forward time (the time the guide quotes): left, the
    distance to the hard image (what sigma blurs); right, the highlight's error (what a
    large gamma spoils)."""
    keys = ("sigma", "K", "gamma")
    plot_generic(axes[0], rows, keys, "soft raster: distance to the hard render",
                 "vs_hard_rmse_255", legend=False)
    plot_generic(axes[1], rows, keys, "soft raster: highlight error", "highlight_rmse_255")


def plot_fitting(axes, rows):
    """Left: Adam's error at its checkpoints (iterate and best loss) and the linear
    solver's, against wall time. Right: the loss of Adam's iterate against its step count,
    the trace whose rise after the float32 floor the guide describes."""
    ax = axes[0]
    steps = sorted((r for r in rows if r["study"] == "steps"), key=lambda r: r["steps"])
    if steps:
        ax.plot([r["wall_s"] for r in steps], [r["max_rel_error"] for r in steps], "o-",
                label="Adam, current iterate")
        ax.plot([r["wall_s"] for r in steps], [r["best_rel_error"] for r in steps], "s--",
                mfc="white", label="Adam, lowest loss so far\n(what fit returns)")
    linear = [r for r in rows if r["study"] in ("method", "scaling") and r["method"] == "linear"]
    ax.scatter([r["wall_s"] for r in linear], [r["max_rel_error"] for r in linear], marker="*",
               s=120, color="C3", label="linear solver\n(noise-free targets)")
    _axes(ax, "fitting: parameter error vs wall time", "wall time of the fit (s)",
          "largest relative parameter error")
    ax.legend(loc="upper right", fontsize=8)
    ax = axes[1]
    if not steps:  # a quick run has no trace
        ax.set_axis_off()
        ax.text(0.5, 0.5, "no step trace in these results", ha="center", transform=ax.transAxes)
        return
    ax.plot([r["steps"] for r in steps], [r["loss"] for r in steps], "o-", color="C0")
    for r in steps:
        ax.annotate(f"{r['loss']:.1e}", (r["steps"], r["loss"]), textcoords="offset points",
                    xytext=(6, 4), fontsize=8)
    _axes(ax, "Adam without a stopping rule: loss of the iterate", "Adam steps",
          "image MSE loss")
    ax.set_xlim(right=3 * steps[-1]["steps"])  # room for the last point's label


def plot_noise(ax, rows):
    """The linear solver's median (solid) and worst-seed (dotted) error against the number
    of views, per target kind."""
    keys = sorted({(r["size"], r["noise_std"], r["quantized"]) for r in rows
                   if r["study"] == "noise" and r["seeds"] > 1})
    handles = []
    for key, colour, marker in zip(keys, COLOURS, MARKERS, strict=False):
        sel = sorted((r for r in rows if r["study"] == "noise" and r["seeds"] > 1
                      and (r["size"], r["noise_std"], r["quantized"]) == key),
                     key=lambda r: r["views"])
        size, noise, quantized = key
        views = [r["views"] for r in sel]
        ax.plot(views, [r["median_rel_error"] for r in sel], "-", color=colour, marker=marker)
        ax.plot(views, [r["max_rel_error"] for r in sel], ":", color=colour, marker=marker,
                mfc="white")
        _key(handles, f"{size} px, " + ("8-bit" if quantized else f"noise σ = {noise}"),
             color=colour, marker=marker, lw=2)
    _key(handles, "median over the seeds", color="k", ls="-")
    _key(handles, "worst seed", color="k", ls=":", marker="o", mfc="white")
    clean = sorted((r for r in rows if r["study"] == "scaling" and r["size"] == 128),
                   key=lambda r: r["views"])
    if clean:
        ax.plot([r["views"] for r in clean], [r["max_rel_error"] for r in clean], "k--")
        _key(handles, "128 px, noise-free", color="k", ls="--")
    _axes(ax, "fitting: error vs views (linear solver)", "views (each lit by 2 lights)",
          "largest relative parameter error")
    views = sorted({r["views"] for r in rows if r["study"] in ("noise", "scaling")})
    ax.set_xticks(views, [str(v) for v in views])
    ax.xaxis.set_minor_formatter(NullFormatter())
    _legend(ax, handles)


def _levels(axis, values):
    """Ticks at exactly the measured levels of a setting (sample counts, map sizes)."""
    axis.set_ticks(values, [str(v) for v in values])
    axis.set_minor_formatter(NullFormatter())


def plot_precision(axes, rows):
    """float32 against float64: the same error (left, whole image; right, highlight) at
    each image size, against forward time."""
    for ax, key, title in ((axes[0], "rmse_255", "whole image"),
                           (axes[1], "highlight_rmse_255", "highlight")):
        plot_generic(ax, rows, ("dtype", "size"), f"float32 vs float64: {title}", key,
                     legend=ax is axes[1], front=False)
        ax.set_ylabel(f"{title} RMSE (1/255 units)")


def plot_shadows(axes, rows):
    """Shadow-map size against the shadow edge's error (left) and against forward time
    (right, each point labelled with its map size; the grey line is the render without
    shadows)."""
    shadowed = sorted((r for r in rows if r["map"] != "off"), key=lambda r: r["map"])
    maps = [r["map"] for r in shadowed]
    errors = [r["edge_error_px"] for r in shadowed]
    axes[0].plot(maps, errors, "o-", color="C0")
    _axes(axes[0], "shadow edge error vs map size", "texels a side of each cube map",
          "mean edge displacement (image px)")
    _levels(axes[0].xaxis, maps)
    axes[1].plot([r["fwd_ms"] for r in shadowed], errors, "o-", color="C0")
    for r in shadowed:
        axes[1].annotate(f"{r['map']}²", (r["fwd_ms"], r["edge_error_px"]),
                         textcoords="offset points", xytext=(7, 3), fontsize=9)
    for r in rows:
        if r["map"] == "off":
            axes[1].axvline(r["fwd_ms"], color="gray", lw=0.8, label="no shadows")
            axes[1].legend(loc="upper right", fontsize=8)
    _axes(axes[1], "shadow edge error vs time", "fwd_ms", "mean edge displacement (image px)")


def _by(rows, key):
    """rows grouped by the value of key, in order of first appearance."""
    groups = {}
    for r in rows:
        groups.setdefault(r[key], []).append(r)
    return groups


def plot_area_lights(axes, rows):
    """RMSE against the light's sample count (left) and forward time (right, each point
    labelled with its count), one colour and marker per light."""
    handles = []
    for (light, sel), colour, marker in zip(_by(rows, "light").items(), COLOURS, MARKERS,
                                            strict=False):
        sel = sorted(sel, key=lambda r: r["samples"])
        errors = [r["rmse_255"] for r in sel]
        axes[0].plot([r["samples"] for r in sel], errors, "-", color=colour, marker=marker)
        axes[1].plot([r["fwd_ms"] for r in sel], errors, "-", color=colour, marker=marker)
        for r in sel:
            axes[1].annotate(str(r["samples"]), (r["fwd_ms"], r["rmse_255"]), color=colour,
                             textcoords="offset points", xytext=(6, 2), fontsize=8)
        _key(handles, f"{light} light", color=colour, marker=marker, lw=1.5)
    for ax in axes:
        ax.axhline(1.0, color="gray", lw=0.8)
    _key(handles, "1/255: one 8-bit step", color="gray", lw=0.8)
    _axes(axes[0], "area lights: error vs samples", "light samples", "rmse_255")
    _levels(axes[0].xaxis, sorted({r["samples"] for r in rows}))
    _axes(axes[1], "area lights: error vs time", "fwd_ms", "rmse_255")
    _legend(axes[1], handles)


def plot_penumbrae(axes, rows):
    """The penumbra's mean error against the light's sample count (left) and forward time
    (right): colour the light, marker the shadow-map size; the dashed line in a light's
    colour is the error of a hard shadow from its centre (a penumbra-blind render)."""
    handles, maps = [], sorted({r["map"] for r in rows if r["map"] is not None})
    for (light, sel), colour in zip(_by(rows, "light").items(), COLOURS, strict=False):
        for r in sel:
            if r["map"] is None:
                for ax in axes:
                    ax.axhline(r["mean_err"], color=colour, ls="--", lw=1)
                continue
            marker = MARKERS[maps.index(r["map"])]
            # the map sizes of one sample count side by side, not on top of each other
            dodge = 1.12 ** (maps.index(r["map"]) - (len(maps) - 1) / 2)
            axes[0].plot(r["samples"] * dodge, r["mean_err"], color=colour, marker=marker, ms=7,
                         mfc="white" if marker != "o" else colour, ls="none")
            axes[1].plot(r["fwd_ms"], r["mean_err"], color=colour, marker=marker, ms=7,
                         mfc="white" if marker != "o" else colour, ls="none")
        _key(handles, f"{light} light", color=colour, lw=2)
    for size, marker in zip(maps, MARKERS, strict=False):
        _key(handles, f"{size}² shadow maps", color="k", marker=marker, ls="none",
             mfc="k" if marker == "o" else "white")
    _key(handles, "hard shadow from the centre", color="k", ls="--", lw=1)
    label = "penumbra's mean error\n(unit: brightest lit floor pixel)"
    _axes(axes[0], "penumbrae: error vs samples", "light samples", label)
    _levels(axes[0].xaxis, sorted({r["samples"] for r in rows if r["map"] is not None}))
    _axes(axes[1], "penumbrae: error vs time", "fwd_ms", label)
    _legend(axes[1], handles)


def _draw(folder, name, panels, draw, width=8.0):
    """Draw one figure of `panels` axes side by side into folder/accuracy_<name>.png."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    # a bare Figure needs no GUI backend (scripts, CI, notebooks alike); the constrained
    # layout makes room for the legend beside the axes
    fig = Figure(figsize=(width, 4.5), dpi=100, layout="constrained")
    axes = [fig.add_subplot(1, panels, i + 1) for i in range(panels)]
    draw(axes[0] if panels == 1 else axes)
    path = folder / f"accuracy_{name}.png"
    fig.savefig(path)
    return str(path)


def draw_precision(results, folder):
    """accuracy_precision.png from the accuracy_vs_time results' precision rows."""
    return [_draw(folder, "precision", 2, lambda axes: plot_precision(axes,
                                                                      results["precision"]),
                  width=11)]


def draw_shadows(results, folder):
    """accuracy_shadows.png from accuracy_shadows.json's results."""
    return [_draw(folder, "shadows", 2, lambda axes: plot_shadows(axes, results["shadows"]),
                  width=10)]


def draw_area_lights(results, folder):
    """accuracy_area_lights.png from accuracy_area_lights.json's results."""
    return [_draw(folder, "area_lights", 2,
                  lambda axes: plot_area_lights(axes, results["rows"]), width=11)]


def draw_penumbrae(results, folder):
    """accuracy_penumbrae.png from accuracy_penumbrae.json's results."""
    return [_draw(folder, "penumbrae", 2, lambda axes: plot_penumbrae(axes, results["rows"]),
                  width=11)]


def draw_all(results, folder):
    """Write the accuracy_vs_time study's accuracy_*.png into folder; returns the paths."""
    panels = [("mesh", 1, lambda ax: plot_mesh(ax, results["mesh"]), 8.0),
              ("mesh_grad", 1, lambda ax: plot_mesh(ax, results["mesh"], "fwd_bwd_ms"), 8.0),
              ("supersample", 1, lambda ax: plot_generic(ax, results["supersample"],
                                                         ("size", "factor"), "supersampling"),
               8.0),
              ("soft", 2, lambda axes: plot_soft(axes, results["soft"]), 11.0)]
    if "fitting" in results:
        panels.append(("fitting", 2, lambda axes: plot_fitting(axes, results["fitting"]),
                       11.0))
        panels.append(("noise", 1, lambda ax: plot_noise(ax, results["fitting"]), 8.0))
    return [_draw(folder, name, n, draw, width) for name, n, draw, width in panels]

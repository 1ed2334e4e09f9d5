"""Plots of the choices study (benchmarks/accuracy_choices.py): one PNG per section, error
against time on log axes, the Pareto front dashed. Colour tells one setting apart and the
marker another, each explained once in a legend beside the axes (accuracy_plots' style);
the points of one colour are joined in the order of the setting named in the title."""

from pathlib import Path

from accuracy_plots import MARKERS, _axes, _front_line, _key, _legend
from matplotlib.figure import Figure
from matplotlib.ticker import NullFormatter

COLOURS = [f"C{i}" for i in range(10)]  # matplotlib's ten; no plot here needs more
AXIS_LABELS = {"size": "image size (px)", "fwd_ms": "time per render, forward (ms)",
               "fwd_bwd_vertices_ms": "time per gradient w.r.t. the vertices (ms)",
               "grad_ms": "time per gradient (ms)", "fit_ms": "time per fit (ms)"}


def _series(ax, rows, colour_of, marker_of, x_key, y_key, order_key=None, join=True):
    """Plot rows grouped by colour_of(row) (joined in order_key order), marked by
    marker_of(row); returns the legend handles for the colours and the markers."""
    colours = list(dict.fromkeys(colour_of(r) for r in rows))
    markers = list(dict.fromkeys(marker_of(r) for r in rows))
    if len(colours) > len(COLOURS) or len(markers) > len(MARKERS):
        raise ValueError(f"rows: {len(colours)} colours and {len(markers)} markers; this "
                         f"plot tells apart {len(COLOURS)} and {len(MARKERS)}")
    for colour, c in zip(colours, COLOURS, strict=False):
        group = [r for r in rows if colour_of(r) == colour]
        if order_key is not None:
            group.sort(key=lambda r: r[order_key])
        if join and len(group) > 1:
            ax.plot([r[x_key] for r in group], [r[y_key] for r in group], color=c, lw=1.0,
                    alpha=0.7)
        for r in group:
            m = MARKERS[markers.index(marker_of(r))]
            ax.plot(r[x_key], r[y_key], ls="none", marker=m, ms=7, color=c)
    handles = []
    for colour, c in zip(colours, COLOURS, strict=False):
        _key(handles, colour, color=c, lw=2)
    if len(markers) > 1:
        for marker, m in zip(markers, MARKERS, strict=False):
            _key(handles, marker, color="k", marker=m, ls="none")
    return handles


def _panel(ax, rows, title, x_key, y_key, ylabel, colour_of, marker_of, order_key=None,
           front=True, line_at=None, ticks_at=None):
    handles = []
    if front:
        handles.append(_front_line(ax, rows, x_key, y_key))
    if line_at is not None:
        ax.axhline(line_at[0], color="gray", lw=0.8)
        _key(handles, line_at[1], color="gray", lw=0.8)
    handles += _series(ax, rows, colour_of, marker_of, x_key, y_key, order_key)
    _axes(ax, title, AXIS_LABELS.get(x_key, x_key), ylabel)
    if ticks_at is not None:  # a few sizes: label each
        values = sorted({r[ticks_at] for r in rows})
        ax.set_xticks(values, [str(v) for v in values])
        ax.xaxis.set_minor_formatter(NullFormatter())
    _legend(ax, handles)


def _count(n, noun):
    return f"{n} {noun}" + ("" if n == 1 else "s")


ONE_STEP = (1.0, "1/255: one 8-bit step")
PANELS = {
    "soft_overlap": lambda ax, rows: _panel(
        ax, [r for r in rows if r["raster"] == "soft"],
        "soft raster on a torus: sigma and K (points: K rising)", "fwd_bwd_vertices_ms",
        "vs_hard_rmse_255", "RMSE against the hard render (1/255 units)",
        lambda r: f"σ = {r['sigma']} px²", lambda r: f"K = {r['K']}", "K"),
    "kernels": lambda ax, rows: _panel(
        ax, rows, "kernels: host against jax", "size", "fwd_ms",
        "time per render, forward (ms)",
        lambda r: f"{r['raster']} raster, kernels='{r['kernels']}'",
        lambda r: f"{r['raster']} raster", "size", front=False, ticks_at="size"),
    "supersample_levels": lambda ax, rows: _panel(
        ax, rows, "supersampling at subdivisions 3 and 4 (points: factor 1, 2, 4)",
        "fwd_ms", "rmse_255", "RMSE against the analytic sphere (1/255 units)",
        lambda r: f"{r['size']} px, subdivision {r['subdivisions']}",
        lambda r: f"{r['factor']}×{r['factor']} samples per pixel", "factor",
        line_at=ONE_STEP),
    "gradients": lambda ax, rows: _panel(
        ax, rows, "gradient accuracy against float64 central differences", "grad_ms",
        "rel_error", "relative error of the gradient vector",
        lambda r: f"{r['raster']} raster, w.r.t. the {r['wrt']}", lambda r: r["dtype"],
        "grad_ms", front=False),
    "highlight_front": lambda ax, rows: _panel(
        ax, rows, "highlight-error frontier (published mesh and supersample rows)",
        "fwd_ms", "highlight_rmse_255", "highlight RMSE against the exact sphere (1/255)",
        lambda r: f"{r['shading']} shading" + (f", {r['factor']}×{r['factor']} samples"
                                                if r["factor"] > 1 else ""),
        lambda r: f"{r['size']} px", "fwd_ms",
        line_at=ONE_STEP),
    "soft_shadows": lambda ax, rows: _panel(
        ax, rows, "shadow edge: hard against soft raster", "fwd_ms", "edge_error_px",
        "shadow-edge error (image pixels)",
        lambda r: "hard raster" if r["raster"] == "hard" else f"soft, σ = {r['sigma']} px²",
        lambda r: (f"map {r['map']}²" if r["raster"] == "hard" else
                   f"shadow softness {r['shadow_softness']} texels"), "fwd_ms"),
    "fit_effects": lambda ax, rows: _panel(
        ax, rows, "inside a fit (linear solver)", "fit_ms", "max_rel_error",
        "largest relative parameter error",
        lambda r: (f"{r['case']}: model {r['model']}" if "model" in r
                   else _count(r["n_lights"], "light") + " per view"),
        lambda r: _count(r.get("n_views", 2), "view"),
        "fit_ms", front=False),
    "fit_resolution": lambda ax, rows: _panel(
        ax, rows, "image size for fitting (linear solver; points: size rising)", "fit_ms",
        "median_rel_error", "largest relative parameter error\n(median over seeds)",
        lambda r: "8-bit targets" if r["quantized"] else f"noise σ = {r['noise_std']}",
        lambda r: f"{r['size']} px", "size", front=False),
}


def draw_all(results, folder):
    """Write accuracy_choices_<section>.png into folder for each section in results."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, draw in PANELS.items():
        if name not in results:
            continue
        fig = Figure(figsize=(8, 4.5), dpi=100, layout="constrained")
        draw(fig.add_subplot(), results[name])
        path = folder / f"accuracy_choices_{name}.png"
        fig.savefig(path)
        paths.append(str(path))
    return paths

"""fitting: recover Blinn-Phong materials (and optionally lights) from images.

The forward model is diffshade's lighting core: targets are rendered with
`diffshade.render`, and a fit evaluates `diffshade.shade` on cached pixels. Start with
`fit(dataset, FitSpec())`; see docs/fitting.md. `fit` and `diffshade fit` run the same
driver (fitting.run) with the same options (fitting.solve.options).

Here: what a user calls and reads. The floors below are namespaces of their own, each
with its public face: `fitting.spec` (the parameter maps), `fitting.data` (datasets),
`fitting.model` (the pixel cache and the losses: build_cache, predict, make_loss),
`fitting.solve` (make_step, make_optimizer, the solvers) and `fitting.report`. Solver
internals (lm_step, normal_equations, ...) stay in their modules.
"""

import importlib

# Imported on first use (module __getattr__): a program that needs one floor, as `diffshade
# synth` needs the dataset format (fitting.data) and not the solvers, optax or the
# reports, does not import the others at start.
_FLOORS = ("data", "model", "report", "solve", "spec")
_NAMES = {
    "load_dataset": "fitting.data.folder", "save_dataset": "fitting.data.folder",
    "Dataset": "fitting.data.views", "View": "fitting.data.views",
    "dataset_of_scene": "fitting.data.views", "view_scene": "fitting.data.views",
    "FitResult": "fitting.driver", "fit": "fitting.driver",
    "Misfit": "fitting.report.misfit",
    "IdentifiabilityWarning": "fitting.report.uncertainty",
    "UncertaintyReport": "fitting.report.uncertainty",
    "FitOptions": "fitting.solve.options",
    "DEFAULT_INIT": "fitting.spec.params", "FitSpec": "fitting.spec.params",
}

__all__ = [
    # fitting
    "fit", "FitSpec", "FitOptions", "DEFAULT_INIT",
    # the data
    "Dataset", "View", "dataset_of_scene", "load_dataset", "save_dataset", "view_scene",
    # what a fit returns
    "FitResult", "IdentifiabilityWarning", "Misfit", "UncertaintyReport",
    # the floors, each a namespace with its own __all__
    "data", "model", "report", "solve", "spec",
]


def __getattr__(name):
    if name in _FLOORS:
        return importlib.import_module(f"{__name__}.{name}")
    if name not in _NAMES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(_NAMES[name]), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))

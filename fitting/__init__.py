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

from fitting import data, model, report, solve, spec
from fitting.data.folder import load_dataset, save_dataset
from fitting.data.views import Dataset, View, dataset_of_scene, view_scene
from fitting.driver import FitResult, fit
from fitting.report.misfit import Misfit
from fitting.report.uncertainty import IdentifiabilityWarning, UncertaintyReport
from fitting.solve.options import FitOptions
from fitting.spec.params import DEFAULT_INIT, FitSpec

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

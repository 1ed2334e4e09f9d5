"""fitting: recover Blinn-Phong materials (and optionally lights) from images.

The forward model is diffshade's lighting core: targets are rendered with
`diffshade.render`, and a fit evaluates `diffshade.shade` on cached pixels. Start with
`fit(dataset, FitSpec())`; see docs/fitting.md. `fit` and `diffshade fit` run the same
driver (fitting.run) with the same options (fitting.solve.options).
"""

from fitting.data.folder import load_dataset, save_dataset
from fitting.data.views import Dataset, View, view_scene
from fitting.fit import FitResult, fit, fit_result, relative_errors
from fitting.model.cache import FitData, ViewSamples, build_cache, pixel_parts, predict
from fitting.model.loss import (
    LOSSES,
    RenderData,
    make_loss,
    make_render_loss,
    render_data,
    residuals,
)
from fitting.report.misfit import Misfit, misfit
from fitting.report.result import comparison_table
from fitting.report.uncertainty import IdentifiabilityWarning, UncertaintyReport, uncertainty
from fitting.run import RunState, advance, finish, start_run
from fitting.solve.gauss_newton import levenberg_marquardt, lm_step
from fitting.solve.linear import box_least_squares, normal_equations, solve_linear
from fitting.solve.options import FIT_METHODS, METHODS, FitOptions
from fitting.solve.step import make_optimizer, make_step
from fitting.spec.params import (
    DEFAULT_INIT,
    KINDS,
    FitSpec,
    at_bound,
    from_values,
    material_values,
    param_labels,
    to_lights,
    to_material,
    to_unconstrained,
    to_values,
    value_names,
    values_to_lights,
    values_to_material,
)

__all__ = [
    "DEFAULT_INIT", "FIT_METHODS", "KINDS", "LOSSES", "METHODS", "Dataset", "FitData",
    "FitOptions", "FitResult", "FitSpec", "IdentifiabilityWarning", "Misfit", "RenderData",
    "RunState", "UncertaintyReport", "View", "ViewSamples", "advance", "at_bound",
    "box_least_squares", "build_cache", "comparison_table", "finish", "fit", "fit_result",
    "from_values", "levenberg_marquardt", "lm_step", "load_dataset", "make_loss",
    "make_optimizer", "make_render_loss", "make_step", "material_values", "misfit",
    "normal_equations", "param_labels", "pixel_parts", "predict", "relative_errors",
    "render_data", "residuals", "save_dataset", "solve_linear", "start_run", "to_lights",
    "to_material", "to_unconstrained", "to_values", "uncertainty", "value_names",
    "values_to_lights", "values_to_material", "view_scene",
]

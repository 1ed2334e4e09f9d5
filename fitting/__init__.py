"""fitting: recover Blinn-Phong materials (and optionally lights) from images.

The forward model is diffshade's lighting core: targets are rendered with
`diffshade.render`, and a fit evaluates `diffshade.shade` on cached pixels. Start with
`fit(dataset, FitSpec())`; see docs/fitting.md. `fit` and `diffshade fit` run the same
driver (fitting.run) with the same options (fitting.options).
"""

from fitting.cache import FitData, ViewSamples, build_cache, pixel_parts, predict
from fitting.data import Dataset, View, view_scene
from fitting.dataset import load_dataset, save_dataset
from fitting.fit import FitResult, fit, fit_result, relative_errors
from fitting.gauss_newton import levenberg_marquardt, lm_step
from fitting.linear import box_least_squares, normal_equations, solve_linear
from fitting.loss import LOSSES, RenderData, make_loss, make_render_loss, render_data, residuals
from fitting.misfit import Misfit, misfit
from fitting.options import FIT_METHODS, METHODS, FitOptions
from fitting.params import (
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
from fitting.report import comparison_table
from fitting.run import RunState, advance, finish, start_run
from fitting.step import make_optimizer, make_step
from fitting.uncertainty import IdentifiabilityWarning, UncertaintyReport, uncertainty

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

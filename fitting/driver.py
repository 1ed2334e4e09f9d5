"""fit: recover the material (and optionally the lights) of a Dataset.

    result = fit(dataset, FitSpec(), method="linear")
    result.material, result.errors, result.uncertainty.table(), print(result.summary())

`fit` is the Python face of the one fit driver (fitting.run), the same loop, options
(fitting.solve.options.FitOptions, as keywords) and result as `diffshade fit`. Methods (all on
the cached pixels, see fitting.model.cache):
- 'linear' (default): variable projection — closed-form coefficients inside a 1-D search
  on log-shininess (fitting.solve.linear) — then Levenberg-Marquardt on every fitted quantity
  with the exact clamped model and the chosen loss (fitting.solve.gauss_newton). Independent of
  the initial guess for the material; the most accurate and the fastest.
- 'adam': Adam on the unconstrained parameters with per-group learning rates.
- 'lbfgs': optax.lbfgs with a zoom line search.
Adam and L-BFGS stop when the relative loss change stays below `tol` for `patience`
steps, the loss reaches `atol` or the gradient norm falls below `gtol`; they are local and
can stall on the ks-shininess ridge from a poor start (see docs/fitting.md).

With `textures={"kd": RES}` (and/or "ks") the mapped coefficients are recovered as RES x
RES maps over the mesh's UVs, alternating with the uniform quantities
(fitting.texture_run); the result then holds the maps (`textures`) and the rounds.

`fit_result` reports a run at its best params: the values, the relative error of every
fitted value when the truth is known (per channel), standard errors, the values that
ended at a bound (no standard error), and whether the model explains the images
(fitting.report.misfit); when it does not, the standard errors are the robust ones
(fitting.report.robust.widened).
"""

import dataclasses
import time

import jax
import numpy as np

from diffshade.scene import Material, Texture
from fitting.data.rounding import carried_rounding
from fitting.data.views import Dataset, material_for
from fitting.model.cache import build_cache
from fitting.report.misfit import Misfit, misfit
from fitting.report.result import comparison_table
from fitting.report.robust import widened
from fitting.report.uncertainty import UncertaintyReport, uncertainty
from fitting.run import advance, finish, start_run
from fitting.solve.distribute import device_list, fit_data, for_options
from fitting.solve.options import FitOptions
from fitting.solve.texture import DEFAULT_SMOOTHNESS
from fitting.spec.params import (
    DEFAULT_INIT,
    MODED,
    FitSpec,
    at_bound,
    material_values,
    start_material,
    to_values,
    value_names,
    values_to_lights,
    values_to_material,
)
from fitting.texture_run import MAX_ROUNDS, ROUND_TOL, check_map_fit, fit_maps


@dataclasses.dataclass(frozen=True)
class FitResult:
    """material: the fitted Material; lights: tuple of LightGroups per view (fitted or
    given); values: physical fitted values (fitting.spec.params); params: unconstrained;
    loss: the lowest loss seen (the values are where it was reached); loss_history:
    [steps + 1]; converged; n_steps; wall_time (s); method; errors: {name: relative error
    per channel} against `truth`, or None; uncertainty: UncertaintyReport or None;
    warnings: tuple of messages; truth: the true Material, or None; status: 'converged',
    'budget', 'stopped' or 'non-finite' (fitting.run); stop_message: why it stopped on
    non-finite values; at_bound: names of the values at a bound; misfit: fitting.report.misfit
    .Misfit or None; object_names: the names of the dataset's objects when they are named
    (scene files' "name", diffshade.scene_object's name), else None; textures: {field:
    fitting.solve.TextureSolution} of a fit with maps (the map, NaN where unseen, its
    coverage and standard error; `material` holds them with 0 where unseen), else None;
    rounds: the alternation's rounds (fitting.texture_run), () without maps."""

    material: object
    lights: tuple
    values: dict
    params: dict
    loss: float
    loss_history: np.ndarray
    converged: bool
    n_steps: int
    wall_time: float
    method: str
    errors: dict | None
    uncertainty: UncertaintyReport | None
    warnings: tuple
    truth: Material | None = None
    status: str = "converged"
    stop_message: str = ""
    at_bound: tuple = ()
    misfit: Misfit | None = None
    object_names: tuple | None = None
    textures: dict | None = None
    rounds: tuple = ()

    def summary(self, truth=None) -> str:
        """A table: parameter, true value (when `truth` or self.truth is known), fitted
        value, standard error and relative error; warnings and notes below."""
        return comparison_table(self, self.truth if truth is None else truth)

    def object_reports(self) -> list:
        """One UncertaintyReport per object (several objects; [the report] for one)."""
        if "objects" not in self.values or self.uncertainty is None:
            return [self.uncertainty]
        return [self.uncertainty.select(f"objects[{i}].")
                for i in range(len(self.values["objects"]))]

    def as_dict(self) -> dict:
        """JSON-ready: method, status, loss, loss_history, converged, n_steps, wall_time,
        values (lights included when fitted), errors, std_errors (the ones the table
        shows), std_error_kind (which: 'gauss-newton' or 'robust'), std_errors_gauss_newton
        and std_errors_robust (both estimates) and rounding_bound (None for a value at a
        bound), at_bound, misfit, warnings, notes; rounds (a fit with maps)."""
        plain = lambda tree: jax.tree.map(lambda x: np.asarray(x).tolist(), tree)
        report = self.uncertainty
        number = lambda name, x: None if name in self.at_bound else float(x)

        def by_name(array):
            return None if report is None or array is None else {
                n: number(n, s) for n, s in zip(report.names, array, strict=True)}
        return {"method": self.method, "status": self.status, "loss": self.loss,
                "loss_history": self.loss_history.tolist(), "converged": self.converged,
                "n_steps": self.n_steps, "wall_time": self.wall_time,
                "values": plain(self.values),
                "errors": None if self.errors is None else plain(self.errors),
                "std_errors": by_name(None if report is None else report.std_errors),
                "std_error_kind": None if report is None else report.kind,
                "std_errors_gauss_newton": by_name(
                    None if report is None else report.gauss_newton_std_errors),
                "std_errors_robust": by_name(
                    None if report is None else report.robust_std_errors),
                "rounding_bound": by_name(None if report is None else report.rounding_bound),
                "at_bound": list(self.at_bound),
                "misfit": None if self.misfit is None else self.misfit.as_dict(),
                "warnings": list(self.warnings),
                "notes": [] if report is None else list(report.notes),
                **({"rounds": list(self.rounds)} if self.rounds else {})}


def relative_errors(values: dict, truth, spec: FitSpec) -> dict:
    """|fitted - true| / |true| per fitted material quantity and channel (the absolute
    error where the truth is 0): {'ka': [3], ..., 'shininess': []} as numpy; with several
    objects (a stacked truth), {'objects': (one such dict per object)}."""
    # a value fitted uniform where the truth has a map has no true value to compare with
    rgb_spec = FitSpec(**{n: "rgb" if getattr(spec, n) and not isinstance(
        getattr(truth, n, None), Texture) else None for n in MODED}, shininess=spec.shininess)
    true = material_values(truth, rgb_spec)
    if "objects" in true:
        return {"objects": tuple(_relative_errors(v, t) for v, t in
                                 zip(values["objects"], true["objects"], strict=True))}
    return _relative_errors(values, true)


def _relative_errors(values, true):
    errors = {}
    for name, t in true.items():
        fitted = np.broadcast_to(np.asarray(values[name], np.float64), np.shape(t))
        t = np.asarray(t, np.float64)
        errors[name] = np.abs(fitted - t) / np.where(t != 0, np.abs(t), 1.0)
    return errors


def _bound_warning(names, values, spec):
    flat = np.concatenate([np.ravel(np.asarray(v, np.float64))
                           for v in jax.tree.leaves(values)])
    shown = ", ".join(f"{n} = {v:.4g}" for n, v in zip(value_names(values), flat, strict=True)
                      if n in names)
    return (f"{shown} ended at a bound of its range (coefficients: [0, {spec.upper:g}]): no "
            "standard error; the model may be missing something the bound stands in for "
            "(see the misfit check), or the value is truly there")


def fit_result(state, dataset, data, *, with_uncertainty=True, warn=False, truth=None,
               status="converged", stop_message="", eliminated=None) -> FitResult:
    """A FitResult at the state's best params (fitting.run.RunState): values, standard
    errors and warnings (fitting.report.uncertainty; raised as warnings when `warn`), the values
    at a bound, the misfit check, relative errors against `truth` (default the dataset's)
    when known; loss is the best loss, loss_history the whole history. data: the cached
    data, or its ShardedViews (fitting.solve.distribute: the report's sums a chunk at a time).
    eliminated: unknowns marginalised in the standard errors (fitting.report.uncertainty's
    keyword: a fit's map texels)."""
    if state.best_params is None:
        raise ValueError("state: no step had a finite loss; there is no result to report")
    spec, truth = state.spec, dataset.truth if truth is None else truth
    values = jax.tree.map(np.asarray, to_values(state.best_params, spec))
    views, data = data, fit_data(data)  # sharded views: the report a chunk at a time
    widths = [v.camera.width for v in dataset.views]
    rounding = carried_rounding(dataset.views)
    report = (uncertainty(values, views, spec, widths=widths, rounding=rounding, warn=warn,
                          eliminated=eliminated) if with_uncertainty else None)
    bound = tuple(n for n, b in zip(value_names(values), at_bound(values, spec), strict=True)
                  if b)
    check = misfit(values, views, spec, widths, rounding) if with_uncertainty else None
    if check is not None and not check.explained:  # correlated residuals: robust errors
        report = widened(report)
    found = (*([f"fit stopped: {stop_message}"] if status == "non-finite" else []),
             *(report.warnings if report else ()),
             *([_bound_warning(bound, values, spec)] if bound else []),
             *([check.message(status)] if check is not None and not check.explained else []))
    errors = (relative_errors(values, truth, spec)
              if truth is not None and spec.fits_material else None)
    return FitResult(
        material=values_to_material(values, spec, data.material),
        lights=values_to_lights(values, spec, data.lights), values=values,
        params=state.best_params, loss=state.best_loss,
        loss_history=np.asarray(state.history), converged=state.converged,
        n_steps=state.step, wall_time=state.wall_time, method=state.method, errors=errors,
        uncertainty=report, warnings=found, truth=truth, status=status,
        stop_message=stop_message, at_bound=bound, misfit=check,
        object_names=None if dataset.objects is None else dataset.objects.names)


def _check_fit_args(dataset, spec, init, truth, options, settings):
    if not isinstance(dataset, Dataset):
        raise TypeError(f"dataset: got {type(dataset).__name__}; expected fitting.Dataset")
    if not isinstance(spec, FitSpec):
        raise TypeError(f"spec: got {type(spec).__name__}; expected FitSpec")
    for name, value in (("init", init), ("truth", truth)):
        named = name == "init" and isinstance(value, dict)  # {object name: Material}
        if value is not None and not isinstance(value, Material) and not named:
            raise TypeError(f"{name}: got {type(value).__name__}; expected a Material "
                            "(diffshade.scene.materials(...)) or None")
    if options is not None and not isinstance(options, FitOptions):
        raise TypeError(f"options: got {type(options).__name__}; expected FitOptions")
    unknown = sorted(set(settings) - {f.name for f in dataclasses.fields(FitOptions)})
    if unknown:
        raise TypeError(f"fit: got unknown option(s) {unknown}; expected FitOptions fields "
                        f"{[f.name for f in dataclasses.fields(FitOptions)]}")


def _notifier(callback, spec, data):
    """(on_step, should_stop) for callback(step, loss, material) -> True stops."""
    stop = [False]
    if callback is None:
        return lambda state: None, lambda: False

    def on_step(state):
        material = values_to_material(to_values(state.params, spec), spec, data.material)
        stop[0] = bool(callback(state.step - 1, state.history[-1], material))
    return on_step, lambda: stop[0]


def map_fit_result(run, dataset, **options) -> FitResult:
    """The FitResult of a fit with maps (a fitting.texture_run.MapRun): fit_result at the
    last round's uniform fit (options: fit_result's keywords), with the maps and the
    rounds; status 'converged' when a round changed less than the tolerance, else
    'budget' (the rounds ran out)."""
    if not run.state.spec.fits_material:  # only maps: no uniform value to report on
        options["with_uncertainty"] = False
    result = fit_result(run.state, dataset, run.data,
                        status="converged" if run.converged else "budget",
                        eliminated=run.eliminated, **options)
    return dataclasses.replace(result, textures=run.maps, rounds=run.rounds)


def _fit_with_maps(dataset, spec, init, options, truth, with_uncertainty, maps):
    """fit(...) with textures: the maps and the uniform quantities (fitting.texture_run)."""
    textures, smoothness, rounds, round_tol = maps
    smoothness = DEFAULT_SMOOTHNESS if smoothness is None else smoothness
    run = fit_maps(dataset, spec, init, textures, options, smoothness=smoothness,
                   rounds=rounds, round_tol=round_tol)
    return map_fit_result(run, dataset, with_uncertainty=with_uncertainty, warn=True,
                          truth=truth)


def fit(dataset: Dataset, spec: FitSpec | None = None, init=None, *, options=None,
        truth=None, with_uncertainty=True, callback=None, textures=None, smoothness=None,
        rounds=MAX_ROUNDS, round_tol=ROUND_TOL, **settings) -> FitResult:
    """Fit `spec`'s quantities (default FitSpec(): ka, kd, ks in RGB and shininess) to
    `dataset`, starting from (and holding fixed the rest of) `init` (a Material; default
    DEFAULT_INIT; kt, when fitted and `init` has none, starts at KT_START; with several
    objects one Material for all, a stacked one or {object name: Material},
    fitting.data.views.material_for).

    options: a FitOptions; settings: any of its fields as keywords (method='linear' |
    'adam' | 'lbfgs', steps, loss, tol, atol, patience, gtol, lr, lr_shininess,
    lr_position, edge_margin, shininess_range, max_bad, devices, chunk: docs/fitting.md;
    devices and chunk: docs/performance.md, "Many views on many devices"), which replace
    those of `options`. truth: the true Material for the errors and the summary (default
    dataset.truth). with_uncertainty: standard errors, identifiability warnings (also
    raised as IdentifiabilityWarning) and the misfit check. callback(step, loss, material)
    after every step; returning True stops the fit (status 'stopped').

    textures: {"kd": RES} and/or {"ks": RES}: recover those coefficients as RES x RES
    maps over the mesh's UVs, with the rest of `spec` fitted uniform, by alternation
    (fitting.texture_run: at most `rounds` rounds, until a round changes the values by at
    most `round_tol`); smoothness: the maps' prior weight (default DEFAULT_SMOOTHNESS,
    fitting.solve.texture). The method runs the maps too ('linear': conjugate gradients;
    'adam', 'lbfgs': descent). The result's `textures` holds the maps; not with
    `callback`, lights, gains or kt fitted, or several devices or chunks."""
    spec = FitSpec() if spec is None else spec
    _check_fit_args(dataset, spec, init, truth, options, settings)
    options = dataclasses.replace(options or FitOptions(), **settings)
    device_list(options.devices)  # more devices than there are: an error before any work
    if textures is not None:
        check_map_fit(dataset, spec, textures, options, callback, "textures")
        init = material_for(dataset, DEFAULT_INIT if init is None else init, "init")
        return _fit_with_maps(dataset, spec, init, options, truth, with_uncertainty,
                              (textures, smoothness, rounds, round_tol))
    if smoothness is not None:
        raise ValueError(f"smoothness: got {smoothness!r} without textures; expected it "
                         "with textures={...}")
    init = start_material(material_for(dataset, DEFAULT_INIT if init is None else init,
                                       "init"), spec)
    start = time.perf_counter()
    data = build_cache(dataset, init, edge_margin=options.edge_margin)
    views = for_options(data, options)  # sharded and chunked, or data itself
    data = fit_data(views)  # (sharded: its views, in host memory)
    state = start_run(views, spec, init, options)
    state.wall_time = time.perf_counter() - start
    on_step, should_stop = _notifier(callback, spec, data)
    status, message = advance(state, views, should_stop=should_stop, on_step=on_step)
    finish(state, views)
    if state.best_params is None:
        raise ValueError(f"dataset: no step had a finite loss ({message})")
    return fit_result(state, dataset, views, with_uncertainty=with_uncertainty, warn=True,
                      truth=truth, status=status, stop_message=message)

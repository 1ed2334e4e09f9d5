"""fit: recover the material (and optionally the lights) of a Dataset.

    result = fit(dataset, FitSpec(), method="linear")
    result.material, result.errors, result.uncertainty.table()

Methods (all on the cached pixels, see fitting.cache):
- 'linear' (default): variable projection — closed-form coefficients inside a 1-D search
  on log-shininess (fitting.linear) — then Levenberg-Marquardt on every fitted quantity
  with the exact clamped model and the chosen loss (fitting.gauss_newton). Independent of
  the initial guess for the material; the most accurate and the fastest.
- 'adam': Adam on the unconstrained parameters with per-group learning rates.
- 'lbfgs': optax.lbfgs with a zoom line search.
Adam and L-BFGS stop when the relative loss change stays below `tol` for `patience`
steps, the loss reaches `atol` or the gradient norm falls below `gtol`; they are local and
can stall on the ks-shininess ridge from a poor start (see docs/fitting.md).

Held-fixed quantities come from `init` (default DEFAULT_INIT). When the dataset knows its
`truth`, the result reports the relative error of every fitted value (per channel).
"""

import dataclasses
import time
from functools import lru_cache, partial

import jax
import numpy as np
import optax

from fitting.cache import build_cache
from fitting.data import Dataset
from fitting.gauss_newton import levenberg_marquardt, loss_at
from fitting.linear import solve_linear
from fitting.loss import check_kind, make_loss
from fitting.params import (
    DEFAULT_INIT,
    FitSpec,
    from_values,
    material_values,
    to_values,
    values_to_lights,
    values_to_material,
)
from fitting.step import make_optimizer, make_step
from fitting.uncertainty import UncertaintyReport, uncertainty

FIT_METHODS = ("linear", "adam", "lbfgs")
DEFAULT_STEPS = {"linear": 50, "adam": 3000, "lbfgs": 500}


@dataclasses.dataclass(frozen=True)
class FitResult:
    """material: the fitted Material; lights: tuple of LightGroups per view (fitted or
    given); values: physical fitted values (fitting.params); params: unconstrained;
    loss: final loss; loss_history: [steps + 1]; converged; n_steps; wall_time (s);
    method; errors: {name: relative error per channel} against dataset.truth, or None;
    uncertainty: UncertaintyReport or None; warnings: tuple of messages."""

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

    def summary(self) -> str:
        """A table: parameter, fitted value, standard error and relative error (vs truth)."""
        return format_summary(self)

    def object_reports(self) -> list:
        """One UncertaintyReport per object (several objects; [the report] for one)."""
        if "objects" not in self.values or self.uncertainty is None:
            return [self.uncertainty]
        return [self.uncertainty.select(f"objects[{i}].")
                for i in range(len(self.values["objects"]))]

    def as_dict(self) -> dict:
        """JSON-ready: method, loss, loss_history, converged, n_steps, wall_time, values
        (material quantities; lights omitted), errors, std_errors, rounding_bound (8-bit
        targets), warnings, notes."""
        plain = lambda tree: jax.tree.map(lambda x: np.asarray(x).tolist(), tree)
        report = self.uncertainty
        return {"method": self.method, "loss": self.loss,
                "loss_history": self.loss_history.tolist(), "converged": self.converged,
                "n_steps": self.n_steps, "wall_time": self.wall_time,
                "values": plain({k: v for k, v in self.values.items() if k != "lights"}),
                "errors": None if self.errors is None else plain(self.errors),
                "std_errors": None if report is None else {
                    name: se for name, (_, se) in report.as_dict().items()},
                "rounding_bound": None if report is None or report.rounding_bound is None
                else dict(zip(report.names, report.rounding_bound.tolist(), strict=True)),
                "warnings": list(self.warnings),
                "notes": [] if report is None else list(report.notes)}


def relative_errors(values: dict, truth, spec: FitSpec) -> dict:
    """|fitted - true| / |true| per fitted material quantity and channel (the absolute
    error where the truth is 0): {'ka': [3], ..., 'shininess': []} as numpy; with several
    objects (a stacked truth), {'objects': (one such dict per object)}."""
    rgb_spec = FitSpec(**{n: "rgb" if getattr(spec, n) else None for n in ("ka", "kd", "ks")},
                       shininess=spec.shininess)
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


@lru_cache(maxsize=32)
def _optax_step(spec, kind, method, lr, lr_shininess, lr_position):
    """One compiled step per configuration, shared by every fit that uses it."""
    optimizer = make_optimizer(method, lr=lr, lr_shininess=lr_shininess, lr_position=lr_position)
    return make_step(make_loss(spec, kind), optimizer), optimizer


@partial(jax.jit, static_argnames=("spec", "kind"))
def _grad_norm(params, data, spec, kind):
    grads = jax.grad(make_loss(spec, kind))(params, data)
    return optax.global_norm(grads)


def _descend(params, data, spec, kind, method, steps, stop, lrs, notify):
    tol, atol, patience, gtol = stop
    step, optimizer = _optax_step(spec, kind, method, *lrs)
    opt_state = optimizer.init(params)
    history, quiet, converged = [], 0, False
    for i in range(steps):
        params, opt_state, loss = step(params, opt_state, data)
        history.append(float(loss))
        if len(history) > 1:
            change = abs(history[-2] - history[-1]) / max(abs(history[-2]), 1e-30)
            quiet = quiet + 1 if change < tol else 0
        if notify(i, history[-1], params):
            break
        if quiet >= patience or history[-1] <= atol or (
                gtol and i % patience == 0 and float(_grad_norm(params, data, spec, kind)) < gtol):
            converged = True
            break
    history.append(float(loss_at(params, data, spec, kind)))
    return params, history, converged


def _check_fit_args(dataset, spec, method, steps):
    if not isinstance(dataset, Dataset):
        raise TypeError(f"dataset: got {type(dataset).__name__}; expected fitting.Dataset")
    if not isinstance(spec, FitSpec):
        raise TypeError(f"spec: got {type(spec).__name__}; expected FitSpec")
    if method not in FIT_METHODS:
        raise ValueError(f"method: got {method!r}; expected one of {FIT_METHODS}")
    if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int) or steps < 0):
        raise ValueError(f"steps: got {steps!r}; expected an integer >= 0")


def fit(dataset: Dataset, spec: FitSpec | None = None, init=None, *, method="linear", steps=None,
        tol=1e-7, atol=1e-12, patience=20, gtol=None, loss="mse", lr=0.05, lr_shininess=0.05,
        lr_position=0.02, edge_margin=1, shininess_range=(1.0, 2000.0),
        with_uncertainty=True, callback=None) -> FitResult:
    """Fit `spec`'s quantities (default FitSpec(): ka, kd, ks in RGB and shininess) to
    `dataset`, starting from (and holding fixed the rest of)
    `init` (a Material; default DEFAULT_INIT).

    method: 'linear' | 'adam' | 'lbfgs' (module docstring); steps: iteration cap (default
    50 Levenberg-Marquardt iterations, 3000 Adam steps, 500 L-BFGS steps); convergence:
    the relative loss change stays below tol for `patience` steps (Levenberg-Marquardt:
    one step), the loss falls to atol, or the gradient norm (checked every `patience`
    steps) below gtol; loss: 'mse' | 'l1' | 'charbonnier' | 'huber'; lr, lr_shininess,
    lr_position: Adam's per-group rates; edge_margin: silhouette pixels left out;
    shininess_range: the 'linear' search interval; with_uncertainty: compute standard
    errors and identifiability warnings; callback(step, loss, material) -> True stops."""
    spec = FitSpec() if spec is None else spec
    _check_fit_args(dataset, spec, method, steps)
    check_kind(loss)
    init = DEFAULT_INIT if init is None else init
    steps = DEFAULT_STEPS[method] if steps is None else steps
    start = time.perf_counter()
    data = build_cache(dataset, init, edge_margin=edge_margin)
    params = from_values(material_values(init, spec, data.lights if spec.fits_lights else None),
                         spec)
    notify = _notifier(callback, spec, data)
    if method == "linear":
        params = _linear_start(params, data, spec, shininess_range)
        params, history, converged = levenberg_marquardt(params, data, spec, loss, steps=steps,
                                                         tol=tol, atol=atol, callback=notify)
    else:
        params, history, converged = _descend(params, data, spec, loss, method, steps,
                                              (tol, atol, patience, gtol),
                                              (lr, lr_shininess, lr_position), notify)
    return _result(dataset, spec, data, params, history, converged, method,
                   time.perf_counter() - start, with_uncertainty)


def _linear_start(params, data, spec, shininess_range):
    """Replace the material part of params by the variable-projection solution (one
    material; several objects start Levenberg-Marquardt from `init`)."""
    if not spec.fits_material or "objects" in params:
        return params
    solved = from_values(solve_linear(data, spec, shininess_range=shininess_range), spec)
    return {**params, **solved}


def _notifier(callback, spec, data):
    if callback is None:
        return lambda *_: False
    return lambda i, loss, params: bool(callback(
        i, loss, values_to_material(to_values(params, spec), spec, data.material)))


def _result(dataset, spec, data, params, history, converged, method, wall_time, with_unc):
    values = jax.tree.map(np.asarray, to_values(params, spec))
    report = uncertainty(values, data, spec) if with_unc else None
    errors = (relative_errors(values, dataset.truth, spec)
              if dataset.truth is not None and spec.fits_material else None)
    return FitResult(
        material=values_to_material(values, spec, data.material),
        lights=values_to_lights(values, spec, data.lights), values=values, params=params,
        loss=history[-1], loss_history=np.asarray(history), converged=converged,
        n_steps=len(history) - 1, wall_time=wall_time, method=method, errors=errors,
        uncertainty=report, warnings=report.warnings if report else ())


def _material_entries(values, errors):
    """(name, value, relative error or None) of every fitted material quantity; names
    'objects[i].kd' with several objects."""
    if "objects" in values:
        per_object = errors["objects"] if errors else [None] * len(values["objects"])
        return [(f"objects[{i}].{name}", value, error) for i, (one, errs) in
                enumerate(zip(values["objects"], per_object, strict=True))
                for name, value, error in _material_entries(one, errs)]
    return [(name, value, errors.get(name) if errors else None)
            for name, value in values.items() if name != "lights"]


def format_summary(result: FitResult) -> str:
    """Parameter table of a FitResult (see FitResult.summary)."""
    report = result.uncertainty
    se = report.as_dict() if report else {}
    lines = [f"method {result.method}: loss {result.loss:.3e} after {result.n_steps} steps, "
             f"{result.wall_time:.2f} s, {'converged' if result.converged else 'not converged'}",
             f"{'parameter':<12} {'fitted':>10} {'± s.e.':>10} {'rel. error':>11}"]
    for name, value, error in _material_entries(result.values, result.errors):
        flat = np.atleast_1d(value)
        errs = np.atleast_1d(error) if error is not None else [None] * len(flat)
        for c, v in enumerate(flat):
            label = name if len(flat) == 1 else f"{name}[{'rgb'[c]}]"
            s = se.get(label, (None, None))[1]
            err = errs[c] if c < len(errs) else None
            lines.append(f"{label:<12} {v:>10.5g} {'' if s is None else f'{s:.2g}':>10} "
                         f"{'' if err is None else f'{100 * err:.3f}%':>11}")
    notes = report.notes if report else ()
    return "\n".join(lines + [f"warning: {w}" for w in result.warnings]
                     + [f"note: {n}" for n in notes])


"""Resumable fits: the state of a run, its checkpoint file, and a step loop that stops
when asked.

    state = start_run(data, spec, init, method="adam")     # or load_checkpoint(path)
    status, message = advance(state, data, budget=3000, should_stop=flag.is_set,
                              save=lambda s: save_checkpoint(path, s), every=500)
    finish(state, data); result = fit_result(state, dataset, data)   # at the best params

`RunState` is a plain, mutable record that `advance` updates in place after every step,
so it is a consistent snapshot whenever `should_stop`, `on_step` or `save` sees it:
params (unconstrained, fitting.params) and optimizer state, the number of steps taken,
the loss history (history[j] = loss after j steps; the loss of the current params is
known only after the next step, or after `finish`), and the best params seen.

Methods as in fitting.fit: 'adam' and 'lbfgs' take steps of fitting.step's jitted optax
step; 'linear' solves the coefficients in closed form at the start (step 0) and then
takes Levenberg-Marquardt iterations. A step that fitting.step rejects (non-finite loss or
gradient: params and optimizer state unchanged) is not counted; `max_bad` rejected steps
in a row stop the run with status 'non-finite' and a message naming the parameters whose
gradient is not finite. Statuses: 'budget' (step budget reached), 'converged', 'stopped'
(should_stop() returned True), 'non-finite'.

A checkpoint (`save_checkpoint`, written atomically) is JSON: the run's spec, initial
material, method and loss, params, optimizer state (every leaf, non-finite numbers as the
strings 'nan', 'inf', '-inf'), step, history, best params and the caller's `meta`.
"""

import dataclasses
import json
import math
import os
import time
from functools import lru_cache, partial

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.io import write_json
from diffshade.material import Material, material
from fitting.dataset import material_dict
from fitting.fit import FitResult, relative_errors
from fitting.gains import GAIN_NAMES
from fitting.gauss_newton import levenberg_marquardt, loss_at
from fitting.linear import solve_linear
from fitting.loss import check_kind, make_loss
from fitting.params import (
    FitSpec,
    from_values,
    material_values,
    to_values,
    value_names,
    values_to_material,
)
from fitting.step import make_optimizer, make_step
from fitting.uncertainty import uncertainty

FORMAT = "diffshade-fit-checkpoint"
VERSION = 1
METHODS = ("linear", "adam", "lbfgs")


@dataclasses.dataclass
class RunState:
    """spec, init (the held-fixed values and the start), method, kind (loss): what is run;
    params, opt_state (None for 'linear'): where it is; step: steps taken; history: loss
    after each step ([<= step + 1] floats, all finite); best_loss, best_params, best_step:
    the lowest loss seen; quiet: consecutive steps of relative change below tol;
    converged; rejected: steps rejected as non-finite; wall_time: seconds spent so far;
    meta: the caller's description of the run (JSON-ready), saved with the checkpoint."""

    spec: FitSpec
    init: Material
    method: str
    kind: str
    params: dict
    opt_state: object = None
    step: int = 0
    history: list = dataclasses.field(default_factory=list)
    best_loss: float = math.inf
    best_params: dict | None = None
    best_step: int = 0
    quiet: int = 0
    converged: bool = False
    rejected: int = 0
    wall_time: float = 0.0
    meta: dict = dataclasses.field(default_factory=dict)


@lru_cache(maxsize=16)
def _step_and_optimizer(spec, kind, method):
    """One compiled step per configuration, shared by every run in the process."""
    optimizer = make_optimizer(method)
    return make_step(make_loss(spec, kind), optimizer), optimizer


def _check_run(spec, method, kind):
    if not isinstance(spec, FitSpec):
        raise TypeError(f"spec: got {type(spec).__name__}; expected FitSpec")
    if spec.fits_lights:
        raise ValueError("spec: fits light colours or positions; a resumable run fits the "
                         "material only")
    if method not in METHODS:
        raise ValueError(f"method: got {method!r}; expected one of {METHODS}")
    check_kind(kind)


def start_run(data, spec: FitSpec, init: Material, method="linear", kind="mse",
              meta=None) -> RunState:
    """A fresh RunState at `init` (for 'linear': at the closed-form solution) on the cached
    `data` (fitting.build_cache(dataset, init))."""
    _check_run(spec, method, kind)
    params = from_values(material_values(init, spec, n_views=len(data.views)), spec)
    opt_state = None
    if method == "linear" and spec.fits_material:
        params = {**params, **from_values(solve_linear(data, spec), spec)}
    elif method != "linear":
        opt_state = _step_and_optimizer(spec, kind, method)[1].init(params)
    return RunState(spec, init, method, kind, params, opt_state, meta=dict(meta or {}))


# ---- the step loop ----


@jax.jit
def _moved(new, old):
    return jnp.any(jnp.stack([jnp.any(a != b) for a, b in zip(jax.tree.leaves(new),
                                                                 jax.tree.leaves(old),
                                                                 strict=True)]))


@partial(jax.jit, static_argnames=("spec", "kind"))
def _gradients(params, data, spec, kind):
    return jax.grad(make_loss(spec, kind))(params, data)


def nonfinite_gradients(state: RunState, data) -> list:
    """Names ('ka[r]', 'shininess', ...) of the parameters whose gradient is not finite at
    the state's params."""
    grads = _gradients(state.params, data, state.spec, state.kind)
    flat = np.concatenate([np.ravel(g) for g in jax.tree.leaves(grads)])
    return [n for n, g in zip(value_names(grads), flat, strict=True) if not np.isfinite(g)]


def _note(state, loss, params):
    """Log the loss of `params`, the params after len(history) steps."""
    state.history.append(loss)
    if loss < state.best_loss:
        state.best_loss, state.best_params, state.best_step = loss, params, len(state.history) - 1


def _record(state, loss, params, tol, atol, patience):
    """_note, and the convergence test on the change from the previous loss."""
    if state.history:
        change = abs(state.history[-1] - loss) / max(abs(state.history[-1]), 1e-30)
        state.quiet = state.quiet + 1 if change < tol else 0
    _note(state, loss, params)
    state.converged = state.quiet >= patience or loss <= atol


def _accepted(state, new_params, loss, data):
    """Did fitting.step take this step? It leaves params unchanged when the loss or the
    gradient is not finite; unchanged params with finite gradients are a zero update."""
    if not math.isfinite(loss):
        return False
    return bool(_moved(new_params, state.params)) or not nonfinite_gradients(state, data)


def _nonfinite_message(state, data, when):
    names = nonfinite_gradients(state, data)
    values = to_values(state.params, state.spec)
    flat = np.concatenate([np.ravel(v) for v in jax.tree.leaves(values)])
    shown = ", ".join(f"{n} = {v:.4g}" for n, v in zip(value_names(values), flat, strict=True)
                      if n in names) or "none (the loss itself is not finite)"
    return (f"the loss or its gradient was not finite {when}; non-finite gradient with "
            f"respect to: {shown}")


def _advance_optax(state, data, budget, rule, hooks):
    step_fn = _step_and_optimizer(state.spec, state.kind, state.method)[0]
    should_stop, on_step, save, every, max_bad = hooks
    bad = 0
    while state.step < budget and not state.converged:
        params, opt_state, loss = step_fn(state.params, state.opt_state, data)
        loss = float(loss)
        if not _accepted(state, params, loss, data):
            bad, state.rejected = bad + 1, state.rejected + 1
            if math.isfinite(loss) and len(state.history) == state.step:
                _note(state, loss, state.params)  # a finite loss with a non-finite gradient
            if bad >= max_bad:
                return "non-finite", _nonfinite_message(
                    state, data, f"for {max_bad} steps in a row at step {state.step}")
        else:
            bad = 0
            if len(state.history) == state.step:  # else known already (finish, then resume)
                _record(state, loss, state.params, *rule)
            state.params, state.opt_state, state.step = params, opt_state, state.step + 1
            on_step(state)
            if every and state.step % every == 0:
                save(state)
        if should_stop():
            return "stopped", ""
    return ("converged", "") if state.converged else ("budget", "")


def _advance_lm(state, data, budget, rule, hooks):
    should_stop, on_step, save, every, _ = hooks
    tol, atol, _ = rule

    def callback(_, loss, params):
        _record(state, float(loss), params, *rule)
        state.params, state.step = params, state.step + 1
        on_step(state)
        if every and state.step % every == 0:
            save(state)
        return bool(should_stop())

    if len(state.history) == state.step:
        loss = float(loss_at(state.params, data, state.spec, state.kind))
        if not math.isfinite(loss):
            return "non-finite", _nonfinite_message(state, data, f"at step {state.step}")
        _record(state, loss, state.params, *rule)
    if state.step < budget and not state.converged and not should_stop():
        _, _, state.converged = levenberg_marquardt(
            state.params, data, state.spec, state.kind, steps=budget - state.step, tol=tol,
            atol=atol, callback=callback)
    if should_stop():
        return "stopped", ""
    return ("converged", "") if state.converged else ("budget", "")


def advance(state: RunState, data, *, budget: int, tol=1e-7, atol=1e-12, patience=20,
            max_bad=5, should_stop=lambda: False, on_step=lambda state: None,
            save=lambda state: None, every=0) -> tuple:
    """Take steps until state.step reaches `budget`, convergence (relative loss change
    below tol for `patience` steps — one step for Levenberg-Marquardt — or loss <= atol),
    should_stop() (checked after every step), or `max_bad` rejected steps in a row.
    on_step(state) after every step; save(state) every `every` steps (0: never).
    Returns (status, message); see the module docstring."""
    start = time.perf_counter()
    advance_fn = _advance_lm if state.method == "linear" else _advance_optax
    try:
        return advance_fn(state, data, budget, (tol, atol, patience),
                          (should_stop, on_step, save, every, max_bad))
    finally:
        state.wall_time += time.perf_counter() - start


def finish(state: RunState, data) -> None:
    """Log the loss of the current params when it is not known yet (so that best_params
    is the best of every params visited); a non-finite loss is left out."""
    if len(state.history) == state.step:
        loss = float(loss_at(state.params, data, state.spec, state.kind))
        if math.isfinite(loss):
            _note(state, loss, state.params)


def fit_result(state: RunState, dataset, data, with_uncertainty=True) -> FitResult:
    """A FitResult at the state's best params: values, standard errors and warnings
    (fitting.uncertainty, not raised as warnings), relative errors when the dataset knows
    its truth; loss is the best loss, loss_history the whole history."""
    if state.best_params is None:
        raise ValueError("state: no step had a finite loss; there is no result to report")
    spec = state.spec
    values = jax.tree.map(np.asarray, to_values(state.best_params, spec))
    report = uncertainty(values, data, spec, warn=False) if with_uncertainty else None
    errors = (relative_errors(values, dataset.truth, spec)
              if dataset.truth is not None and spec.fits_material else None)
    return FitResult(
        material=values_to_material(values, spec, data.material), lights=tuple(data.lights),
        values=values, params=state.best_params, loss=state.best_loss,
        loss_history=np.asarray(state.history), converged=state.converged,
        n_steps=state.step, wall_time=state.wall_time, method=state.method, errors=errors,
        uncertainty=report, warnings=report.warnings if report else ())


# ---- the checkpoint file ----


def _encode(leaf):
    arr = np.asarray(leaf)
    flat = [x if math.isfinite(x) else str(x) for x in arr.astype(np.float64).ravel().tolist()]
    return {"dtype": str(arr.dtype), "shape": list(arr.shape), "data": flat}


def _decode(entry, template, where):
    want = np.asarray(template)
    data = np.array([float(x) for x in entry["data"]], np.float64)
    if tuple(entry["shape"]) != want.shape or data.size != want.size:
        raise ValueError(f"{where}: got shape {entry['shape']}; expected {list(want.shape)}")
    return jnp.asarray(data.reshape(want.shape).astype(want.dtype))


def _encode_tree(tree):
    return None if tree is None else [_encode(leaf) for leaf in jax.tree.leaves(tree)]


def _decode_tree(entries, template, where):
    leaves, treedef = jax.tree.flatten(template)
    if not isinstance(entries, list) or len(entries) != len(leaves):
        count = len(entries) if isinstance(entries, list) else entries
        raise ValueError(f"{where}: got {count} arrays; expected {len(leaves)}")
    return jax.tree.unflatten(treedef, [_decode(e, t, f"{where}[{i}]")
                                        for i, (e, t) in enumerate(zip(entries, leaves,
                                                                       strict=True))])


def save_checkpoint(path, state: RunState) -> str:
    """Write the state to `path` (JSON, atomically); returns the path."""
    return write_json(path, {
        "format": FORMAT, "version": VERSION, "meta": state.meta,
        "spec": dataclasses.asdict(state.spec), "init": material_dict(state.init),
        "method": state.method, "loss": state.kind, "step": state.step,
        "params": _encode_tree(state.params), "optimizer_state": _encode_tree(state.opt_state),
        "loss_history": state.history, "best": {
            "step": state.best_step, "loss": state.best_loss if state.best_params else None,
            "params": _encode_tree(state.best_params)},
        "quiet": state.quiet, "converged": state.converged, "rejected": state.rejected,
        "wall_time": state.wall_time, "n_views": _n_views(state.params)})


def _n_views(params):
    """The views the per-view gains (fitting.gains) of params cover, or None."""
    gains = [params[name] for name in GAIN_NAMES if name in params]
    return int(np.shape(gains[0])[0]) + 1 if gains else None


def _read(path):
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"checkpoint not found: {path!r}")
    try:
        with open(path, encoding="utf-8") as file:
            data = json.load(file)
    except json.JSONDecodeError as err:
        raise ValueError(f"checkpoint {path!r}: not valid JSON ({err})") from err
    if not isinstance(data, dict) or data.get("format") != FORMAT or data.get("version") != VERSION:
        raise ValueError(f"checkpoint {path!r}: not a {FORMAT} file of version {VERSION}")
    return data


def load_checkpoint(path) -> RunState:
    """The RunState saved at `path`. Raises FileNotFoundError when there is none and
    ValueError naming the file when it is not a valid checkpoint."""
    data = _read(path)
    try:
        spec, init = FitSpec(**data["spec"]), material(**data["init"])
        method, kind = data["method"], data["loss"]
        _check_run(spec, method, kind)
        template = from_values(material_values(init, spec, n_views=data.get("n_views")), spec)
        params = _decode_tree(data["params"], template, "params")
        opt_state = None
        if method != "linear":
            opt_state = _decode_tree(data["optimizer_state"],
                                     _step_and_optimizer(spec, kind, method)[1].init(params),
                                     "optimizer_state")
        best = data["best"]
        best_params = (None if best["params"] is None
                       else _decode_tree(best["params"], template, "best.params"))
        return RunState(spec, init, method, kind, params, opt_state, int(data["step"]),
                        [float(x) for x in data["loss_history"]],
                        math.inf if best["loss"] is None else float(best["loss"]),
                        best_params, int(best["step"]), int(data["quiet"]),
                        bool(data["converged"]), int(data["rejected"]),
                        float(data["wall_time"]), dict(data["meta"]))
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"checkpoint {os.fspath(path)!r}: {err}") from err

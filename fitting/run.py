"""The one fit driver: the state of a run and the step loop that `fitting.fit` and
`diffshade fit` both use.

    state = start_run(data, spec, init, FitOptions(method="adam"))   # or load_checkpoint
    status, message = advance(state, data, should_stop=flag.is_set, on_step=show,
                              save=lambda s: save_checkpoint(path, s), every=500)
    finish(state, data)            # then fitting.driver.fit_result(state, dataset, data)

`RunState` is a plain, mutable record that `advance` updates in place after every step,
so it is a consistent snapshot whenever `should_stop`, `on_step` or `save` sees it: the
spec, the initial material and every option (fitting.solve.options) — what is run — and the
params (unconstrained, fitting.spec.params), the optimizer state, the steps taken, the loss
history (history[j] = loss after j steps; for the optax methods the loss of the current
params is known only after the next step, or after `finish`) and the best params seen.

Methods (fitting.solve.options.METHODS): 'adam' and 'lbfgs' take fitting.solve.step's jitted optax
steps, guarded by optax.apply_if_finite: a step with a non-finite loss or gradient leaves
the params and the inner state unchanged and is not counted; `max_bad` of them in a row
stop the run with status 'non-finite' and a message naming the parameters whose gradient
is not finite. 'linear' solves the coefficients in closed form at the start (step 0) and
then takes Levenberg-Marquardt iterations (fitting.solve.gauss_newton.lm_step), whose state is
the damping. Statuses: 'budget' (the step budget reached), 'converged', 'stopped'
(should_stop() returned True), 'non-finite'.
"""

import dataclasses
import math
import time
from functools import lru_cache, partial

import jax
import numpy as np
import optax

from diffshade.scene import Material
from fitting.model.batch import batched
from fitting.model.loss import make_loss
from fitting.solve.distribute import ShardedViews, fit_data
from fitting.solve.gauss_newton import lm_step, loss_at
from fitting.solve.linear import solve_linear
from fitting.solve.options import METHODS, FitOptions
from fitting.solve.step import make_optimizer, make_step
from fitting.spec.params import FitSpec, from_values, material_values, to_values, value_names

LM_DAMPING = 1e-3


@dataclasses.dataclass
class RunState:
    """spec, init (the held-fixed values and the start), options: what is run; params,
    opt_state (the optax state, or the Levenberg-Marquardt damping): where it is; step:
    steps taken; history: loss after each step ([<= step + 1] floats, all finite);
    best_loss, best_params, best_step: the lowest loss seen; quiet: consecutive steps of
    relative change below tol; converged; rejected: steps rejected as non-finite;
    wall_time: seconds spent so far; meta: the caller's description of the run
    (JSON-ready), saved with the checkpoint."""

    spec: FitSpec
    init: Material
    options: FitOptions
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

    @property
    def method(self):
        return self.options.method

    @property
    def kind(self):
        """The image loss ('mse', ...)."""
        return self.options.loss


@lru_cache(maxsize=16)
def optax_step(spec, kind, method, lr, lr_shininess, lr_position):
    """(step, optimizer): one compiled step per configuration, shared by every run."""
    optimizer = make_optimizer(method, lr=lr, lr_shininess=lr_shininess,
                               lr_position=lr_position)
    return make_step(make_loss(spec, kind), optimizer), optimizer


def _optax_step_of(spec, options, data=None):
    if isinstance(data, ShardedViews):  # fitting.solve.distribute: sharded, chunked views
        optimizer = _optax_step_of(spec, options)[1]
        return data.step_fn(spec, options, optimizer), optimizer
    return optax_step(spec, options.loss, options.method, options.lr, options.lr_shininess,
                      options.lr_position)


def initial_opt_state(spec, options, params):
    """The optimizer state at the start: the optax state, or the initial damping."""
    if not METHODS[options.method].optax:
        return np.float64(LM_DAMPING)
    return _optax_step_of(spec, options)[1].init(params)


def check_run(spec, init, options):
    if not isinstance(spec, FitSpec):
        raise TypeError(f"spec: got {type(spec).__name__}; expected FitSpec")
    if not isinstance(init, Material):
        raise TypeError(f"init: got {type(init).__name__}; expected a Material")
    if not isinstance(options, FitOptions):
        raise TypeError(f"options: got {type(options).__name__}; expected FitOptions")


def start_params(spec, init, lights, n_views=None):
    """Unconstrained params of `init` (and `lights`, one LightGroups per view, when the
    spec fits them; per-view gains start at 1 for n_views views, default len(lights))."""
    if n_views is None and lights is not None:
        n_views = len(lights)
    return from_values(material_values(init, spec, lights if spec.fits_lights else None,
                                       n_views=n_views), spec)


def start_run(data, spec: FitSpec, init: Material, options: FitOptions | None = None,
              meta=None) -> RunState:
    """A fresh RunState at `init` (for 'linear' with one object: at the closed-form
    solution) on the cached `data` (fitting.model.build_cache(dataset, init), or its
    fitting.solve.distribute.ShardedViews); options default FitOptions()."""
    options = FitOptions() if options is None else options
    check_run(spec, init, options)
    params = start_params(spec, init, fit_data(data).lights)
    # several objects: Levenberg-Marquardt starts from `init` (the closed-form start
    # solves one material); kt, not linear, starts from `init` too
    linear = bool(spec.coefficients) or spec.shininess
    if options.method == "linear" and linear and "objects" not in params:
        # sharded views: their sums a chunk at a time (fitting.solve.linear.fold_parts)
        solved = solve_linear(data, spec, shininess_range=options.shininess_range)
        params = {**params, **from_values(solved, spec)}
    return RunState(spec, init, options, params, initial_opt_state(spec, options, params),
                    meta=dict(meta or {}))


# ---- bookkeeping ----


@partial(jax.jit, static_argnames=("spec", "kind"))
def gradients(params, data, spec, kind):
    return jax.grad(make_loss(spec, kind))(params, data)


def _stacked(data):
    """The data a compiled step reads: sharded views as they are, a FitData with its views
    stacked once (fitting.model.batch.batched), not in every step."""
    return data if isinstance(data, ShardedViews) else batched(data)


def _gradients_at(state, data):
    if isinstance(data, ShardedViews):  # fitting.solve.distribute
        return data.value_and_grad(state.params, state.spec, state.kind)[1]
    return gradients(state.params, _stacked(data), state.spec, state.kind)


def nonfinite_gradients(state: RunState, data) -> list:
    """Names ('ka[r]', 'shininess', ...) of the parameters whose gradient is not finite at
    the state's params."""
    grads = _gradients_at(state, data)
    flat = np.concatenate([np.ravel(g) for g in jax.tree.leaves(grads)])
    return [n for n, g in zip(value_names(grads), flat, strict=True) if not np.isfinite(g)]


def _nonfinite_message(state, data, when):
    names = nonfinite_gradients(state, data)
    values = to_values(state.params, state.spec)
    flat = np.concatenate([np.ravel(v) for v in jax.tree.leaves(values)])
    shown = ", ".join(f"{n} = {v:.4g}" for n, v in zip(value_names(values), flat, strict=True)
                      if n in names) or "none (the loss itself is not finite)"
    return (f"the loss or its gradient was not finite {when}; non-finite gradient with "
            f"respect to: {shown}")


def _note(state, loss, params):
    """Log the loss of `params`, the params after len(history) steps."""
    state.history.append(loss)
    if loss < state.best_loss:
        state.best_loss, state.best_params, state.best_step = loss, params, len(state.history) - 1


def _record(state, loss, params):
    """_note, and the convergence test on the change from the previous loss."""
    options = state.options
    if state.history:
        change = abs(state.history[-1] - loss) / max(abs(state.history[-1]), 1e-30)
        state.quiet = state.quiet + 1 if change < options.tol else 0
    _note(state, loss, params)
    state.converged = state.quiet >= options.stop_patience or loss <= options.atol


def _small_gradient(state, data):
    """The gtol test, every `patience` steps."""
    options = state.options
    if options.gtol is None or state.step % options.stop_patience:
        return False
    grads = _gradients_at(state, data)
    return float(optax.tree.norm(grads)) < options.gtol


def _loss_known(state):
    return len(state.history) > state.step


# ---- one step of each kind: 'moved', 'rejected', 'converged' or 'non-finite' ----


def _optax_take(state, data):
    step_fn = _optax_step_of(state.spec, state.options, data)[0]
    params, opt_state, loss = step_fn(state.params, state.opt_state, _stacked(data))
    loss = float(loss)
    state.opt_state = opt_state  # rejected: only apply_if_finite's counters changed
    if not bool(opt_state.last_finite):
        state.rejected += 1
        if math.isfinite(loss) and not _loss_known(state):
            _note(state, loss, state.params)  # a finite loss with a non-finite gradient
        return "non-finite" if int(opt_state.notfinite_count) >= state.options.max_bad \
            else "rejected"
    if not _loss_known(state):  # else known already (finish, then resume)
        _record(state, loss, state.params)
    state.params, state.step = params, state.step + 1
    return "moved"


def _lm_take(state, data):
    if not _loss_known(state):
        loss = float(loss_at(state.params, data, state.spec, state.kind))
        if not math.isfinite(loss):
            return "non-finite"
        _record(state, loss, state.params)
        if state.converged:
            return "converged"
    found = lm_step(state.params, data, state.spec, state.kind, float(state.opt_state))
    if found.status != "moved":
        return found.status
    state.params, state.opt_state = found.params, np.float64(found.damping)
    state.step += 1
    _record(state, found.loss, found.params)
    return "moved"


def advance(state: RunState, data, *, should_stop=lambda: False, on_step=lambda state: None,
            save=lambda state: None, every=0) -> tuple:
    """Take steps until state.step reaches the budget (state.options.budget), convergence
    (relative loss change below tol for `patience` steps — one step for Levenberg-
    Marquardt —, loss <= atol, or gradient norm below gtol), should_stop() (checked after
    every step), or `max_bad` rejected steps in a row. on_step(state) after every step;
    save(state) every `every` steps (0: never). Returns (status, message); see the module
    docstring."""
    start = time.perf_counter()
    take = _optax_take if METHODS[state.method].optax else _lm_take
    try:
        while state.step < state.options.budget and not state.converged:
            outcome = take(state, data)
            if outcome == "non-finite":
                when = (f"for {state.options.max_bad} steps in a row at step {state.step}"
                        if METHODS[state.method].optax else f"at step {state.step}")
                return "non-finite", _nonfinite_message(state, data, when)
            if outcome == "converged":
                state.converged = True
            elif outcome == "moved":
                state.converged = state.converged or _small_gradient(state, data)
                on_step(state)
                if every and state.step % every == 0:
                    save(state)
            if should_stop():
                return "stopped", ""
        return ("converged", "") if state.converged else ("budget", "")
    finally:
        state.wall_time += time.perf_counter() - start


def finish(state: RunState, data) -> None:
    """Log the loss of the current params when it is not known yet (so that best_params
    is the best of every params visited); a non-finite loss is left out."""
    if not _loss_known(state):
        loss = float(loss_at(state.params, data, state.spec, state.kind))
        if math.isfinite(loss):
            _note(state, loss, state.params)

"""`diffshade fit DATASET -o RESULT`: fit a material to a dataset folder (see docs/cli.md).

    diffshade fit DATASET -o RESULT [--method linear|adam|lbfgs] [--steps N]
        [--fit ka,kd,ks,shininess] [--grey NAMES] [--init KA,KD,KS,N|FILE.json]
        [--loss mse|l1|charbonnier|huber] [--color-space srgb|linear] [--tol T]
        [--checkpoint-every N] [--resume] [--quiet]

Everything that can be wrong with the input (options, the dataset folder, its targets,
the output path, the checkpoint to resume; fitting.inputs) is checked before anything is
written; such an error is raised as ValueError or OSError, which diffshade.cli prints as
one line (exit 2). Then the fit runs (fitting.checkpoint) with a progress bar on a terminal, writing
RESULT/checkpoint.json every --checkpoint-every steps, and at its end the result files
(fitting.report) and the true-versus-recovered table.

Exit status: 0 done; 2 bad input (nothing written); 3 the fit stopped on non-finite
values (the best finite parameters are written); 128 + signal number (130 SIGINT, 143
SIGTERM) interrupted: the signal handlers only record the signal, the loop stops after
the current step, and the checkpoint and complete result files are written (further
signals are ignored meanwhile). A signal before the first step ends the command at once,
writing nothing.
"""

import os
import signal
import sys
import threading
import time
from typing import NamedTuple

import jax
import numpy as np
from tqdm import tqdm

from diffshade.color import COLOR_SPACES
from fitting.cache import build_cache
from fitting.checkpoint import (
    advance,
    finish,
    fit_result,
    load_checkpoint,
    material_dict,
    save_checkpoint,
    start_run,
)
from fitting.fit import DEFAULT_STEPS, FIT_METHODS
from fitting.gains import GAIN_NAMES
from fitting.inputs import (
    check_output,
    dataset_fingerprint,
    fit_spec,
    load_checked_dataset,
    non_negative_float,
    parse_material,
    positive_int,
)
from fitting.loss import LOSSES
from fitting.params import COEFFICIENTS, DEFAULT_INIT, FitSpec, to_values
from fitting.report import comparison_table, write_result

CHECKPOINT = "checkpoint.json"
RESULT_FORMAT = "diffshade-fit-result"
EXIT_NON_FINITE = 3
SIGNALS = {signal.SIGINT: "SIGINT", signal.SIGTERM: "SIGTERM"}


# ---- the parser ----


def register(subparsers):
    parser = subparsers.add_parser(
        "fit", help="fit a Blinn-Phong material to a dataset folder",
        description="Fit ka, kd, ks and shininess to the target images of a dataset folder "
                    "(made by 'diffshade synth' or by hand, see docs/cli.md) and write the "
                    "result files into RESULT. On --resume, options left out are taken from "
                    "RESULT/checkpoint.json and the ones given must agree with it.")
    parser.add_argument("dataset", metavar="DATASET", help="dataset folder")
    parser.add_argument("-o", "--output", required=True, metavar="RESULT",
                        help="result folder (created if missing)")
    parser.add_argument("--method", choices=FIT_METHODS,
                        help="'linear' (default): closed form + Levenberg-Marquardt; "
                             "'adam'; 'lbfgs'")
    parser.add_argument("--steps", type=positive_int, metavar="N",
                        help="step budget, counted across resumes (default: "
                             + ", ".join(f"{m} {n}" for m, n in DEFAULT_STEPS.items()) + ")")
    parser.add_argument("--fit", metavar="NAMES",
                        help="comma-separated quantities to fit (default ka,kd,ks,shininess; "
                             "also exposure, white_balance: per-view gains against view 0)")
    parser.add_argument("--grey", metavar="NAMES",
                        help="coefficients fitted as one grey value (default: none, RGB)")
    parser.add_argument("--init", metavar="KA,KD,KS,N|FILE",
                        help="start and held-fixed values (default 0.3,0.5,0.3,20)")
    parser.add_argument("--loss", choices=LOSSES, help="image loss (default mse)")
    parser.add_argument("--color-space", choices=COLOR_SPACES,
                        help="decode every PNG/JPEG target as this, overriding the dataset's "
                             "'color_space' keys and the files' own tags (default: as they "
                             "say, else srgb; .npy targets are linear; docs/color.md)")
    parser.add_argument("--tol", type=non_negative_float, default=1e-7,
                        help="stop when the relative loss change stays below this (0: never)")
    parser.add_argument("--checkpoint-every", type=positive_int, default=500, metavar="N",
                        help="write RESULT/checkpoint.json every N steps (default 500)")
    parser.add_argument("--resume", action="store_true",
                        help="continue from RESULT/checkpoint.json")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.set_defaults(run=run_fit)


# ---- the run's plan (nothing is written before it is made) ----


def _check_agrees(args, state, checkpoint):
    """On --resume, every option given must describe the checkpoint's run."""
    given = {"--method": (args.method, state.method), "--loss": (args.loss, state.kind),
             "--color-space": (args.color_space, state.meta.get("color_space"))}
    for option, (value, saved) in given.items():
        if value is not None and value != saved:
            raise ValueError(f"{option}: got {value!r}; the checkpoint {checkpoint!r} was "
                             f"made with {saved!r}")
    if (args.fit is not None or args.grey is not None) and fit_spec(args.fit,
                                                                   args.grey) != state.spec:
        raise ValueError(f"--fit/--grey: describe another fit than the checkpoint "
                         f"{checkpoint!r} ({state.spec})")
    if args.init is not None:
        init = material_dict(parse_material(args.init, "--init"))
        if init != material_dict(state.init):
            raise ValueError(f"--init: got {args.init!r}; the checkpoint {checkpoint!r} was "
                             f"made from {material_dict(state.init)}")


class Plan(NamedTuple):
    """What `fit` will run: the fit spec, initial material, method and loss, and the
    RunState to continue (None: a fresh run); budget: the step budget; fingerprint: of the
    dataset's targets."""

    spec: FitSpec
    init: object
    method: str
    kind: str
    state: object
    budget: int
    fingerprint: str


def _prepare(args):
    """Check every input; returns (dataset, Plan). Writes nothing."""
    check_output(args.output)
    checkpoint = os.path.join(args.output, CHECKPOINT)
    state = load_checkpoint(checkpoint) if args.resume else None
    if state is not None:
        _check_agrees(args, state, checkpoint)
        spec, init, method, kind = state.spec, state.init, state.method, state.kind
    else:
        spec, method, kind = fit_spec(args.fit, args.grey), args.method or "linear", args.loss
        init = DEFAULT_INIT if args.init is None else parse_material(args.init, "--init")
    if state is not None and args.color_space is None:
        args.color_space = state.meta.get("color_space")
    dataset = load_checked_dataset(args.dataset, args.color_space)
    fingerprint = dataset_fingerprint(dataset)
    if state is not None and state.meta.get("dataset_sha256") != fingerprint:
        raise ValueError(f"DATASET: {args.dataset!r} holds other targets than the dataset the "
                         f"checkpoint {checkpoint!r} was made with")
    budget = args.steps or (state.meta.get("steps") if state else None) or DEFAULT_STEPS[method]
    return dataset, Plan(spec, init, method, kind or "mse", state, budget, fingerprint)


# ---- signals and progress ----


class _Signals:
    """Records the first SIGINT or SIGTERM while active; never acts on it (the fit loop
    asks `received` after every step). Handlers are only installed in the main thread."""

    def __init__(self):
        self.received = None
        self._previous = {}

    def _handler(self, signum, _frame):
        if self.received is None:
            self.received = signum

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self._previous = {s: signal.signal(s, self._handler) for s in SIGNALS}
        return self

    def __exit__(self, *_):
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)


def _brief(state):
    """'loss 1.2e-04 ka .35/.30/.50 ... shininess 35.2' for the progress bar."""
    values = jax.tree.map(np.asarray, to_values(state.params, state.spec))
    parts = [f"loss {state.history[-1]:.3e}" if state.history else ""]
    for name, value in values.items():
        parts.append(f"{name} " + "/".join(f"{v:.3g}" for v in np.atleast_1d(value)))
    return " ".join(parts)


def _progress(state, budget, quiet):
    """A tqdm bar (stderr; off when not a terminal or with --quiet) and on_step(state)."""
    bar = tqdm(total=budget, initial=state.step, disable=True if quiet else None,
               unit="step", dynamic_ncols=True, file=sys.stderr, desc=f"fit {state.method}")
    shown = [0.0]

    def on_step(state):
        if bar.disable:
            return
        bar.update(state.step - bar.n)
        if time.monotonic() - shown[0] > 0.1:  # tqdm redraws at most every 0.1 s
            bar.set_postfix_str(_brief(state), refresh=False)
            shown[0] = time.monotonic()
    return bar, on_step


# ---- the command ----


def _extra(args, state, status, signum, message):
    return {"format": RESULT_FORMAT, "version": 1,
            "dataset": os.path.abspath(args.dataset), "loss_kind": state.kind,
            "color_space": args.color_space,
            "fit": {name: getattr(state.spec, name)
                    for name in (*COEFFICIENTS, "shininess", *GAIN_NAMES)},
            "status": status, "interrupted": signum is not None,
            "signal": SIGNALS.get(signum), "stop_message": message or None,
            "best_step": state.best_step, "rejected_steps": state.rejected,
            "checkpoint": CHECKPOINT}


def _report(args, dataset, data, state, status, message, signum):
    """Write the checkpoint and the result files, print the table; returns the exit code."""
    result_path = os.path.join(args.output, "result.json")
    save_checkpoint(os.path.join(args.output, CHECKPOINT), state)
    result = fit_result(state, dataset, data)
    label = {"stopped": f"interrupted ({SIGNALS.get(signum)})", "budget": "step budget reached",
             "non-finite": "stopped on non-finite values"}.get(status, status)
    paths = write_result(args.output, dataset, result, state.init,
                         _extra(args, state, status, signum, message),
                         f"diffshade fit: {state.method}, {state.kind} loss")
    print(comparison_table(result, dataset.truth, label))
    for path in paths:
        print(path)
    where = f"the best parameters so far (step {state.best_step}) are in {result_path}"
    if status == "non-finite":
        print(f"diffshade: error: fit stopped: {message}; {where}", file=sys.stderr)
        return EXIT_NON_FINITE
    if signum is not None:
        print(f"diffshade: interrupted by {SIGNALS[signum]} at step {state.step}; {where}; "
              "continue with --resume", file=sys.stderr)
        return 128 + signum
    return 0


def run_fit(args) -> int:
    """The `fit` command (module docstring)."""
    with _Signals() as signals:
        dataset, plan = _prepare(args)
        start = time.perf_counter()
        data = build_cache(dataset, plan.init)
        state = plan.state or start_run(data, plan.spec, plan.init, plan.method, plan.kind)
        state.meta |= {"dataset_sha256": plan.fingerprint, "steps": plan.budget,
                       "color_space": args.color_space}
        if signals.received is not None:
            print(f"diffshade: interrupted by {SIGNALS[signals.received]} before the first "
                  "step; nothing written", file=sys.stderr)
            return 128 + signals.received
        state.wall_time += time.perf_counter() - start
        bar, on_step = _progress(state, plan.budget, args.quiet)
        with bar:
            status, message = advance(
                state, data, budget=plan.budget, tol=args.tol,
                should_stop=lambda: signals.received is not None, on_step=on_step,
                save=lambda s: save_checkpoint(os.path.join(args.output, CHECKPOINT), s),
                every=args.checkpoint_every)
        finish(state, data)
        if state.best_params is None:
            print(f"diffshade: error: fit stopped: {message}; no step had a finite loss, "
                  "nothing written", file=sys.stderr)
            return EXIT_NON_FINITE
        return _report(args, dataset, data, state, status, message, signals.received)

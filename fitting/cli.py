"""`diffshade fit DATASET -o RESULT`: fit a material to a dataset folder (see docs/cli.md).

    diffshade fit DATASET -o RESULT [--method linear|adam|lbfgs] [--steps N]
        [--fit ka,kd,ks,shininess,light_colors,light_positions] [--grey NAMES]
        [--init KA,KD,KS,N|FILE.json] [--loss mse|l1|charbonnier|huber]
        [--color-space srgb|linear] [--tol T] [--atol T] [--gtol T] [--patience N]
        [--lr R] [--lr-shininess R] [--lr-position R] [--edge-margin N]
        [--shininess-range LOW,HIGH] [--max-bad N] [--checkpoint-every N] [--resume]
        [--holdout N,M] [--quiet] [--refine-pose]

The fit is fitting.run's, the driver `fitting.fit` uses, with the same options: one flag
per field of fitting.solve.options.FitOptions. A dataset of several objects (scene files with
"objects") has every object's material fitted at once: --init is every object's start
(KA,KD,KS,N) or one per object (a file {"objects": ...}, fitting.data.views.material_for), and
the table, material.mtl and result.json have each object's part (fitting.report.result).
--holdout N,M keeps those views out of the fit and evaluates the fitted material on them
(fitting.report.holdout): a PSNR table after the result table, holdout_NNN.png panels and
result.json's "holdout".

Everything that can be wrong with the input (options, the dataset folder, its targets,
the output path, the checkpoint to resume; fitting.plan, fitting.inputs) is checked
before anything is written; such an error is raised as ValueError or OSError, which
diffshade.cli prints as one line (exit 2). Then the fit runs with a progress bar on a
terminal, writing RESULT/checkpoint.json every --checkpoint-every steps, and at its end
the result files (fitting.report.result) and the true-versus-recovered table. On --resume every
option left out comes from the checkpoint, so the run continues with the settings it
started with.

Exit status: 0 done (also when the model does not explain the images: a
`diffshade: warning:` line on stderr and `misfit` in result.json say so); 2 bad input
(nothing written); 3 the fit stopped on non-finite values (the best finite parameters are
written); 128 + signal number (130 SIGINT, 143 SIGTERM) interrupted: the signal handlers
only record the signal, the loop stops after the current step, and the checkpoint and
complete result files are written (further signals are ignored meanwhile). A signal
before the first step ends the command at once, writing nothing.
"""

import argparse
import dataclasses
import os
import signal
import sys
import threading
import time

import jax
import numpy as np
from tqdm import tqdm

from diffshade.io import COLOR_SPACES
from fitting.checkpoint import save_checkpoint
from fitting.driver import fit_result
from fitting.inputs import non_negative_float, non_negative_int, positive_float, positive_int
from fitting.model.cache import build_cache
from fitting.model.loss import LOSSES
from fitting.plan import CHECKPOINT, flag, prepare
from fitting.precompile import await_background
from fitting.refine import pose_records, refined_poses
from fitting.report.holdout import holdout_results, holdout_table, write_panels
from fitting.report.result import RESULT_FORMAT, STATUS_LABELS, comparison_table, write_result
from fitting.run import advance, finish, start_run
from fitting.solve.distribute import fit_data, for_options
from fitting.solve.options import FIT_METHODS, OPTIONS, FitOptions
from fitting.spec.params import to_values
from fitting.texture_fit import add_texture_options, run_texture

EXIT_NON_FINITE = 3
SIGNALS = {signal.SIGINT: "SIGINT", signal.SIGTERM: "SIGTERM"}


# ---- the parser ----


def number_pair(text):
    """argparse type: LOW,HIGH with 0 < LOW < HIGH."""
    try:
        low, high = (float(x) for x in text.split(","))
        FitOptions(shininess_range=(low, high))
    except ValueError:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected LOW,HIGH with "
                                         "0 < LOW < HIGH") from None
    return low, high


def view_indices(text):
    """argparse type: N,M,... distinct view indices >= 0."""
    try:
        indices = tuple(int(x) for x in text.split(","))
    except ValueError:
        indices = ()
    if not indices or min(indices) < 0 or len(set(indices)) != len(indices):
        raise argparse.ArgumentTypeError(f"got {text!r}; expected distinct view indices "
                                         ">= 0 separated by commas, e.g. 3 or 0,4")
    return indices


def device_count(text):
    """argparse type: 'all' or an integer >= 1."""
    if text == "all":
        return text
    try:
        return positive_int(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected 'all' or an integer "
                                         ">= 1") from None


# The argparse type of every FitOptions field (choices for 'method' and 'loss').
_OPTION_TYPES = {"method": FIT_METHODS, "steps": positive_int, "loss": LOSSES,
                 "tol": non_negative_float, "atol": non_negative_float,
                 "patience": positive_int, "gtol": non_negative_float, "lr": positive_float,
                 "lr_shininess": positive_float, "lr_position": positive_float,
                 "edge_margin": non_negative_int, "shininess_range": number_pair,
                 "max_bad": positive_int, "devices": device_count, "chunk": positive_int}


def _add_option(parser, name):
    """--NAME for the FitOptions field `name`, default None (not given)."""
    kind, default = _OPTION_TYPES[name], FitOptions.__dataclass_fields__[name].default
    shown = ",".join(map(str, default)) if isinstance(default, tuple) else default
    help_text = OPTIONS[name].help + ("" if default is None else f" (default {shown})")
    if isinstance(kind, tuple):
        parser.add_argument(flag(name), choices=kind, help=help_text)
    else:
        metavar = {number_pair: "LOW,HIGH", positive_int: "N", non_negative_int: "N",
                   device_count: "all|N"}
        parser.add_argument(flag(name), type=kind, metavar=metavar.get(kind, "X"),
                            help=help_text)


def register(subparsers):
    parser = subparsers.add_parser(
        "fit", help="fit a Blinn-Phong material to a dataset folder",
        description="Fit ka, kd, ks and shininess (and, with --fit, light colours and "
                    "positions) to the target images of a dataset folder (made by "
                    "'diffshade synth' or by hand, see docs/cli.md) and write the result "
                    "files into RESULT. On --resume, options left out are taken from "
                    "RESULT/checkpoint.json and the ones given must agree with it.")
    parser.add_argument("dataset", metavar="DATASET", help="dataset folder")
    parser.add_argument("-o", "--output", required=True, metavar="RESULT",
                        help="result folder (created if missing)")
    parser.add_argument("--fit", metavar="NAMES",
                        help="comma-separated quantities to fit among ka, kd, ks, "
                             "shininess, light_colors, light_positions, and the per-view "
                             "gains against view 0 exposure, white_balance (default "
                             "ka,kd,ks,shininess)")
    parser.add_argument("--grey", metavar="NAMES",
                        help="coefficients fitted as one grey value (default: none, RGB)")
    parser.add_argument("--init", metavar="KA,KD,KS,N|FILE",
                        help="start and held-fixed values (default 0.3,0.5,0.3,20; with "
                             "several objects, for each, or a file {\"objects\": ...} "
                             "with one per object)")
    parser.add_argument("--color-space", type=str.lower, choices=COLOR_SPACES,
                        help="decode every PNG/JPEG target as this, overriding the dataset's "
                             "'color_space' keys and the files' own tags (default: as they "
                             "say, else srgb; .npy targets are linear; any case; "
                             "docs/color.md)")
    for field in dataclasses.fields(FitOptions):
        _add_option(parser, field.name)
    parser.add_argument("--checkpoint-every", type=positive_int, metavar="N",
                        help="write RESULT/checkpoint.json every N steps (default 500)")
    parser.add_argument("--resume", action="store_true",
                        help="continue from RESULT/checkpoint.json")
    parser.add_argument("--holdout", type=view_indices, metavar="N,M",
                        help="keep these views (indices into dataset.json's views) out of "
                             "the fit; render them with the fitted material and report "
                             "their PSNR (holdout_NNN.png, result.json 'holdout')")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    parser.add_argument("--refine-pose", action="store_true",
                        help="refine each view's pose near its calibration, alternating "
                             "with the material, before the fit (result.json 'poses': the "
                             "refined cameras in OpenCV form; docs/calibrated-cameras.md)")
    add_texture_options(parser)
    parser.set_defaults(run=run_fit)


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


def _progress(state, budget, disable=None, file=None):
    """A tqdm bar (on stderr; disable=None: off when it is not a terminal) and
    on_step(state). The first step of a run compiles the step: the bar restarts its clock
    after it, so its rate and remaining time count only the steps after compilation."""
    bar = tqdm(total=budget, initial=state.step, disable=disable, unit="step",
               dynamic_ncols=True, file=file or sys.stderr, desc=f"fit {state.method}",
               postfix="compiling")
    shown, compiled = [0.0], [False]

    def on_step(state):
        if bar.disable:
            return
        if time.monotonic() - shown[0] > 0.1:  # tqdm redraws at most every 0.1 s
            bar.set_postfix_str(_brief(state), refresh=False)
            shown[0] = time.monotonic()
        if compiled[0]:
            bar.update(state.step - bar.n)
            return
        compiled[0] = True  # restart the clock now, after the step and _brief compiled
        bar.reset(total=budget)
        bar.initial = bar.n = bar.last_print_n = state.step
    return bar, on_step


# ---- the command ----


def _extra(args, state, status, signum, message, plan):
    return {"format": RESULT_FORMAT, "version": 1, "views": list(plan.fitted),
            "dataset": os.path.abspath(args.dataset), "loss_kind": state.kind,
            "color_space": args.color_space, "fit": state.spec.fitted,
            "options": state.options.as_dict(), "interrupted": signum is not None,
            "signal": SIGNALS.get(signum), "stop_message": message or None,
            "best_step": state.best_step, "rejected_steps": state.rejected,
            "checkpoint": CHECKPOINT}


def _holdout(plan, result, edge_margin):
    """(result.json's "holdout" entries, {file name: panel}) of the held-out views, or
    ([], {}) when none is held out; rendered with the fitted material (without gains)."""
    if plan.held is None:
        return [], {}
    return holdout_results(plan.held, plan.holdout, result.material, edge_margin)


def _report(args, dataset, views, state, status, message, signum, plan, poses=None):
    """Write the checkpoint and the result files, print the tables; returns the exit code.
    views: the cached data, or its ShardedViews (the report's sums a chunk at a time)."""
    result_path = os.path.join(args.output, "result.json")
    save_checkpoint(os.path.join(args.output, CHECKPOINT), state)
    result = fit_result(state, dataset, views, status=status, stop_message=message)
    data = fit_data(views)
    label = (f"interrupted ({SIGNALS.get(signum)})" if status == "stopped"
             else STATUS_LABELS[status])
    held, panels = _holdout(plan, result, state.options.edge_margin)
    extra = _extra(args, state, status, signum, message, plan) | (
        {"holdout": held} if held else {})
    if poses is not None:
        extra["poses"] = pose_records(poses)
    paths = write_result(args.output, dataset, result, state.init, extra,
                         f"diffshade fit: {state.method}, {state.kind} loss",
                         kept=[np.asarray(v.pixels) for v in data.views], ids=plan.fitted)
    paths += write_panels(args.output, panels)
    print(comparison_table(result, result.truth, label))
    if held:
        print(holdout_table(held))
    for path in paths:
        print(path)
    if result.misfit is not None and not result.misfit.explained and status in (
            "converged", "budget"):  # else stderr says why the fit stopped
        print(f"diffshade: warning: {result.misfit.message(status)}", file=sys.stderr)
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
    if args.texture is not None or args.smoothness is not None:
        return run_texture(args)  # a kd map in closed form (fitting.texture_fit)
    with _Signals() as signals:
        dataset, plan = prepare(args)
        await_background(args.dataset)  # the programs synth's background compile makes
        start = time.perf_counter()
        poses = None
        if args.refine_pose:
            poses = refined_poses(dataset, plan.spec, plan.init, options=plan.options)
            dataset = poses.dataset
        data = build_cache(dataset, plan.init, edge_margin=plan.options.edge_margin)
        views = for_options(data, plan.options)  # sharded and chunked, or data itself
        data = fit_data(views)  # (sharded: its views, in host memory)
        state = plan.state or start_run(views, plan.spec, plan.init, plan.options)
        state.meta |= {"dataset_sha256": plan.fingerprint, "color_space": args.color_space,
                       "checkpoint_every": plan.every, "holdout": list(plan.holdout)}
        if signals.received is not None:
            print(f"diffshade: interrupted by {SIGNALS[signals.received]} before the first "
                  "step; nothing written", file=sys.stderr)
            return 128 + signals.received
        state.wall_time += time.perf_counter() - start
        bar, on_step = _progress(state, state.options.budget, True if args.quiet else None)
        with bar:
            status, message = advance(
                state, views, should_stop=lambda: signals.received is not None,
                on_step=on_step, every=plan.every,
                save=lambda s: save_checkpoint(os.path.join(args.output, CHECKPOINT), s))
        finish(state, views)
        if state.best_params is None:
            print(f"diffshade: error: fit stopped: {message}; no step had a finite loss, "
                  "nothing written", file=sys.stderr)
            return EXIT_NON_FINITE
        return _report(args, dataset, views, state, status, message, signals.received, plan,
                       poses)

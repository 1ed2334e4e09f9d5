"""The run a `diffshade fit` command line asks for (fitting.cli): a new one from the
options given, or the checkpoint's, resumed with every option it was started with.

`prepare(args)` checks every input and writes nothing: the output folder, the checkpoint
(on --resume: the options given must agree with it; --steps may change), the dataset
folder and its targets (fitting.inputs), the views held out (--holdout). It returns the
dataset of the views to fit and a `Plan`.
"""

import dataclasses
import os
from typing import NamedTuple

from fitting.checkpoint import checkpoint_run, load_checkpoint, material_dict, read_checkpoint
from fitting.data.views import material_for, object_total
from fitting.inputs import (
    check_output,
    dataset_fingerprint,
    fit_spec,
    load_checked_dataset,
    parse_material,
)
from fitting.report.holdout import split_views
from fitting.solve.distribute import device_list
from fitting.solve.options import PLACEMENT, FitOptions
from fitting.spec.params import DEFAULT_INIT, FitSpec, object_count, start_material

CHECKPOINT = "checkpoint.json"


def flag(name):
    """The command-line flag of a FitOptions field: lr_shininess -> --lr-shininess."""
    return "--" + name.replace("_", "-")


def _given_options(args):
    """{FitOptions field: value} of the options on the command line."""
    return {f.name: getattr(args, f.name) for f in dataclasses.fields(FitOptions)
            if getattr(args, f.name) is not None}


def options_of(args):
    """FitOptions of the options on a new run's command line (ValueError naming the
    flag)."""
    try:
        return FitOptions(**_given_options(args))
    except ValueError as err:  # "name: got ..." -> "--name: got ..."
        name, _, rest = str(err).partition(":")
        raise ValueError(f"{flag(name)}:{rest}") from None


def _resumed_options(args, saved, checkpoint):
    """The checkpoint's options; those given must agree (--steps, and where the fit runs:
    --devices, --chunk, may change)."""
    given = _given_options(args)
    free = ("steps", *PLACEMENT)
    for name, value in given.items():
        if name not in free and value != getattr(saved, name):
            raise ValueError(f"{flag(name)}: got {value!r}; the checkpoint {checkpoint!r} "
                             f"was made with {getattr(saved, name)!r}")
    return dataclasses.replace(saved, **{k: v for k, v in given.items() if k in free})


def _check_agrees(args, spec, meta, checkpoint):
    """On --resume, the data options given must describe the checkpoint's run."""
    if args.color_space is not None and args.color_space != meta.get("color_space"):
        raise ValueError(f"--color-space: got {args.color_space!r}; the checkpoint "
                         f"{checkpoint!r} was made with {meta.get('color_space')!r}")
    if (args.fit is not None or args.grey is not None) and fit_spec(args.fit,
                                                                   args.grey) != spec:
        raise ValueError(f"--fit/--grey: describe another fit than the checkpoint "
                         f"{checkpoint!r} ({spec})")


def _check_init(args, init, dataset, checkpoint):
    """On --resume, the checkpoint's init must be the dataset's objects' and an --init
    given must be the checkpoint's (for every object)."""
    count, given = object_total(dataset), object_count(init)
    if given != count:
        raise ValueError(f"checkpoint {checkpoint!r}: init: got materials for {given or 1} "
                         f"object(s); expected {count or 1}, the dataset's objects")
    if args.init is not None:
        given = material_dict(material_for(dataset, parse_material(args.init, "--init"),
                                           "--init"))
        if given != material_dict(init):
            raise ValueError(f"--init: got {args.init!r}; the checkpoint {checkpoint!r} was "
                             f"made from {material_dict(init)}")


class Plan(NamedTuple):
    """What `fit` will run: the fit spec, initial material and options, the RunState to
    continue (None: a fresh run), how often to checkpoint, the fingerprint of the fitted
    views' targets, the dataset numbers of the fitted views and of the held-out ones, and
    the dataset of the held-out views (None without --holdout)."""

    spec: FitSpec
    init: object
    options: FitOptions
    state: object
    every: int
    fingerprint: str
    fitted: tuple = ()
    holdout: tuple = ()
    held: object = None


def _holdout(args, meta, checkpoint):
    """The views to hold out: --holdout, or on --resume the checkpoint's (which a given
    --holdout must repeat)."""
    saved = tuple(meta.get("holdout") or ())
    if args.holdout is None:
        return saved if args.resume else ()
    if args.resume and tuple(args.holdout) != saved:
        raise ValueError(f"--holdout: got {','.join(map(str, args.holdout))}; the checkpoint "
                         f"{checkpoint!r} was made holding out {list(saved) or 'no view'}")
    return tuple(args.holdout)


def prepare(args):
    """Check every input; returns (dataset, Plan). Writes nothing."""
    check_output(args.output)
    checkpoint = os.path.join(args.output, CHECKPOINT)
    saved, meta = None, {}
    if args.resume:
        saved = read_checkpoint(checkpoint)
        try:
            spec, init, options = checkpoint_run(saved)
        except (KeyError, TypeError, ValueError) as err:
            raise ValueError(f"checkpoint {checkpoint!r}: {err}") from err
        meta = saved.get("meta", {})
        _check_agrees(args, spec, meta, checkpoint)
        options = _resumed_options(args, options, checkpoint)
        if args.color_space is None:
            args.color_space = meta.get("color_space")
    else:
        spec, options = fit_spec(args.fit, args.grey), options_of(args)
        init = DEFAULT_INIT if args.init is None else parse_material(args.init, "--init")
    try:
        device_list(options.devices)
    except ValueError as err:
        raise ValueError(f"--{err}") from None
    dataset = load_checked_dataset(args.dataset, args.color_space)
    holdout = _holdout(args, meta, checkpoint)
    fitted = tuple(i for i in range(len(dataset.views)) if i not in holdout)
    held = None
    if holdout:
        dataset, held = split_views(dataset, holdout, "--holdout")
    if saved is None:  # one start for every object, or one per object
        init = start_material(material_for(dataset, init, "--init"), spec)
    else:
        _check_init(args, init, dataset, checkpoint)
    fingerprint = dataset_fingerprint(dataset)
    state = None
    if saved is not None:
        if meta.get("dataset_sha256") != fingerprint:
            raise ValueError(f"DATASET: {args.dataset!r} holds other targets than the dataset "
                             f"the checkpoint {checkpoint!r} was made with")
        state = load_checkpoint(checkpoint, [v.lights for v in dataset.views])
        if options.budget < state.step:
            raise ValueError(f"--steps: got {options.steps}; the checkpoint {checkpoint!r} "
                             f"is at step {state.step}; expected at least {state.step}")
        state.options = options
    every = args.checkpoint_every or meta.get("checkpoint_every") or 500
    return dataset, Plan(spec, init, options, state, every, fingerprint, fitted, holdout, held)

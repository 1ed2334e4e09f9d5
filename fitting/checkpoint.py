"""The checkpoint file of a run (fitting.run): everything needed to continue it.

    save_checkpoint(path, state)                       # atomically
    state = load_checkpoint(path, lights=[v.lights for v in dataset.views])

A checkpoint is JSON: the run's spec, initial material and every option
(fitting.solve.options.FitOptions, so a resumed run continues with the settings it started
with), the params, the optimizer state (every leaf; non-finite numbers as the strings
'nan', 'inf', '-inf'), the step, the history, the best params and the caller's `meta`.
`read_checkpoint` gives the checked JSON (a caller can learn the options and meta before
it loads the dataset the arrays need when lights are fitted).

A checkpoint is checked as a whole before anything uses it (`check_checkpoint`): every
field present, of its type and in its range (params finite; step within the options'
budget; the history no longer than the steps; the best step not after the step ...);
`load_checkpoint` then checks it against the dataset (array shapes, the number of views).
A damaged one raises one ValueError naming the file and the field.
"""

import dataclasses
import json
import math
import os

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.io import COLOR_SPACES, write_json
from fitting.data.folder import material_dict, material_from_dict
from fitting.run import RunState, check_run, initial_opt_state, start_params
from fitting.solve.options import FitOptions
from fitting.spec.gains import GAIN_NAMES
from fitting.spec.params import FitSpec

FORMAT = "diffshade-fit-checkpoint"
VERSION = 2


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
        "options": state.options.as_dict(), "step": state.step,
        "params": _encode_tree(state.params), "optimizer_state": _encode_tree(state.opt_state),
        "loss_history": state.history, "best": {
            "step": state.best_step, "loss": state.best_loss if state.best_params else None,
            "params": _encode_tree(state.best_params)},
        "quiet": state.quiet, "converged": state.converged, "rejected": state.rejected,
        "wall_time": state.wall_time, "n_views": _n_views(state.params)})


def _n_views(params):
    """The views the per-view gains (fitting.spec.gains) of params cover, or None."""
    gains = [params[name] for name in GAIN_NAMES if name in params]
    return int(np.shape(gains[0])[0]) + 1 if gains else None


def read_checkpoint(path) -> dict:
    """The checkpoint's JSON, checked as a whole (check_checkpoint). Raises
    FileNotFoundError when there is none and ValueError naming the file and the field when
    it is not a valid checkpoint of this version."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"checkpoint not found: {path!r}")
    try:
        with open(path, encoding="utf-8") as file:
            data = json.load(file)
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as err:
        raise ValueError(f"checkpoint {path!r}: not valid JSON ({err})") from err
    if not isinstance(data, dict) or data.get("format") != FORMAT or data.get("version") != VERSION:
        raise ValueError(f"checkpoint {path!r}: not a {FORMAT} file of version {VERSION}")
    try:
        check_checkpoint(data)
    except ValueError as err:
        raise ValueError(f"checkpoint {path!r}: {err}") from None
    return data


# ---- the schema ----

FIELDS = ("format", "version", "meta", "spec", "init", "options", "step", "params",
          "optimizer_state", "loss_history", "best", "quiet", "converged", "rejected",
          "wall_time", "n_views")
BEST_FIELDS = ("step", "loss", "params")
_NON_FINITE = ("nan", "inf", "-inf")


def _fail(field, value, expected):
    shown = repr(value)
    raise ValueError(f"{field}: got {shown if len(shown) <= 60 else shown[:57] + '...'}; "
                     f"expected {expected}")


def _count(x, low=0):
    return type(x) is int and x >= low


def _finite(x):
    return type(x) in (int, float) and math.isfinite(x)


def _check_keys(data, field, keys):
    if not isinstance(data, dict):
        _fail(field, data, f"an object with the keys {list(keys)}")
    unknown, missing = sorted(set(data) - set(keys)), [k for k in keys if k not in data]
    for key, what in [(k, "an unknown key") for k in unknown] + [(k, "missing")
                                                                 for k in missing]:
        name = f"{field}.{key}" if field else key
        raise ValueError(f"{name}: {what}; expected the keys {list(keys)}")


def _check_array(entry, field, finite):
    """One encoded array (_encode); `finite`: no NaN or infinity (params)."""
    _check_keys(entry, field, ("dtype", "shape", "data"))
    try:
        kind = np.dtype(entry["dtype"]).kind if isinstance(entry["dtype"], str) else None
    except TypeError:
        kind = None
    if kind not in ("b", "i", "u", "f"):
        _fail(f"{field}.dtype", entry["dtype"], "the name of a numeric dtype")
    shape, data = entry["shape"], entry["data"]
    if not (isinstance(shape, list) and all(_count(n) for n in shape)):
        _fail(f"{field}.shape", shape, "a list of integers >= 0")
    if not isinstance(data, list) or len(data) != math.prod(shape):
        _fail(f"{field}.data", data, f"a list of {math.prod(shape)} numbers (the shape's)")
    for i, x in enumerate(data):
        if not (_finite(x) or (not finite and x in _NON_FINITE)):
            _fail(f"{field}.data[{i}]", x, "a finite number (parameters are never NaN or "
                  "infinite)" if finite else f"a number or one of {list(_NON_FINITE)}")


def _check_arrays(entries, field, finite):
    if not isinstance(entries, list):
        _fail(field, entries, "a list of arrays")
    for i, entry in enumerate(entries):
        _check_array(entry, f"{field}[{i}]", finite)


def _check_meta(meta):
    """The caller's description (any JSON object); the command line's keys are checked."""
    if not isinstance(meta, dict):
        _fail("meta", meta, "an object")
    checks = {"dataset_sha256": (lambda x: isinstance(x, str) and len(x) == 64,
                                 "a SHA-256 hex digest"),
              "color_space": (lambda x: x is None or x in COLOR_SPACES,
                              f"null or one of {COLOR_SPACES}"),
              "checkpoint_every": (lambda x: _count(x, 1), "an integer >= 1"),
              "holdout": (lambda x: isinstance(x, list) and all(_count(i, 0) for i in x)
                          and len(set(x)) == len(x), "a list of distinct view indices >= 0")}
    for key, (check, expected) in checks.items():
        if key in meta and not check(meta[key]):
            _fail(f"meta.{key}", meta[key], expected)


def _dataclass_of(cls, data, field):
    """cls(**data) of a JSON object with cls's fields; ValueError naming field.key."""
    names = [f.name for f in dataclasses.fields(cls)]
    if not isinstance(data, dict):
        _fail(field, data, f"an object with keys among {names}")
    for key in sorted(set(data) - set(names)):
        raise ValueError(f"{field}.{key}: an unknown key; expected keys among {names}")
    try:
        return cls(**data)
    except (TypeError, ValueError) as err:  # "name: got ...; expected ..."
        raise ValueError(f"{field}.{err}") from None


def _check_spec(data):
    spec = _dataclass_of(FitSpec, data, "spec")
    for f in dataclasses.fields(FitSpec):
        if isinstance(f.default, bool) and type(getattr(spec, f.name)) is not bool:
            _fail(f"spec.{f.name}", getattr(spec, f.name), "true or false")
    return spec


def _check_run(data):
    """The step, history and counters against the options' budget and each other."""
    options = _dataclass_of(FitOptions, data["options"], "options")
    step = data["step"]
    if not _count(step) or step > options.budget:
        _fail("step", step, f"an integer from 0 to the step budget ({options.budget}, "
              "options.steps)")
    history = data["loss_history"]
    if not (isinstance(history, list) and len(history) <= step + 1
            and all(_finite(x) for x in history)):
        _fail("loss_history", history, f"at most {step + 1} finite numbers (step + 1)")
    for name, check, expected in (("quiet", _count, "an integer >= 0"),
                                  ("rejected", _count, "an integer >= 0"),
                                  ("converged", lambda x: type(x) is bool, "true or false"),
                                  ("wall_time", lambda x: _finite(x) and x >= 0,
                                   "a finite number >= 0"),
                                  ("n_views", lambda x: x is None or _count(x, 2),
                                   "null or an integer >= 2")):
        if not check(data[name]):
            _fail(name, data[name], expected)


def _check_best(best, step):
    _check_keys(best, "best", BEST_FIELDS)
    if not _count(best["step"]) or best["step"] > step:
        _fail("best.step", best["step"], f"an integer from 0 to step ({step})")
    if best["params"] is None:
        if best["loss"] is not None:
            _fail("best.loss", best["loss"], "null, as best.params is null")
        return
    if not _finite(best["loss"]):
        _fail("best.loss", best["loss"], "a finite number")
    _check_arrays(best["params"], "best.params", finite=True)


def check_checkpoint(data):
    """Check a checkpoint's JSON as a whole, without the dataset; ValueError naming the
    field ('best.params[1].data[0]: got 'nan'; expected a finite number ...')."""
    _check_keys(data, "", FIELDS)
    _check_meta(data["meta"])
    _check_spec(data["spec"])
    if isinstance(material_from_dict(data["init"], "init"), dict):  # objects by name
        _fail("init.objects", data["init"]["objects"], "a list, one material per object")
    _check_run(data)
    _check_arrays(data["params"], "params", finite=True)
    _check_arrays(data["optimizer_state"], "optimizer_state", finite=False)
    _check_best(data["best"], data["step"])


def checkpoint_run(data: dict):
    """(spec, init, options) of a checkpoint's JSON."""
    return (FitSpec(**data["spec"]), material_from_dict(data["init"], "init"),
            FitOptions(**data["options"]))


def _check_views(data, lights):
    """The checkpoint's per-view gains against the dataset's views."""
    if lights is not None and data["n_views"] is not None and data["n_views"] != len(lights):
        _fail("n_views", data["n_views"], f"{len(lights)}, the dataset's views")


def load_checkpoint(path, lights=None) -> RunState:
    """The RunState saved at `path`; `lights` (one LightGroups per view, the dataset's) is
    needed when the run fits lights. Raises FileNotFoundError when there is no checkpoint
    and ValueError naming the file and the field when it is not a valid one (for the
    dataset of `lights`)."""
    data = read_checkpoint(path)
    try:
        spec, init, options = checkpoint_run(data)
        check_run(spec, init, options)
        if spec.fits_lights and lights is None:
            raise ValueError("the run fits lights; expected the dataset's lights")
        _check_views(data, lights)
        template = start_params(spec, init, lights, data["n_views"])
        params = _decode_tree(data["params"], template, "params")
        opt_state = _decode_tree(data["optimizer_state"],
                                 initial_opt_state(spec, options, params), "optimizer_state")
        best = data["best"]
        best_params = (None if best["params"] is None
                       else _decode_tree(best["params"], template, "best.params"))
        return RunState(spec, init, options, params, opt_state, data["step"],
                        [float(x) for x in data["loss_history"]],
                        math.inf if best["loss"] is None else float(best["loss"]),
                        best_params, best["step"], data["quiet"], data["converged"],
                        data["rejected"], float(data["wall_time"]), dict(data["meta"]))
    except (TypeError, ValueError) as err:
        raise ValueError(f"checkpoint {os.fspath(path)!r}: {err}") from err

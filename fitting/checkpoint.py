"""The checkpoint file of a run (fitting.run): everything needed to continue it.

    save_checkpoint(path, state)                       # atomically
    state = load_checkpoint(path, lights=[v.lights for v in dataset.views])

A checkpoint is JSON: the run's spec, initial material and every option
(fitting.solve.options.FitOptions, so a resumed run continues with the settings it started
with), the params, the optimizer state (every leaf; non-finite numbers as the strings
'nan', 'inf', '-inf'), the step, the history, the best params and the caller's `meta`.
`read_checkpoint` gives the checked JSON (a caller can learn the options and meta before
it loads the dataset the arrays need when lights are fitted).
"""

import dataclasses
import json
import math
import os

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.io import write_json
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
    """The checkpoint's JSON, checked to be one. Raises FileNotFoundError when there is
    none and ValueError naming the file when it is not a checkpoint of this version."""
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
    return data


def checkpoint_run(data: dict):
    """(spec, init, options) of a checkpoint's JSON."""
    return (FitSpec(**data["spec"]), material_from_dict(data["init"], "init"),
            FitOptions(**data["options"]))


def load_checkpoint(path, lights=None) -> RunState:
    """The RunState saved at `path`; `lights` (one LightGroups per view, the dataset's) is
    needed when the run fits lights. Raises FileNotFoundError when there is no checkpoint
    and ValueError naming the file when it is not a valid one."""
    data = read_checkpoint(path)
    try:
        spec, init, options = checkpoint_run(data)
        check_run(spec, init, options)
        if spec.fits_lights and lights is None:
            raise ValueError("the run fits lights; expected the dataset's lights")
        template = start_params(spec, init, lights, data.get("n_views"))
        params = _decode_tree(data["params"], template, "params")
        opt_state = _decode_tree(data["optimizer_state"],
                                 initial_opt_state(spec, options, params), "optimizer_state")
        best = data["best"]
        best_params = (None if best["params"] is None
                       else _decode_tree(best["params"], template, "best.params"))
        return RunState(spec, init, options, params, opt_state, int(data["step"]),
                        [float(x) for x in data["loss_history"]],
                        math.inf if best["loss"] is None else float(best["loss"]),
                        best_params, int(best["step"]), int(data["quiet"]),
                        bool(data["converged"]), int(data["rejected"]),
                        float(data["wall_time"]), dict(data["meta"]))
    except (KeyError, TypeError, ValueError) as err:
        raise ValueError(f"checkpoint {os.fspath(path)!r}: {err}") from err

"""A damaged checkpoint is refused as a whole before anything is written (fitting.checkpoint,
fitting.plan): `diffshade fit --resume` on a checkpoint with one field changed exits with
status 2 and one line naming the file and the field, and the result folder is left
byte for byte as it was.

The reference is the schema as docs/cli.md states it, field by field: each case changes
one field of a checkpoint that a real fit wrote (Adam, so that the optimizer state holds
moments; exposure fitted, so that it covers two views) to a value outside its type or
range, or inconsistent with another field or with the dataset."""

import copy
import json
import os

import numpy as np
import pytest

import diffshade as ds
from data_synth import make_dataset, save_dataset
from diffshade import cli
from fitting.checkpoint import load_checkpoint, read_checkpoint

STEPS = 4
pytestmark = pytest.mark.cost(5)  # one short fit shared by the module


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """(dataset folder, result folder) of a 4-step Adam fit of kd and exposure."""
    root = tmp_path_factory.mktemp("checkpoint")
    dataset = make_dataset(ds.icosphere(1), ds.material(ka=0.2, kd=0.5, ks=0.3, shininess=20.0),
                           n_views=2, n_lights=1, size=16, seed=3)
    save_dataset(dataset, root / "data")
    assert cli.main(["fit", str(root / "data"), "-o", str(root / "fit"), "--method", "adam",
                     "--fit", "kd,exposure", "--steps", str(STEPS)]) == 0
    return root / "data", root / "fit"


def _set(path, value):
    """A function that sets the field at `path` (keys and list indices) to value."""
    def change(data):
        *parents, last = path
        for key in parents:
            data = data[key]
        data[last] = value
    return change


def _remove(key):
    return lambda data: data.pop(key)


NAN = float("nan")
CASES = {  # name: (change, the field the message names)
    "meta a list": (_set(["meta"], ["a", "list"]), "meta"),
    "meta color space": (_set(["meta", "color_space"], "cmyk"), "meta.color_space"),
    "meta holdout": (_set(["meta", "holdout"], [1, 1]), "meta.holdout"),
    "step negative": (_set(["step"], -5), "step"),
    "step a string": (_set(["step"], "12"), "step"),
    "step beyond the budget": (_set(["options", "steps"], 0), "step"),
    "options unknown": (_set(["options", "speed"], 3), "options"),
    "options lr": (_set(["options", "lr"], -1.0), "options.lr"),
    "spec flag": (_set(["spec", "shininess"], "yes"), "spec.shininess"),
    "spec mode": (_set(["spec", "kd"], "cmyk"), "spec.kd"),
    "init": (_set(["init", "kd"], "red"), "init: kd"),
    "init for two objects": (lambda d: d.update(init={"objects": [d["init"], d["init"]]}),
                             "init"),
    "init by object name": (lambda d: d.update(init={"objects": {"a": d["init"]}}),
                            "init.objects"),
    "params NaN": (_set(["params", 1, "data", 1], "nan"), "params[1].data[1]"),
    "params null": (_set(["params"], None), "params"),
    "params entry": (_set(["params", 0], None), "params[0]"),
    "params shape": (_set(["params", 0, "shape"], [2]), "params[0].data"),
    "params count": (lambda d: d["params"].pop(), "params"),
    "optimizer state dtype": (_set(["optimizer_state", 0, "dtype"], "object"),
                              "optimizer_state[0].dtype"),
    "optimizer state value": (_set(["optimizer_state", 1, "data", 0], "1e3"),
                              "optimizer_state[1].data[0]"),
    "best null": (_set(["best"], None), "best"),
    "best params NaN": (_set(["best", "params", 0, "data", 0], NAN), "best.params[0].data[0]"),
    "best step after step": (_set(["best", "step"], STEPS + 1), "best.step"),
    "best loss without params": (_set(["best", "params"], None), "best.loss"),
    "history too long": (_set(["loss_history"], [0.1] * (STEPS + 2)), "loss_history"),
    "history NaN": (_set(["loss_history", 0], NAN), "loss_history"),
    "quiet": (_set(["quiet"], 1.5), "quiet"),
    "converged": (_set(["converged"], "no"), "converged"),
    "wall time": (_set(["wall_time"], -1), "wall_time"),
    "n_views of another dataset": (_set(["n_views"], 3), "n_views"),
    "a key missing": (_remove("rejected"), "rejected"),
    "an unknown key": (_set(["extra"], 1), "extra"),
}


def _listing(folder):
    return {name: (folder / name).read_bytes() for name in sorted(os.listdir(folder))}


@pytest.mark.parametrize("case", CASES)
def test_a_damaged_checkpoint_is_refused_naming_the_file_and_field(fitted, tmp_path, capsys,
                                                                    case):
    data, fit = fitted
    out = tmp_path / "fit"
    out.mkdir()
    for name, content in _listing(fit).items():
        (out / name).write_bytes(content)
    checkpoint = json.loads((out / "checkpoint.json").read_text())
    change, field = CASES[case]
    damaged = copy.deepcopy(checkpoint)
    change(damaged)
    (out / "checkpoint.json").write_text(json.dumps(damaged))
    before = _listing(out)
    code = cli.main(["fit", str(data), "-o", str(out), "--resume", "--steps", str(STEPS + 2)])
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"diffshade: error: checkpoint {str(out / 'checkpoint.json')!r}")
    assert f": {field}" in lines[0] and "expected" in lines[0], lines[0]
    assert _listing(out) == before  # nothing written


def test_resume_with_fewer_steps_than_taken_is_refused(fitted, tmp_path, capsys):
    data, fit = fitted
    out = tmp_path / "fit"
    out.mkdir()
    for name, content in _listing(fit).items():
        (out / name).write_bytes(content)
    before = _listing(out)
    code = cli.main(["fit", str(data), "-o", str(out), "--resume", "--steps", "2"])
    (line,) = capsys.readouterr().err.splitlines()
    assert code == 2 and line.startswith("diffshade: error: --steps: got 2;")
    assert f"at step {STEPS}; expected at least {STEPS}" in line
    assert _listing(out) == before


def test_the_checkpoint_a_fit_wrote_loads_whole(fitted):
    """The reference side: the undamaged checkpoint passes every check and loads as the
    state it describes (its parameters finite, the step the fit took)."""
    data, fit = fitted
    saved = read_checkpoint(fit / "checkpoint.json")
    from data_synth import load_dataset
    views = load_dataset(data).views
    state = load_checkpoint(fit / "checkpoint.json", [v.lights for v in views])
    assert state.step == saved["step"] == STEPS and state.options.method == "adam"
    assert all(np.all(np.isfinite(np.asarray(v))) for v in state.params.values())
    assert saved["n_views"] == 2

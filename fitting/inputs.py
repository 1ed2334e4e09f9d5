"""Command-line inputs of `diffshade fit` and `diffshade synth`, checked at the boundary.

argparse types (`positive_int`, `non_negative_float`), materials from text or a JSON file
(`parse_material`), the FitSpec from --fit and --grey names (`fit_spec`), the output
folder (`check_output`), and the dataset folder (`load_checked_dataset`:
fitting.data.folder.load_dataset, which checks the folder and names the file at fault).
Every problem is a ValueError or an OSError whose message names the option or the file,
the value and what was expected; diffshade.cli prints it as one line.
"""

import argparse
import os

import numpy as np

from diffshade.io import check_writable, read_json
from diffshade.pipeline import check_render
from diffshade.scene import Texture, material
from fitting.data.folder import fingerprint, load_dataset, material_from_dict
from fitting.data.views import material_for, view_scene
from fitting.spec.params import DEFAULT_INIT, FIT_NAMES, MODED, FitSpec

DEFAULT_FIT = tuple(name for name, value in FitSpec().fitted.items() if value)


# ---- arguments ----


def _number_type(name, convert, low, strict, expected):
    """An argparse type: text -> convert(text), finite and above `low` (at or above it
    unless strict), else ArgumentTypeError naming the text and `expected`."""
    def parse(text):
        try:
            value = convert(text)
        except ValueError:
            value = None
        if value is None or not np.isfinite(value) or value < low or (strict and value == low):
            raise argparse.ArgumentTypeError(f"got {text!r}; expected {expected}")
        return value
    parse.__name__ = parse.__qualname__ = name
    return parse


positive_int = _number_type("positive_int", int, 1, False, "a positive integer")
non_negative_int = _number_type("non_negative_int", int, 0, False, "an integer >= 0")
positive_float = _number_type("positive_float", float, 0.0, True, "a finite number > 0")
non_negative_float = _number_type("non_negative_float", float, 0.0, False,
                                  "a finite number >= 0")


def _material_file(path, option):
    """The fields of a JSON material file (a result.json: its 'material')."""
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{option}: material file not found: {path!r}")
    try:
        data = read_json(path, "material file")
    except ValueError as err:
        raise ValueError(f"{option}: {path!r} is not valid JSON ({err})") from err
    if isinstance(data, dict) and isinstance(data.get("material"), dict):
        data = data["material"]  # a result.json
    return data


def parse_material(text, option):
    """'KA,KD,KS,N' (grey coefficients and the shininess) or a JSON file with keys ka, kd,
    ks, shininess, emission (a dataset's truth.json; a result.json's 'material') ->
    Material; a file of several objects' materials ({"objects": [...]} or {"objects":
    {name: ...}}, fitting.data.folder.material_from_dict) gives a stacked Material or a dict
    {name: Material}. Raises ValueError (or FileNotFoundError) naming `option`."""
    if "," in text:
        parts = text.split(",")
        try:
            ka, kd, ks, shininess = (float(p) for p in parts)
        except ValueError:
            raise ValueError(f"{option}: got {text!r}; expected KA,KD,KS,N (4 numbers) or a "
                             "JSON file") from None
        fields = {"ka": ka, "kd": kd, "ks": ks, "shininess": shininess}
        try:
            return material(**fields)
        except ValueError as err:
            raise ValueError(f"{option}: {err}") from err
    return material_from_dict(_material_file(text, option), f"{option}: {text!r}")


def _names(text, option, allowed):
    names = [name.strip() for name in text.split(",")]
    unknown = [name for name in names if name not in allowed]
    if unknown or not text.strip() or len(set(names)) != len(names):
        raise ValueError(f"{option}: got {text!r}; expected distinct comma-separated names "
                         f"among {', '.join(allowed)}")
    return names


def fit_spec(fit_text=None, grey_text=None) -> FitSpec:
    """FitSpec from --fit (names among fitting.spec.params.FIT_NAMES, the per-view gains
    exposure and white_balance included; default: ka, kd, ks, shininess) and --grey (fitted
    coefficients that get one value for all channels)."""
    fitted = _names(fit_text, "--fit", FIT_NAMES) if fit_text is not None else DEFAULT_FIT
    grey = _names(grey_text, "--grey", MODED) if grey_text is not None else []
    for name in grey:
        if name not in fitted:
            raise ValueError(f"--grey: {name!r} is not fitted (--fit {','.join(fitted)})")
    return FitSpec.from_names(fitted, grey)


# ---- folders ----


def check_output(path):
    """--output: a new path, or an existing writable folder, in a writable place (checked
    before the fit, so that it never fails only when the results are written)."""
    if os.path.exists(path) and not os.path.isdir(path):
        raise ValueError(f"--output: {path!r} is a file; expected a folder for the results")
    check_writable(path, "--output", "folder")


def load_checked_dataset(path, color_space=None, uniform_truth=True):
    """fitting.data.folder.load_dataset, after checking that DATASET is a folder, and
    each view checked against the memory budget. color_space: 'srgb' or 'linear' decodes
    every image target so (--color-space). uniform_truth: refuse a textured truth (what
    the material fit cannot compare)."""
    if not os.path.exists(path):
        raise FileNotFoundError(f"DATASET: folder not found: {path!r}")
    if not os.path.isdir(path):
        raise ValueError(f"DATASET: {path!r} is a file; expected a dataset folder")
    dataset = load_dataset(path, color_space)
    if uniform_truth:
        _check_uniform_truth(dataset.truth, path)
    _check_memory(dataset)
    return dataset


def _check_uniform_truth(truth, path):
    """ValueError for a textured truth: the fit recovers uniform materials only."""
    textured = [name for name in ("kd", "ks", "shininess")
                if truth is not None and isinstance(getattr(truth, name), Texture)]
    if textured:
        raise ValueError(f"DATASET: {path!r} truth.json: {textured[0]} is a texture; expected "
                         "uniform materials (recover a texture with --texture kd=RES)")


def _check_memory(dataset):
    """Rasterizing each view must fit the memory budget (diffshade.budget: its image size,
    mesh and the shadow maps of its lights), checked before anything is compiled."""
    start = material_for(dataset, DEFAULT_INIT)
    for i in range(len(dataset.views)):
        check_render(view_scene(dataset, i, start), dataset.settings)


def dataset_fingerprint(dataset) -> str:
    """sha256 of the targets and masks: resume only on the same data."""
    return fingerprint(dataset)

"""Command-line inputs of `diffshade fit` and `diffshade synth`, checked at the boundary.

argparse types (`positive_int`, `non_negative_float`), materials from text or a JSON file
(`parse_material`), the FitSpec from --fit and --grey names (`fit_spec`), the output
folder (`check_output`), and the dataset folder (`load_checked_dataset`: data_synth's
load_dataset after checks that name the file, and the first non-finite target pixel).
Every problem is a ValueError or an OSError whose message names the option or the file,
the value and what was expected; diffshade.cli prints it as one line.
"""

import argparse
import hashlib
import json
import os

import numpy as np

from data_synth.io import load_dataset
from diffshade.material import material
from fitting.params import COEFFICIENTS, FIT_NAMES, FitSpec

DEFAULT_FIT = tuple(name for name, value in FitSpec().fitted.items() if value)


# ---- arguments ----


def positive_int(text):
    """argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected a positive integer")
    return value


def non_negative_float(text):
    """argparse type: a finite number >= 0."""
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not (np.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"got {text!r}; expected a finite number >= 0")
    return value


def _material_file(path, option):
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{option}: material file not found: {path!r}")
    try:
        with open(path, encoding="utf-8") as file:
            data = json.load(file)
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{option}: {path!r} is not valid JSON ({err})") from err
    if isinstance(data, dict) and isinstance(data.get("material"), dict):
        data = data["material"]  # a result.json
    allowed = ("ka", "kd", "ks", "shininess", "emission")
    if not isinstance(data, dict) or set(data) - set(allowed):
        extra = sorted(set(data) - set(allowed)) if isinstance(data, dict) else type(data).__name__
        raise ValueError(f"{option}: {path!r} has {extra}; expected an object with keys "
                         f"among {allowed}")
    for key, value in data.items():
        _check_material_value(key, value, f"{option}: {path!r}: {key}")
    return data


def _check_material_value(key, value, where):
    """JSON material values: numbers ([r, g, b] for a coefficient; null for ks and
    emission, which may be absent). material() checks the ranges and lengths."""
    if value is None and key in ("ks", "emission"):
        return
    items = value if isinstance(value, list) and key != "shininess" else [value]
    if not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in items):
        expected = "a number" if key == "shininess" else "a number or [r, g, b]"
        raise ValueError(f"{where}: got {value!r}; expected {expected}")


def parse_material(text, option):
    """'KA,KD,KS,N' (grey coefficients and the shininess) or a JSON file with keys ka, kd,
    ks, shininess, emission (a dataset's truth.json; a result.json's 'material') ->
    Material. Raises ValueError (or FileNotFoundError) naming `option`."""
    if "," in text:
        parts = text.split(",")
        try:
            ka, kd, ks, shininess = (float(p) for p in parts)
        except ValueError:
            raise ValueError(f"{option}: got {text!r}; expected KA,KD,KS,N (4 numbers) or a "
                             "JSON file") from None
        fields = {"ka": ka, "kd": kd, "ks": ks, "shininess": shininess}
    else:
        fields = _material_file(text, option)
    try:
        return material(**fields)
    except ValueError as err:
        raise ValueError(f"{option}: {err}") from err


def _names(text, option, allowed):
    names = [name.strip() for name in text.split(",")]
    unknown = [name for name in names if name not in allowed]
    if unknown or not text.strip() or len(set(names)) != len(names):
        raise ValueError(f"{option}: got {text!r}; expected distinct comma-separated names "
                         f"among {', '.join(allowed)}")
    return names


def fit_spec(fit_text=None, grey_text=None) -> FitSpec:
    """FitSpec from --fit (names among fitting.params.FIT_NAMES; default: ka, kd, ks,
    shininess) and --grey (fitted coefficients that get one value for all channels)."""
    fitted = _names(fit_text, "--fit", FIT_NAMES) if fit_text is not None else DEFAULT_FIT
    grey = _names(grey_text, "--grey", COEFFICIENTS) if grey_text is not None else []
    for name in grey:
        if name not in fitted:
            raise ValueError(f"--grey: {name!r} is not fitted (--fit {','.join(fitted)})")
    return FitSpec.from_names(fitted, grey)


# ---- folders ----


def check_output(path):
    """--output: a new path, or an existing folder, in a writable place."""
    if os.path.exists(path) and not os.path.isdir(path):
        raise ValueError(f"--output: {path!r} is a file; expected a folder for the results")
    ancestor = os.path.dirname(os.path.abspath(path))
    while not os.path.exists(ancestor):
        ancestor = os.path.dirname(ancestor)
    if not os.path.isdir(ancestor) or not os.access(ancestor, os.W_OK | os.X_OK):
        raise ValueError(f"--output: cannot create or write {path!r} ({ancestor!r} is not a "
                         "writable folder)")


def _dataset_entries(path):
    """dataset.json's view entries, checked enough for load_dataset not to stumble."""
    meta_path = os.path.join(path, "dataset.json")
    if not os.path.isfile(meta_path):
        raise FileNotFoundError(f"DATASET: {path!r} has no dataset.json; expected a dataset "
                                "folder (see 'diffshade synth')")
    try:
        with open(meta_path, encoding="utf-8") as file:
            views = json.load(file).get("views")
    except (json.JSONDecodeError, UnicodeDecodeError, AttributeError) as err:
        raise ValueError(f"{meta_path!r}: not a JSON object ({err})") from err
    if not isinstance(views, list) or not all(
            isinstance(v, dict) and isinstance(v.get("scene"), str)
            and isinstance(v.get("image"), str) for v in views):
        raise ValueError(f"{meta_path!r}: 'views' must be a list of objects with 'scene' and "
                         "'image' file names")
    return views


def _check_targets(path, entries):
    """Name the first non-finite pixel of any float target (load_dataset only says that
    there is one)."""
    for index, entry in enumerate(entries):
        npy = entry.get("target")
        if not (isinstance(npy, str) and os.path.isfile(os.path.join(path, npy))):
            continue
        try:
            target = np.load(os.path.join(path, npy), allow_pickle=False)
        except (OSError, ValueError):
            continue  # load_dataset reports an unreadable file
        if not np.issubdtype(target.dtype, np.floating):
            continue
        bad = np.argwhere(~np.isfinite(target))
        if bad.size:
            row, column = (int(i) for i in bad[0][:2])
            kind = "NaN" if np.isnan(target[tuple(bad[0])]) else "infinity"
            raise ValueError(f"target image of view {index} ({npy}) contains {kind} at pixel "
                             f"(row {row}, column {column}) ({len(bad)} non-finite values); "
                             "expected finite colours")


def load_checked_dataset(path, color_space=None):
    """load_dataset with the CLI's checks first: the folder, dataset.json, finite targets.
    color_space: 'srgb' or 'linear' decodes every image target so (--color-space)."""
    if not os.path.exists(path):
        raise FileNotFoundError(f"DATASET: folder not found: {path!r}")
    if not os.path.isdir(path):
        raise ValueError(f"DATASET: {path!r} is a file; expected a dataset folder")
    _check_targets(path, _dataset_entries(path))
    try:
        return load_dataset(path, color_space)
    except (KeyError, TypeError) as err:
        raise ValueError(f"DATASET: {path!r} is malformed ({err!r})") from err


def dataset_fingerprint(dataset) -> str:
    """sha256 of the targets (shapes and float32 bytes): resume only on the same data."""
    digest = hashlib.sha256()
    for view in dataset.views:
        target = np.ascontiguousarray(view.target, np.float32)
        digest.update(repr(target.shape).encode())
        digest.update(target.tobytes())
    return digest.hexdigest()



"""Views the fit did not see: how well the fitted material predicts them.

`diffshade fit --holdout N,M` (fitting.cli) fits the dataset's other views, then renders
each held-out view with the fitted material and that view's own camera and lights (as
given: fitted light values and per-view gains belong to the fitted views, so a held-out
view is rendered with gain 1), and compares it with its target over the pixels that
count, chosen as the fit chooses them (covered by the object, inside the view's mask,
unsaturated, `edge_margin` pixels inside the silhouette: fitting.model.cache.kept_pixels):

    PSNR = 10 log10(1 / MSE)   (peak 1; MSE over the counted pixels and the 3 channels)

once on linear values and once on sRGB-encoded ones (both clipped to [0, 1], as an image
shows them). For 8-bit targets it also gives the PSNR that their rounding alone allows (a
perfect prediction against targets rounded to the nearest code: the error uniform over
half a code step h either side, MSE = mean(h^2) / 3). Linear codes allow 10 log10(12 *
255^2) = 58.9 dB on linear values (on sRGB values less in the darks, where the sRGB curve
is steep, and more in the lights); sRGB codes 58.9 dB on sRGB values. `write_panels` writes
per view holdout_NNN.png: target | prediction | ERROR_GAIN x |prediction - target| on the
counted pixels (sRGB-encoded, as every PNG);
`holdout_results` computes everything first, so that nothing is written on an error.
"""

import dataclasses
import os

import numpy as np

from diffshade.io import encode, write_png
from fitting.model.cache import view_samples
from fitting.report.result import ERROR_GAIN, PANEL_GAP, counted_mask, render_rgb
from fitting.report.uncertainty import rounding_encoding, steps_in


def split_views(dataset, holdout, name="holdout"):
    """(the dataset of the views not in `holdout`, the dataset of those in it, in order),
    sharing everything else; ValueError naming `name` for an index out of range or for
    holding out every view."""
    count = len(dataset.views)
    wrong = [i for i in holdout if not 0 <= i < count]
    if wrong or len(set(holdout)) == count:
        expected = (f"view indices below {count}" if wrong
                    else f"at most {count - 1} of the {count} views (one must be fitted)")
        raise ValueError(f"{name}: got {','.join(map(str, holdout))}; expected {expected}")
    kept = [v for i, v in enumerate(dataset.views) if i not in holdout]
    held = [dataset.views[i] for i in holdout]
    return dataset_with(dataset, kept), dataset_with(dataset, held)


def dataset_with(dataset, views):
    """The dataset with `views` instead of its own."""
    return dataclasses.replace(dataset, views=tuple(views))


def psnr(prediction, target, mask) -> float:
    """10 log10(1 / MSE) over the pixels where mask [H, W] is True (inf for a perfect
    prediction, NaN for no pixel). prediction, target: [H, W, 3] in [0, 1]."""
    diff = np.asarray(prediction, np.float64)[mask] - np.asarray(target, np.float64)[mask]
    if not diff.size:
        return float("nan")
    mse = float(np.mean(diff**2))
    return float("inf") if mse == 0.0 else float(10.0 * np.log10(1.0 / mse))


def _psnr_of_halfsteps(half) -> float:
    """The PSNR of an error uniform on [-h, h] per value: 10 log10(3 / mean(h^2))."""
    return float(10.0 * np.log10(3.0 / np.mean(np.asarray(half, np.float64) ** 2)))


def rounding_limits(target, counted):
    """(linear, sRGB) PSNR that the 8-bit rounding of `target` [H, W, 3] (linear values)
    allows over the counted pixels (module docstring), or (None, None) when the target is
    not 8-bit codes or no pixel counts."""
    encoding = rounding_encoding([target])
    values = np.asarray(target, np.float64)[counted]
    if encoding is None or not values.size:
        return None, None
    if encoding == "srgb":
        return _psnr_of_halfsteps(steps_in(values, "srgb")), _psnr_of_halfsteps(
            np.full(values.shape, 0.5 / 255.0))
    half = 0.5 / 255.0
    srgb = (encode(np.minimum(values + half, 1.0), "srgb")
            - encode(np.maximum(values - half, 0.0), "srgb")) / 2.0
    return _psnr_of_halfsteps(np.full(values.shape, half)), _psnr_of_halfsteps(srgb)


def evaluate(dataset, index, material, edge_margin=1):
    """(prediction [H, W, 3] linear, counted [H, W] bool, {"pixels", "psnr_linear",
    "psnr_srgb", "psnr_linear_8bit", "psnr_srgb_8bit"}) of view `index` of `dataset`
    rendered with `material` (the last two: rounding_limits, None unless 8-bit)."""
    view = dataset.views[index]
    prediction = render_rgb(dataset, index, material)
    counted = counted_mask(view.target.shape, view_samples(dataset, index, edge_margin).pixels)
    shown = [np.clip(x, 0.0, 1.0) for x in (prediction, view.target)]
    limits = rounding_limits(view.target, counted)
    scores = {"pixels": int(counted.sum()), "psnr_linear": psnr(*shown, counted),
              "psnr_srgb": psnr(*(encode(x, "srgb") for x in shown), counted),
              "psnr_linear_8bit": limits[0], "psnr_srgb_8bit": limits[1]}
    return prediction, counted, scores


def holdout_panel(target, prediction, counted, gain=ERROR_GAIN):
    """[H, W, 3] images -> target | prediction | gain * |prediction - target| on the
    counted pixels (black elsewhere), separated by grey bars."""
    error = np.clip(gain * np.abs(prediction - target), 0.0, 1.0) * counted[..., None]
    gap = np.full((target.shape[0], PANEL_GAP, 3), 0.5)
    return np.concatenate([np.asarray(target, np.float64), gap, prediction, gap, error], 1)


def holdout_results(dataset, ids, material, edge_margin=1):
    """Evaluate every view of `dataset` (the held-out views, numbered `ids` in the full
    dataset); returns (one entry per view: {"view", "image", "pixels", "psnr_linear",
    "psnr_srgb"}, {image file name: its panel}). Nothing is written."""
    entries, panels = [], {}
    for i, number in enumerate(ids):
        prediction, counted, scores = evaluate(dataset, i, material, edge_margin)
        name = f"holdout_{number:03d}.png"
        target = np.asarray(dataset.views[i].target, np.float64)
        panels[name] = holdout_panel(target, prediction, counted)
        entries.append({"view": number, "image": name, **scores})
    return entries, panels


def write_panels(out_dir, panels) -> list:
    """Write holdout_results' panels into out_dir; returns their paths."""
    return [write_png(os.path.join(out_dir, name), image) for name, image in panels.items()]


def holdout_table(entries) -> str:
    """The printed table: one row per held-out view with its counted pixels and PSNRs, and
    for 8-bit targets the PSNRs their rounding allows."""
    limits = any(e["psnr_linear_8bit"] is not None for e in entries)
    lines = [f"{'held-out view':<14}{'pixels':>8}{'PSNR linear':>14}{'PSNR sRGB':>12}"
             + (f"{'8-bit limit: linear':>22}{'sRGB':>11}" if limits else "")]
    for e in entries:
        row = (f"{e['view']:<14}{e['pixels']:>8}{e['psnr_linear']:>11.2f} dB"
               f"{e['psnr_srgb']:>9.2f} dB")
        if e["psnr_linear_8bit"] is not None:
            row += f"{e['psnr_linear_8bit']:>19.2f} dB{e['psnr_srgb_8bit']:>8.2f} dB"
        lines.append(row)
    return "\n".join(lines)

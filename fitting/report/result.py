"""The files of a fit result, and the table printed at its end.

`write_result(out_dir, dataset, result, init, extra)` writes, each file atomically
(diffshade.io.images), in this order so that the parameters are on disk first:

    material.mtl   the fitted material as a Wavefront MTL (Ka, Kd, Ks, Ns, Ke; map_Kd,
                   map_Ks for maps); one `newmtl` per object for several objects
    result.json    `result_dict`: the FitResult's values, standard errors, warnings and
                   loss history, the full fitted and initial materials, the truth and the
                   relative errors when the dataset has a truth (absent otherwise), and
                   the caller's `extra` keys; with several objects the materials are
                   {"objects": [one per object]} and "objects" holds one report per
                   object (`object_reports`)
    loss.png       the loss history (matplotlib, Agg canvas, log y)
    view_000.png   per view: target | initial | fitted | ERROR_GAIN x |fitted - target|,
                   as diffshade.render renders them (`render_rgb`), separated by grey
                   bars; computed in linear colour and written sRGB-encoded, as every PNG
                   (docs/color.md)
    residual_000.npy    per view: fitted - target, linear float32 [H, W, 3] (signed), every
                   pixel
    residual_000.png    per view: |fitted - target| / residual_scale, clipped to 1, written
                   sRGB-encoded, on the pixels the fit counted (black elsewhere);
                   residual_scale (in result.json) is the 99th percentile of
                   |fitted - target| over the counted pixels of all views (at least 1/255)
    mask_000.png   per view: white where the fit counted the pixel (covered, inside the
                   view's mask, unsaturated, edge_margin away from the silhouette)

The files are numbered by `ids` (default 0, 1, ...: the dataset's own view numbers when
views were held out of the fit, fitting.report.holdout).

`comparison_table(result, truth)` is the true-versus-recovered table (with standard
errors; "at bound" for a value at a bound, which has none), one row per fitted scalar.
"""

import dataclasses
import math
import os

import jax
import numpy as np

from diffshade.composite import layers_needed
from diffshade.io import (
    FAST_COMPILE,
    srgb_to_linear,
    stored_jit,
    write_json,
    write_npy,
    write_png,
    write_text,
)
from diffshade.numerics import float_dtype
from diffshade.pipeline import render_fragments
from diffshade.scene import Texture, unstack_material
from diffshade.shading import shadow_maps
from fitting.data.folder import material_dict
from fitting.data.views import view_scene
from fitting.model.batch import common_lights
from fitting.model.cache import fixed_fragments, geometry_scene
from fitting.spec.gains import GAIN_NAMES, view_materials
from fitting.spec.params import object_count, value_names

RESULT_FORMAT = "diffshade-fit-result"  # result.json's "format"
ERROR_GAIN = 10.0
STATUS_LABELS = {"converged": "converged", "budget": "step budget reached",
                 "stopped": "stopped", "non-finite": "stopped on non-finite values"}
PANEL_GAP = 2
MTL_NS_LIMIT = 1000.0


def panel(target, initial, fitted, gain=ERROR_GAIN):
    """[H, W, 3] images -> [H, 4 W + 3 PANEL_GAP, 3]: target | initial | fitted |
    gain * |fitted - target| (clipped to 1)."""
    error = np.clip(gain * np.abs(np.asarray(fitted) - np.asarray(target)), 0.0, 1.0)
    gap = np.full((np.shape(target)[0], PANEL_GAP, 3), 0.5)
    parts = [np.asarray(target), gap, np.asarray(initial), gap, np.asarray(fitted), gap, error]
    return np.concatenate([np.asarray(p, np.float64)[..., :3] for p in parts], axis=1)


CURVE_SIZE = (600, 400)  # loss.png: width, height in pixels
CURVE_COLOR = (31, 119, 180)  # sRGB codes of the loss line
_MARGINS = (72, 36, 20, 48)  # left, top, right, bottom


def _tick_step(span, most=8):
    """The smallest of 1, 2, 5 x 10^k (k >= 0) that cuts [0, span] into at most `most`."""
    return next(step for k in range(20) for m in (1, 2, 5)
                if span <= most * (step := m * 10**k))


def _decade_label(d):
    return "1" if d == 0 else f"1e{d}"


def _font(size):
    from PIL import ImageFont

    try:
        return ImageFont.load_default(size=size)
    except (TypeError, ImportError, OSError):  # a Pillow without FreeType: its bitmap font
        return ImageFont.load_default()


def _layout(history, size=CURVE_SIZE):
    """Where loss_curve draws: (x of step 0, x of the last step or step 1, y of the bottom
    decade, y of the top decade, bottom decade, top decade), in pixels of an image of
    `size` (width, height); the loss axis is log10, values below the smallest positive
    loss (or NaN) drawn at it."""
    history = np.asarray(history, np.float64).reshape(-1)
    positive = history[np.isfinite(history) & (history > 0)]
    floor = positive.min() if positive.size else 1e-30
    logs = np.log10(np.clip(np.nan_to_num(history, nan=floor), floor, np.finfo(np.float64).max))
    low = int(np.floor(logs.min())) if logs.size else -1
    high = int(np.ceil(logs.max())) if logs.size else 0
    high = max(high, low + 1)
    left, top, right, bottom = _MARGINS
    return left, size[0] - right, size[1] - bottom, top, low, high, logs


def loss_curve(history, title=""):
    """The loss per step on a log axis, as a linear RGB image [h, w, 3] in [0, 1]
    (CURVE_SIZE; drawn with Pillow: decades and their 2-9 multiples as grid lines, a
    marker per step below 50 steps)."""
    from PIL import Image, ImageDraw

    x0, x1, y0, y1, low, high, logs = _layout(history)
    count = logs.size
    last = max(count - 1, 1)
    width, height = CURVE_SIZE
    image = Image.new("RGB", CURVE_SIZE, (255, 255, 255))
    draw = ImageDraw.Draw(image)
    font, small = _font(14), _font(12)

    def x_of(k):
        return x0 + (x1 - x0) * k / last

    def y_of(log):
        return y0 + (y1 - y0) * (log - low) / (high - low)

    decades = high - low
    every = _tick_step(decades)
    for d in range(low, high + 1):
        if decades <= 6:  # minor grid: 2 x ... 9 x each decade
            for m in range(2, 10):
                if d + np.log10(m) < high:
                    y = y_of(d + np.log10(m))
                    draw.line([(x0, y), (x1, y)], fill=(238, 238, 238))
        y = y_of(d)
        draw.line([(x0, y), (x1, y)], fill=(210, 210, 210))
        if (d - low) % every == 0:
            draw.line([(x0 - 5, y), (x0, y)], fill=(0, 0, 0))
            draw.text((x0 - 8, y), _decade_label(d), fill=(0, 0, 0), font=small, anchor="rm")
    step = _tick_step(last)
    for k in range(0, last + 1, step):
        x = x_of(k)
        draw.line([(x, y1), (x, y0)], fill=(210, 210, 210))
        draw.line([(x, y0), (x, y0 + 5)], fill=(0, 0, 0))
        draw.text((x, y0 + 8), str(k), fill=(0, 0, 0), font=small, anchor="mt")
    points = [(x_of(k), y_of(v)) for k, v in enumerate(logs)]
    if count > 1:
        draw.line(points, fill=CURVE_COLOR, width=2, joint="curve")
    if count < 50:
        for x, y in points:
            draw.ellipse([x - 3, y - 3, x + 3, y + 3], fill=CURVE_COLOR)
    draw.rectangle([x0, y1, x1, y0], outline=(0, 0, 0))
    draw.text(((x0 + x1) / 2, height - 8), "step", fill=(0, 0, 0), font=font, anchor="md")
    draw.text(((x0 + x1) / 2, y1 / 2), title, fill=(0, 0, 0), font=font, anchor="mm")
    label = Image.new("RGB", (40, 20), (255, 255, 255))
    ImageDraw.Draw(label).text((20, 10), "loss", fill=(0, 0, 0), font=font, anchor="mm")
    image.paste(label.rotate(90, expand=True), (4, int((y0 + y1) / 2) - 20))
    # sRGB codes (what a screen shows); write_png encodes them again
    return srgb_to_linear(np.asarray(image, np.float64) / 255.0)


def _rgb_line(key, value):
    return f"{key} " + " ".join(f"{float(x):.6f}" for x in np.broadcast_to(value, (3,)))


def _coefficient_lines(key, value, maps):
    """`Kd r g b`, or for a map `Kd 1 1 1` and `map_Kd FILE` (the map is the colour)."""
    if isinstance(value, Texture):
        return [_rgb_line(key, 1.0), f"map_{key} {(maps or {})[key.lower()]}"]
    return [_rgb_line(key, value)]


def _newmtl(material, name, maps=None):
    """The lines of one `newmtl` entry (maps: {field: file} of its textures)."""
    specular = material.ks is not None
    lines = [f"newmtl {name}", _rgb_line("Ka", material.ka),
             *_coefficient_lines("Kd", material.kd, maps),
             *_coefficient_lines("Ks", material.ks if specular else 0.0, maps),
             f"Ns {float(material.shininess):.6f}"]
    if material.emission is not None:
        lines.append(_rgb_line("Ke", material.emission))
    if getattr(material, "kt", None) is not None:
        kt = np.broadcast_to(np.asarray(material.kt, np.float64), (3,))
        lines += [f"Tr {kt.mean():.6f}", _rgb_line("Tf", kt)]
    return lines + [f"illum {2 if specular else 1}"]


def mtl_text(material, name="diffshade_fit", comment="", names=None, maps=None):
    """Wavefront MTL text of a Material: Ka, Kd, Ks (0 without specular), Ns (the Blinn-
    Phong exponent, written as fitted), Ke when it emits, Tr (the mean of kt) and Tf (kt
    per channel) when it is transparent, illum 2 (1 without specular); a kd or ks map
    (maps: {field: its image file}) as `Kd 1 1 1` and `map_Kd FILE`. A stacked Material
    (several objects, [O, 3] leaves) gives one `newmtl` per object, in object order,
    named by `names` (the objects' names) or else `{name}_0`, `{name}_1`, ..."""
    count = object_count(material)
    materials = ([material] if count is None
                 else [unstack_material(material, i) for i in range(count)])
    names = ([name] if count is None else list(names) if names is not None
             else [f"{name}_{i}" for i in range(count)])
    lines = ["# diffshade: Blinn-Phong material, linear RGB, OpenGL 1.x lighting",
             f"# Ns is the specular exponent as fitted; many OBJ viewers clamp Ns to "
             f"[0, {MTL_NS_LIMIT:g}] (OpenGL's fixed pipeline to 128)"]
    for one, label in zip(materials, names, strict=True):
        shininess = float(one.shininess)
        if shininess > MTL_NS_LIMIT:
            which = "" if count is None else f"{label}: "
            lines.append(f"# note: {which}Ns = {shininess:.6g} > {MTL_NS_LIMIT:g}: a "
                         "viewer that clamps it shows a broader highlight than the fit")
    lines += [f"# {comment}"] if comment else []
    for one, label in zip(materials, names, strict=True):
        lines += _newmtl(one, label, maps)
    return "\n".join(lines) + "\n"


def _finite_only(obj, path, replaced):
    """obj with every non-finite float replaced by None (JSON has no NaN); the paths of
    the replaced values are appended to `replaced`."""
    if isinstance(obj, dict):
        return {k: _finite_only(v, f"{path}.{k}" if path else str(k), replaced)
                for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite_only(v, f"{path}[{i}]", replaced) for i, v in enumerate(obj)]
    if isinstance(obj, float) and not math.isfinite(obj):
        replaced.append(path)
        return None
    return obj


def object_reports(result, truth) -> list:
    """Per object of a fit of several objects: its name, fitted material, truth (when
    known), its relative errors and its uncertainty report ({name: standard error, or
    None at a bound}, named without the 'objects[i].' prefix, and its warnings)."""
    reports = []
    names = result.object_names or [None] * len(result.values["objects"])
    for i, report in enumerate(result.object_reports()):
        prefix = f"objects[{i}]."
        entry = {"name": names[i],
                 "material": material_dict(unstack_material(result.material, i))}
        if truth is not None:
            entry["truth"] = material_dict(unstack_material(truth, i))
        if result.errors is not None:
            entry["errors"] = jax.tree.map(lambda x: np.asarray(x).tolist(),
                                           result.errors["objects"][i])
        if report is not None:
            entry["std_errors"] = {n.removeprefix(prefix): s
                                   for n, (_, s) in report.as_dict().items()}
            entry["warnings"] = list(report.warnings)
        reports.append(entry)
    return reports


def _map_refs(material, refs):
    """{field: file} for each texture of `material`: refs' (None where not given)."""
    return {name: (refs or {}).get(name) for name in ("kd", "ks", "shininess")
            if isinstance(getattr(material, name, None), Texture)}


def result_dict(result, init, truth, extra=None, maps=None, truth_maps=None) -> dict:
    """result.json's content: FitResult.as_dict() (without 'errors' when there is no truth),
    'material' (the full fitted material; its maps as {"texture": FILE}, maps: {field:
    FILE}), 'initial', 'truth' (when known; its maps' files from truth_maps, else null)
    and `extra`. Non-finite numbers become null and are listed in 'notes'."""
    out = dict(extra or {})
    out |= {k: v for k, v in result.as_dict().items() if not (k == "errors" and v is None)}
    names = result.object_names
    out["material"] = material_dict(result.material, names, _map_refs(result.material, maps))
    out["initial"] = material_dict(init, names)
    if truth is not None:
        out["truth"] = material_dict(truth, names, _map_refs(truth, truth_maps))
    if "objects" in result.values:
        out["objects"] = object_reports(result, truth)
    replaced = []
    out = _finite_only(out, "", replaced)
    if replaced:
        out["notes"] = out.get("notes", []) + [
            f"non-finite values written as null: {', '.join(replaced)}"]
    return out


def _std_errors(result):
    """{name: (standard error, or None at a bound; rounding bound or None)}; {} without an
    uncertainty report."""
    report = result.uncertainty
    if report is None:
        return {}
    bounds = report.rounding_bound
    return {n: (s, None if s is None or bounds is None else float(bounds[i]))
            for i, (n, (_, s)) in enumerate(report.as_dict().items())}


def _material_rows(result, truth, se):
    """The rows of the material values (one object's, or each object's in turn, labelled
    'objects[i].kd[r]', or 'NAME.kd[r]' for named objects) and the per-view gains."""
    errors = result.errors or {}
    if "objects" in result.values:
        for i, one in enumerate(result.values["objects"]):
            true = None if truth is None else unstack_material(truth, i)
            errs = errors["objects"][i] if "objects" in errors else {}
            rows = _value_rows(one, true, errs, se, result.at_bound, f"objects[{i}].")
            if result.object_names is None:
                yield from rows
                continue
            for label, *rest in rows:  # a named object's rows say its name
                yield (label.replace(f"objects[{i}]", result.object_names[i], 1), *rest)
    yield from _value_rows(result.values, truth, errors, se, result.at_bound)


_NONE = (None, None)  # no standard error, no rounding bound


def _or_zero(value):
    """An absent optional term (ks, kt: None) is 0."""
    return 0.0 if value is None else value


def _value_rows(values, truth, errors, se, at_bound, prefix=""):
    for name, value in values.items():
        if name in ("lights", "objects"):
            continue
        fitted = np.atleast_1d(np.asarray(value, np.float64))
        if name in GAIN_NAMES:  # per-view gains: no true value, one row per scalar
            for label, v in zip(value_names({name: value}), fitted.ravel(), strict=True):
                yield label, None, v, se.get(label, _NONE), label in at_bound, None
            continue
        mapped = truth is not None and isinstance(getattr(truth, name), Texture)
        true = None if truth is None or mapped else np.atleast_1d(np.asarray(
            _or_zero(getattr(truth, name)), np.float64))
        error = np.atleast_1d(errors[name]) if name in errors else None
        count = max(fitted.size, 1 if true is None else true.size)
        for c in range(count):
            label = prefix + (name if count == 1 else f"{name}[{'rgb'[c]}]")
            key = label if label in se or label in at_bound else prefix + name
            yield (label, None if true is None else true[min(c, true.size - 1)],
                   fitted[min(c, fitted.size - 1)], se.get(key, _NONE), key in at_bound,
                   None if error is None else error[min(c, error.size - 1)])


def _rows(result, truth):
    """(label, true or None, fitted, (standard error or None, rounding bound or None), at a
    bound, relative error or None): the material's rows (per channel when the truth is
    known), then the lights' (no truth)."""
    se = _std_errors(result)
    yield from _material_rows(result, truth, se)
    lights = {"lights": result.values["lights"]} if "lights" in result.values else {}
    flat = [float(x) for leaf in jax.tree.leaves(lights) for x in np.ravel(leaf)]
    for label, value in zip(value_names(lights), flat, strict=True):
        yield label, None, value, se.get(label, _NONE), label in result.at_bound, None


def _cell(value, fmt, width):
    return f"{'' if value is None else format(value, fmt):>{width}}"


ROBUST_NOTE = ("± is the robust (sandwich) standard error, as the model does not explain "
               "the images: the residuals are correlated, and the Gauss-Newton one would "
               "understate the error (docs/fitting.md)")


def _spread_columns(result):
    """(the ± column's title, whether a rounding column follows), from the report."""
    report = result.uncertainty
    robust = report is not None and report.kind == "robust"
    return ("± robust" if robust else "± s.e."), (
        report is not None and report.rounding_bound is not None)


def comparison_table(result, truth=None, status=None) -> str:
    """The true-versus-recovered table: one row per fitted scalar with the true value, the
    fitted value, its standard error ('at bound' where it has none; the robust one, titled
    '± robust', when the model does not explain the images), the worst-case shift the
    8-bit rounding of the targets can cause (a 'rounding' column, 8-bit targets only) and
    the relative error (true and error columns only when `truth` is known); warnings and
    notes below. status: the end of the first line (default: result.status in words)."""
    status = STATUS_LABELS.get(result.status, result.status) if status is None else status
    steps = f"{result.n_steps} step{'' if result.n_steps == 1 else 's'}"
    head = (f"method {result.method}: loss {result.loss:.4g} after {steps}, "
            f"{result.wall_time:.2f} s{', ' + status if status else ''}")
    known = truth is not None
    title, rounding = _spread_columns(result)
    width = max([12] + [len(row[0]) + 1 for row in _rows(result, truth)])
    lines = [head, f"{'parameter':<{width}}" + (f"{'true':>11}" if known else "")
             + f"{'fitted':>11}{title:>11}" + (f"{'rounding':>11}" if rounding else "")
             + (f"{'rel. error':>12}" if known else "")]
    for label, true, fitted, (std, bound), bounded, error in _rows(result, truth):
        spread = f"{'at bound':>11}" if bounded else _cell(std, ".2g", 11)
        spread += _cell(None if bounded else bound, ".2g", 11) if rounding else ""
        lines.append(f"{label:<{width}}" + (_cell(true, ".5g", 11) if known else "")
                     + _cell(fitted, ".5g", 11) + spread
                     + (_cell(None if error is None else 100 * error, ".3g", 11) + "%"
                        if known and error is not None else ""))
    notes = result.uncertainty.notes if result.uncertainty else ()
    notes = (*notes, *([ROBUST_NOTE] if title == "± robust" else ()))
    return "\n".join(lines + [f"warning: {w}" for w in result.warnings]
                     + [f"note: {n}" for n in notes])


# The panels render each view a few times: compiled without LLVM's optimizations
# (FAST_COMPILE), about half the compile time, no measurable cost at run time.
_render_fragments = stored_jit(render_fragments, compiler_options=FAST_COMPILE)


def render_rgb(dataset, index, material, lights=None, fragments=None):
    """View `index` rendered with `material` (and `lights`, default the view's): [H, W, 3]
    float64, equal to diffshade.render up to float rounding. The geometry is the fit's,
    fixed: the fragments come from fitting.model.cache.fixed_fragments and the shading runs in
    jax.numpy (settings.kernels 'jax'), so no program here has a host callback and the
    persistent compilation cache keeps them all; unless a light casts shadows (the maps
    are then rasterized as the settings say). fragments: a dict {layers: (Projected,
    Fragments)} of this view that the call fills, for a caller that renders the view
    again (the panels: the fitted and the initial material), which then rasterizes once."""
    scene = view_scene(dataset, index, material, lights)
    settings = dataset.settings
    fragments = {} if fragments is None else fragments
    layers = layers_needed(scene, settings)
    if layers not in fragments:
        fragments[layers] = fixed_fragments(geometry_scene(dataset, index), settings, layers)
    proj, frags = fragments[layers]
    if jax.eval_shape(lambda s: shadow_maps(s, settings), scene) is None:
        settings = dataclasses.replace(settings, kernels="jax")
    return np.asarray(_render_fragments(scene, frags, settings, proj=proj))[..., :3].astype(
        np.float64)


def panel_lights(lights) -> list:
    """The views' lights (one LightGroups each) padded to one layout with lights of
    colour 0 (fitting.model.batch.common_lights: the same images), so that every view's panel
    render shares one compiled program; as given when they differ in a static setting."""
    host = [jax.tree.map(np.asarray, g) for g in lights]
    try:
        return common_lights(host)
    except ValueError:
        return list(lights)


def residual_scale(residuals, kept) -> float:
    """The 99th percentile of |residual| over the kept pixels of all views, at least
    1/255: the value a residual PNG shows as white."""
    values = np.concatenate([np.abs(r.reshape(-1, 3)[k]).ravel()
                             for r, k in zip(residuals, kept, strict=True)])
    return max(float(np.percentile(values, 99)) if values.size else 0.0, 1.0 / 255.0)


def counted_mask(shape, kept):
    """[H, W] bool: True at the flat pixel indices `kept` of an image of `shape`."""
    mask = np.zeros(shape[0] * shape[1], bool)
    mask[np.asarray(kept, np.int64)] = True
    return mask.reshape(shape[:2])


def panel_renders(dataset, result, init, indices) -> tuple:
    """(fitted, initial): the renders of the views `indices` with the fitted material and
    lights and with the initial material and the given lights (render_rgb), as their
    panels show them (the initial ones in the dataset's float dtype)."""
    count = len(dataset.views)
    materials = view_materials(result.material, result.values, count)  # per-view gains
    lights, given = panel_lights(result.lights), panel_lights([v.lights for v in dataset.views])
    fitted, initial = [], []
    for i in indices:  # each view rasterized once for both of its renders
        fragments = {}
        fitted.append(render_rgb(dataset, i, materials[i], lights[i], fragments))
        # kept until its panel in the dtype it was rendered in (float64 adds nothing)
        initial.append(render_rgb(dataset, i, init, given[i], fragments).astype(float_dtype()))
    return fitted, initial


def write_result(out_dir, dataset, result, init, extra=None, title="", kept=None,
                 ids=None, maps=None, truth_maps=None) -> list:
    """Write the result files (module docstring) into out_dir; returns their paths.
    kept: per view, the flat indices of the pixels the fit counted (fitting.model.cache;
    default every pixel), for residual_scale, the residual images and the masks; ids: the
    number of each view in the file names (default 0, 1, ...); maps: {field: image file,
    relative to out_dir} of the fitted material's maps (written by the caller), for
    material.mtl and result.json; truth_maps: {field: file} of the truth's maps."""
    out_dir = os.fspath(out_dir)
    count = len(dataset.views)
    ids = list(range(count)) if ids is None else list(ids)
    fitted, initial = panel_renders(dataset, result, init, range(count))
    residuals = [f - v.target for f, v in zip(fitted, dataset.views, strict=True)]
    kept = kept or [np.arange(v.target.shape[0] * v.target.shape[1]) for v in dataset.views]
    scale = residual_scale(residuals, kept)
    files = {"material": "material.mtl", "loss_curve": "loss.png",
             "views": [f"view_{i:03d}.png" for i in ids],
             "residuals": [f"residual_{i:03d}.npy" for i in ids],
             "residual_images": [f"residual_{i:03d}.png" for i in ids],
             "masks": [f"mask_{i:03d}.png" for i in ids]}
    extra = dict(extra or {}) | {"files": files, "error_gain": ERROR_GAIN,
                                 "residual_scale": scale}
    paths = [write_text(os.path.join(out_dir, files["material"]),
                        mtl_text(result.material, comment=title, names=result.object_names,
                                 maps=maps)),
             write_json(os.path.join(out_dir, "result.json"),
                        result_dict(result, init, dataset.truth, extra, maps, truth_maps)),
             write_png(os.path.join(out_dir, files["loss_curve"]),
                       loss_curve(result.loss_history, title))]
    for i in range(count):
        image = panel(dataset.views[i].target, initial[i], fitted[i])
        paths.append(write_png(os.path.join(out_dir, files["views"][i]), image))
    for i, r in enumerate(residuals):
        counted = counted_mask(r.shape, kept[i])
        paths.append(write_npy(os.path.join(out_dir, files["residuals"][i]),
                               r.astype(np.float32)))
        paths.append(write_png(os.path.join(out_dir, files["residual_images"][i]),
                               np.clip(np.abs(r) / scale, 0.0, 1.0) * counted[..., None]))
        paths.append(write_png(os.path.join(out_dir, files["masks"][i]),
                               counted.astype(np.float64), color_space="linear"))
    return paths

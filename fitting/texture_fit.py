"""`diffshade fit DATASET -o OUT --texture kd=RES[,ks=RES]`: maps and the rest, and their files.

The command fits the maps and the uniform quantities together (fitting.texture_run,
through `fitting.fit(..., textures=...)`'s path): the maps by the method (--method:
'linear' solves them in closed form; 'adam', 'lbfgs' descend), the rest (ka, ks,
shininess, less the mapped ones; --fit and --grey choose among ka, kd, ks, shininess:
`--fit kd` with `--texture kd=RES` fits the map alone) by the usual fit from --init
(default DEFAULT_INIT, which also holds what is not fitted; the truth is never read).
OUT then holds the standard result files (fitting.report.result: result.json with
"format": "diffshade-fit-result", material.mtl, the panels) and, per map FIELD:
FIELD.npy (linear float [R, R, 3], row 0 = v = 1, NaN where no view sees the texel),
FIELD.png (sRGB, unseen texels black: the material's map, `map_Kd` in material.mtl and
{"texture": "kd.png"} in result.json's material, so `diffshade render --material
OUT/result.json` renders with it), FIELD_coverage.npy and .png (how many views see each
texel; the PNG scaled so the most is white) and FIELD_std_error.npy (NaN where unseen).
result.json lists them under "textures": {FIELD: {"png", "npy", "coverage", "std_error",
...}} (paths relative to OUT) with the solver's figures, and the rounds under "rounds".
Every input is checked before anything is written (fitting.texture_run.check_map_fit).

`fit_texture(dataset, res, material)` is the map alone: every other parameter held at
`material`'s (a uniform fit's, or the dataset's truth).
"""

import argparse
import os

import jax.numpy as jnp
import numpy as np

from diffshade import replace, texture, write_npy, write_png
from diffshade.io import read_json
from diffshade.scene import Texture
from fitting.data.views import view_scene
from fitting.driver import map_fit_result
from fitting.inputs import check_output, fit_spec, load_checked_dataset, parse_material
from fitting.plan import options_of
from fitting.report.result import RESULT_FORMAT, comparison_table, write_result
from fitting.solve.texture import DEFAULT_SMOOTHNESS, TEXTURE_FIELDS, solve_texture
from fitting.spec.params import DEFAULT_INIT, FitSpec
from fitting.texture_run import MAX_RES, check_map_fit, check_maps, fit_maps, uniform_spec

__all__ = ["add_texture_options", "fit_texture", "run_texture", "write_maps"]
MAP_FILES = ("png", "npy", "coverage", "std_error")
#: what --fit and --grey may name with --texture
MATERIAL_NAMES = ("ka", "kd", "ks", "shininess")


def fit_texture(dataset, res, material=None, *, field="kd", smoothness=DEFAULT_SMOOTHNESS,
                wrap="repeat", method="linear"):
    """The `field` map (res x res, a TextureSolution) of a loaded Dataset with every other
    parameter held at `material`'s (default the dataset's truth, when it has one); each
    view's pixels count where its mask says."""
    material = dataset.truth if material is None else material
    if material is None:
        raise ValueError("material: got None; expected the material of the other "
                         "parameters (ka, ks, shininess), e.g. a uniform fit's")
    check_maps(dataset, {field: res}, key="res")
    blank = replace(material, **{field: texture(np.zeros((res, res, 3), np.float32), wrap)})
    scenes = [view_scene(dataset, i, blank) for i in range(len(dataset.views))]
    masks = [jnp.ones(view.target.shape[:2], bool) if view.mask is None
             else jnp.asarray(view.mask) for view in dataset.views]
    return solve_texture(scenes, [view.target for view in dataset.views], masks, res,
                         dataset.settings, field=field, method=method, smoothness=smoothness)


def write_maps(out_dir, maps) -> dict:
    """Write each map's files (module docstring) into out_dir; returns result.json's
    "textures": {field: {"png", "npy", "coverage", "std_error", figures}}."""
    entries = {}
    for field, solution in maps.items():
        texels = np.asarray(solution.texels, np.float32)
        coverage = np.asarray(solution.coverage, np.int32)
        names = dict(zip(MAP_FILES, (f"{field}.png", f"{field}.npy", f"{field}_coverage.npy",
                                     f"{field}_std_error.npy"), strict=True))
        write_npy(os.path.join(out_dir, names["npy"]), texels)
        write_png(os.path.join(out_dir, names["png"]), np.nan_to_num(texels, nan=0.0))
        write_npy(os.path.join(out_dir, names["coverage"]), coverage)
        write_npy(os.path.join(out_dir, names["std_error"]),
                  np.asarray(solution.std_error, np.float32))
        write_png(os.path.join(out_dir, f"{field}_coverage.png"),
                  coverage[..., None] / max(int(coverage.max()), 1), color_space="linear")
        entries[field] = names | {
            "resolution": int(texels.shape[0]), "unseen_texels": int(np.sum(coverage == 0)),
            "iterations": solution.iterations, "smoothness": solution.smoothness,
            "prior_weight": solution.lam, "relative_residual": solution.residual}
    return entries


# ---- the command line ----


def texture_spec(text):
    """argparse type of --texture: 'kd=RES[,ks=RES]' -> {field: RES}."""
    maps = {}
    for item in text.split(","):
        field, _, res = item.strip().partition("=")
        if field not in TEXTURE_FIELDS or field in maps or not res.isdigit() or not (
                1 <= int(res) <= MAX_RES):
            raise argparse.ArgumentTypeError(
                f"got {text!r}; expected FIELD=RES[,FIELD=RES] with FIELD among "
                f"{', '.join(TEXTURE_FIELDS)} (each once) and RES in [1, {MAX_RES}], "
                "e.g. kd=64 or kd=64,ks=32")
        maps[field] = int(res)
    return maps


def add_texture_options(parser):
    """--texture and --smoothness on the fit command's parser."""
    parser.add_argument("--texture", type=texture_spec, metavar="kd=RES[,ks=RES]",
                        help="recover kd (and/or ks) as a RES x RES map over the mesh's UVs, "
                             "with the other parameters fitted as usual; docs/textures.md")
    parser.add_argument("--smoothness", type=float, metavar="X",
                        help=f"with --texture: the maps' prior weight, unitless, >= 0 "
                             f"(default {DEFAULT_SMOOTHNESS:g})")


_NOT_WITH_TEXTURE = (("--resume", "resume"), ("--holdout", "holdout"),
                     ("--refine-pose", "refine_pose"), ("--checkpoint-every",
                                                        "checkpoint_every"),
                     ("--chunk", "chunk"), ("--devices", "devices"))


def _check_args(args):
    if args.smoothness is not None and not (np.isfinite(args.smoothness)
                                            and args.smoothness >= 0):
        raise ValueError(f"--smoothness: got {args.smoothness!r}; expected a finite number "
                         ">= 0")
    if args.texture is None:
        raise ValueError("--smoothness: given without --texture; expected it with --texture")
    given = [flag for flag, name in _NOT_WITH_TEXTURE if getattr(args, name) not in
             (None, False)]
    if given:
        raise ValueError(f"{given[0]}: given with --texture; expected --texture without "
                         f"{', '.join(flag for flag, _ in _NOT_WITH_TEXTURE)}")


def _names_option(option, text, maps, allowed):
    """--fit or --grey with --texture: names among `allowed`; --grey names no map (a map
    named in --fit is fitted as the map)."""
    names = [n.strip() for n in text.split(",")]
    mapped = [n for n in names if n in maps]
    if mapped and option == "--grey":
        raise ValueError(f"{option}: got {text!r}; {mapped[0]} is recovered as a map "
                         f"(--texture {mapped[0]}={maps[mapped[0]]}); expected names among "
                         f"{', '.join(n for n in allowed if n not in maps)}")
    unknown = [n for n in names if n not in allowed]
    if unknown:
        raise ValueError(f"{option}: got {text!r}; with --texture expected names among "
                         f"{', '.join(n for n in allowed if n not in maps)}")


def texture_fit_spec(args) -> FitSpec:
    """The uniform quantities of `fit --texture`: --fit/--grey (default ka, kd, ks,
    shininess), less the maps (--fit kd with --texture kd=RES: none, the rest held at
    --init)."""
    maps = args.texture
    for option, text in (("--fit", args.fit), ("--grey", args.grey)):
        if text is not None:
            _names_option(option, text, maps, MATERIAL_NAMES)
    return uniform_spec(fit_spec(args.fit, args.grey), maps)


def truth_maps(dataset_dir, truth) -> dict:
    """{field: absolute path} of the truth's maps as the dataset's truth.json names them
    (result.json's "truth"), {} without a textured truth."""
    if truth is None or not any(isinstance(getattr(truth, f), Texture)
                                for f in TEXTURE_FIELDS):
        return {}
    data = read_json(os.path.join(dataset_dir, "truth.json"), "truth.json")
    return {field: os.path.abspath(os.path.join(dataset_dir, entry["texture"]))
            for field, entry in data.items() if isinstance(entry, dict) and "texture" in entry}


def _extra(args, state, spec, maps, run):
    return {"format": RESULT_FORMAT, "version": 1,
            "views": list(range(len(run.data.views))),
            "dataset": os.path.abspath(args.dataset), "loss_kind": state.kind,
            "color_space": args.color_space, "fit": spec.fitted,
            "options": state.options.as_dict(), "interrupted": False, "signal": None,
            "stop_message": None, "best_step": state.best_step,
            "rejected_steps": state.rejected, "textures": maps}


def run_texture(args) -> int:
    """`diffshade fit ... --texture FIELD=RES` (module docstring): prints the table and the
    files."""
    _check_args(args)
    check_output(args.output)
    options = options_of(args)
    spec = texture_fit_spec(args)
    init = DEFAULT_INIT if args.init is None else parse_material(args.init, "--init")
    dataset = load_checked_dataset(args.dataset, args.color_space, uniform_truth=False)
    check_map_fit(dataset, spec, args.texture, options, key="--texture")
    smoothness = DEFAULT_SMOOTHNESS if args.smoothness is None else args.smoothness
    run = fit_maps(dataset, spec, init, args.texture, options, smoothness=smoothness)
    result = map_fit_result(run, dataset)
    entries = write_maps(args.output, run.maps)
    paths = write_result(args.output, dataset, result, init,
                         _extra(args, run.state, spec, entries, run),
                         f"diffshade fit --texture: {options.method}",
                         kept=[np.asarray(v.pixels) for v in run.data.views],
                         maps={f: e["png"] for f, e in entries.items()},
                         truth_maps=truth_maps(args.dataset, dataset.truth))
    label = "converged" if run.converged else f"{len(run.rounds)} rounds, not converged"
    print(comparison_table(result, result.truth, label))
    for field, entry in entries.items():
        res = entry["resolution"]
        print(f"{field} map {res}x{res}: {res * res - entry['unseen_texels']} texels seen, "
              f"{entry['unseen_texels']} unseen; {len(run.rounds)} rounds, "
              f"{entry['iterations']} solver iterations in the last")
    for path in [os.path.join(args.output, e[k]) for e in entries.values() for k in MAP_FILES]:
        print(path)
    for path in paths:
        print(path)
    return 0

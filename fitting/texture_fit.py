"""fit_texture: a dataset's kd map in closed form, and the files that show it.

`fit_texture(dataset, res, material)` solves the dataset's kd texels over its mesh's UVs
(fitting.solve.texture: conjugate gradients on the normal equations, a smoothness prior
whose weight follows one documented rule) with every other parameter fixed at
`material`'s (ka, ks, shininess, emission: a uniform fit's result, or a synthetic
dataset's truth). Each view's pixels count where its mask says (saturated pixels are
out: the model is linear only below the clip).

`write_texture(out_dir, solution, material)` writes what docs/textures.md lists:
kd.npy (linear float [R, R, 3], row 0 = v = 1, NaN where no view sees the texel),
kd.png (sRGB, unseen texels black), kd_coverage.npy and kd_coverage.png (how many views
see each texel; the PNG scaled so the most is white), kd_std_error.npy (per texel,
NaN where unseen), material.mtl (the material with
`map_Kd kd.png`) and result.json ({"format": "diffshade-texture-result", "textures":
{"kd": {"png", "npy", "coverage", "std_error", ...}}, the solver's figures, and the
material of the other parameters), every file atomically.

`diffshade fit DATASET -o OUT --texture kd=RES [--init ...] [--smoothness X]` runs this
(`run_texture`): the other parameters come from --init, else the dataset's truth, else
the fit's default start; every input is checked before anything is written.
"""

import argparse
import os

import jax.numpy as jnp
import numpy as np

from diffshade import Mesh, replace, texture, write_npy, write_png
from diffshade.io import write_json, write_text
from fitting.data.folder import material_dict
from fitting.data.views import view_scene
from fitting.inputs import check_output, load_checked_dataset, parse_material
from fitting.report import mtl_text
from fitting.solve.texture import DEFAULT_SMOOTHNESS, TextureSolution, solve_kd_texture
from fitting.spec.params import DEFAULT_INIT

__all__ = ["add_texture_options", "fit_texture", "run_texture", "write_texture"]
RESULT_FORMAT = "diffshade-texture-result"


def _check(dataset, res, material):
    if not isinstance(res, int) or isinstance(res, bool) or not 1 <= res <= 8192:
        raise ValueError(f"res: got {res!r}; expected a texture resolution in [1, 8192]")
    if not isinstance(dataset.mesh, Mesh) or dataset.mesh.uv is None:
        raise ValueError("dataset: its mesh has no UVs; expected a mesh with texture "
                         "coordinates (an OBJ with vt, a built-in shape with \"uv\": true)")
    if dataset.objects is not None:
        raise ValueError("dataset: has several objects; expected one (textures are for "
                         "scenes of one object)")
    if material is None:
        raise ValueError("material: got None; expected the material of the other "
                         "parameters (ka, ks, shininess), e.g. a uniform fit's")


def fit_texture(dataset, res, material=None, *, smoothness=DEFAULT_SMOOTHNESS,
                wrap="repeat") -> TextureSolution:
    """The kd texture (res x res) of a loaded Dataset (module docstring). material: the
    other parameters (default the dataset's truth, when it has one)."""
    material = dataset.truth if material is None else material
    _check(dataset, res, material)
    kd = texture(np.zeros((res, res, 3), np.float32), wrap)
    material = replace(material, kd=kd)
    scenes = [view_scene(dataset, i, material) for i in range(len(dataset.views))]
    targets = [jnp.asarray(view.target) for view in dataset.views]
    masks = [jnp.ones(view.target.shape[:2], bool) if view.mask is None
             else jnp.asarray(view.mask) for view in dataset.views]
    return solve_kd_texture(scenes, targets, masks, res, dataset.settings,
                            smoothness=smoothness)


def _mtl(material):
    """material.mtl's text: the material with its kd read from kd.png."""
    lines = mtl_text(replace(material, kd=jnp.ones(3)), name="diffshade_texture").splitlines()
    at = next(i for i, line in enumerate(lines) if line.startswith("Kd "))
    return "\n".join(lines[:at + 1] + ["map_Kd kd.png"] + lines[at + 1:]) + "\n"


def write_texture(out_dir, solution: TextureSolution, material) -> dict:
    """Write the files of the module docstring into out_dir; returns result.json's
    content."""
    out_dir = os.fspath(out_dir)
    texels = np.asarray(solution.texels, np.float32)
    coverage = np.asarray(solution.coverage, np.int32)
    write_npy(os.path.join(out_dir, "kd.npy"), texels)
    write_png(os.path.join(out_dir, "kd.png"), np.nan_to_num(texels, nan=0.0))
    write_npy(os.path.join(out_dir, "kd_coverage.npy"), coverage)
    write_npy(os.path.join(out_dir, "kd_std_error.npy"), np.asarray(solution.std_error,
                                                                    np.float32))
    write_png(os.path.join(out_dir, "kd_coverage.png"),
              coverage[..., None] / max(int(coverage.max()), 1), color_space="linear")
    write_text(os.path.join(out_dir, "material.mtl"), _mtl(material))
    entry = {"png": "kd.png", "npy": "kd.npy", "coverage": "kd_coverage.npy",
             "std_error": "kd_std_error.npy",
             "unseen_texels": int(np.sum(coverage == 0)), "iterations": solution.iterations,
             "smoothness": solution.smoothness, "prior_weight": solution.lam,
             "relative_residual": solution.residual}
    summary = {"format": RESULT_FORMAT, "version": 1, "textures": {"kd": entry},
               "material": material_dict(replace(material, kd=jnp.ones(3)))}
    write_json(os.path.join(out_dir, "result.json"), summary)
    return summary


def texture_spec(text):
    """argparse type of --texture: 'kd=RES' -> ('kd', RES)."""
    field, _, res = text.partition("=")
    if field != "kd" or not res.isdigit() or not 1 <= int(res) <= 8192:
        raise argparse.ArgumentTypeError(f"got {text!r}; expected kd=RES with RES in "
                                         "[1, 8192] (a kd map; ks maps are not available)")
    return field, int(res)


def add_texture_options(parser):
    """--texture and --smoothness on the fit command's parser."""
    parser.add_argument("--texture", type=texture_spec, metavar="kd=RES",
                        help="recover a RES x RES kd texture over the mesh's UVs in closed "
                             "form, the other parameters held at --init (default: the "
                             "dataset's truth, else the default start); docs/textures.md")
    parser.add_argument("--smoothness", type=float, metavar="X",
                        help=f"with --texture: the prior's unitless weight, >= 0 (default "
                             f"{DEFAULT_SMOOTHNESS:g})")


def _check_args(args):
    if args.smoothness is not None and not args.smoothness >= 0:
        raise ValueError(f"--smoothness: got {args.smoothness!r}; expected a number >= 0")
    if args.texture is None and args.smoothness is not None:
        raise ValueError("--smoothness: given without --texture; expected it with --texture")
    given = [name for name, value in (("--resume", args.resume), ("--fit", args.fit),
                                      ("--holdout", args.holdout)) if value]
    if args.texture is not None and given:
        which = given[0]
        raise ValueError(f"{which}: given with --texture; expected --texture alone (the "
                         "other parameters are held at --init)")


def run_texture(args) -> int:
    """`diffshade fit ... --texture kd=RES` (module docstring): prints the files."""
    _check_args(args)
    check_output(args.output)
    dataset = load_checked_dataset(args.dataset, args.color_space, uniform_truth=False)
    material = (parse_material(args.init, "--init") if args.init is not None
                else dataset.truth or DEFAULT_INIT)
    _, res = args.texture
    smoothness = DEFAULT_SMOOTHNESS if args.smoothness is None else args.smoothness
    solution = fit_texture(dataset, res, material, smoothness=smoothness)
    summary = write_texture(args.output, solution, material)
    entry = summary["textures"]["kd"]
    print(f"kd texture {res}x{res}: {res * res - entry['unseen_texels']} texels seen, "
          f"{entry['unseen_texels']} unseen; {entry['iterations']} CG iterations")
    for name in ("result.json", "kd.png", "kd.npy", "kd_coverage.npy", "kd_std_error.npy",
                 "material.mtl"):
        print(os.path.join(args.output, name))
    return 0

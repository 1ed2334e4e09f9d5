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
`map_Kd kd.png`) and texture.json ({"textures": {"kd": {"png", "npy", "coverage"}}, the
solver's figures), every file atomically.
"""

import os

import jax.numpy as jnp
import numpy as np

from diffshade import Mesh, replace, texture, write_npy, write_png
from diffshade.io import write_json, write_text
from fitting.data.views import view_scene
from fitting.report import mtl_text
from fitting.solve.texture import DEFAULT_SMOOTHNESS, TextureSolution, solve_kd_texture

__all__ = ["fit_texture", "write_texture"]


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
    """Write the files of the module docstring into out_dir; returns texture.json's
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
    summary = {"textures": {"kd": entry}}
    write_json(os.path.join(out_dir, "texture.json"), summary)
    return summary

"""The texels' share of the uniform values' normal matrix: their errors with the maps free.

A fit with maps (fitting.texture_run) fits uniform values v (ka, ks, shininess, ...)
beside the maps' texels t. Its Gauss-Newton normal matrix over both is

    [[J'MJ, J'MA], [A'MJ, H]],    H = A'MA + the maps' prior (fitting.solve.texture)

J = d render / d v, A = d render / d t, M the counted pixels. The covariance of v with
the texels marginalised (free to move with v, as the fit lets them) is sigma^2 times v's
block of its inverse, the inverse of the Schur complement J'MJ - J'MA H^-1 A'MJ: less
than J'MJ by `texel_share` = J'MA H^-1 A'MJ, which fitting.report.uncertainty subtracts
(its `eliminated`). Each column of J is an image per view (uncertainty's own rows of J,
from the fit's program on the cached pixels, put in place: nothing more to compile),
the maps' solve of them all a few solve_maps calls (a right-hand side per value, on the
fit's operator and compiled program), and the share is P_i'M (A T_j), T_j = H^-1 A'MP_j.

The prior is part of H: the texels are marginalised under the same smoothness prior the
maps are solved with (with smoothness 0, the plain least-squares marginal).
"""

import numpy as np

from diffshade import replace
from fitting.data.views import view_scene
from fitting.model.batch import unpadded
from fitting.report.uncertainty import rows_fold
from fitting.solve.texture import solve_maps
from fitting.spec.params import values_to_material

__all__ = ["texel_share"]


def _columns(values, data, spec, shapes):
    """Per view [H, W, 3, p]: d model / d each scalar of `values` (value_names order) at
    the view's cached pixels (the rows fitting.report.uncertainty's J is made of), 0
    elsewhere; shapes: each view's (H, W)."""
    jac = rows_fold(values, data, spec)(lambda total, rows, *_: rows[1], None)
    columns = []
    for rows, view, (height, width) in zip(unpadded(jac, data.views), data.views, shapes,
                                           strict=True):
        image = np.zeros((height * width, 3, rows.shape[-1]))
        image[np.asarray(view.pixels)] = rows
        columns.append(image.reshape(height, width, 3, -1))
    return columns


def _solved_images(scenes, columns, masks, maps, settings, batch, options):
    """Per view [p, H, W, 3]: A T_j of every column j, `batch` right-hand sides a call
    (the last call padded with zeros), so that the calls share one compiled program
    (that of the fit's joint solves, which have `batch` right-hand sides)."""
    count = columns[0].shape[-1]
    images = [[] for _ in scenes]
    for start in range(0, count, batch):
        chunk = [np.moveaxis(c[..., start:start + batch], -1, 0) for c in columns]
        pad = batch - chunk[0].shape[0]
        chunk = [np.concatenate([c, np.zeros((pad, *c.shape[1:]), c.dtype)]) for c in chunk]
        solved = solve_maps(scenes, chunk, masks, maps, settings, affine=False, **options)
        for view, image in zip(images, solved.images, strict=True):
            view.append(np.asarray(image[:batch - pad], np.float64))
    return [np.concatenate(view) for view in images]


def texel_share(dataset, data, values, spec, maps, masks, batch=1,
                **options) -> np.ndarray:
    """[p, p] J'MA H^-1 A'MJ (module docstring) at `values` (a fit's physical values of
    `spec`, value_names order) on `data` (the fit's FitData, whose material holds the maps
    ({field: RES}) and everything else); masks: per view [H, W] bool, the counted pixels;
    batch: right-hand sides per solve (_solved_images); options: solve_maps' keywords
    (smoothness, method)."""
    settings = replace(dataset.settings, clamp=False)
    material = values_to_material(values, spec, data.material)
    scenes = [view_scene(dataset, i, material) for i in range(len(dataset.views))]
    columns = _columns(values, data, spec, [np.shape(m) for m in masks])
    images = _solved_images(scenes, columns, masks, maps, settings, batch, options)
    share = sum(np.einsum("hwci,jhwc->ij", np.where(np.asarray(m)[..., None, None], c, 0.0),
                          a)
                for c, a, m in zip(columns, images, masks, strict=True))
    return 0.5 * (share + share.T)

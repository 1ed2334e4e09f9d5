"""Standard errors that stay honest when the model does not explain the images: the
cluster-robust ("sandwich") covariance.

The Gauss-Newton covariance sigma^2 (J^T J)^-1 (fitting.report.uncertainty) assumes
independent residuals of equal variance. A model that misses something (a shadow, the
wrong shading, a light a little off) leaves a residual that is smooth over the image: its
pixels move together, so they carry far less independent information than their number
says, and the shift the missing part causes in the parameters is far larger than sigma^2
(J^T J)^-1 predicts. The sandwich estimator measures the spread from the residuals
themselves, pooled over tiles of TILE x TILE pixels (all channels) of each view so that
the correlation inside a tile is counted:

    covariance = G / (G - 1) (J^T J)^-1 (sum_c g_c g_c^T) (J^T J)^-1,   g_c = J_c^T r_c

(G tiles holding kept pixels, J_c and r_c the rows of tile c; Liang and Zeger 1986,
Cameron and Miller 2015). It treats the model error as a random field whose correlation
does not reach beyond a tile, the standard reading of misspecification; a part of the
model error that the fitted parameters can imitate exactly leaves no residual, and no
estimator computed from the residuals can see it.

`widened(report)` is the report a fit shows when the misfit check fires: per parameter
the larger of the two standard errors (correlations from the sandwich), kind 'robust'.
"""

import dataclasses

import numpy as np

#: the side of the square pixel tiles whose residuals are pooled (a view's image grid)
TILE = 16


def tile_ids(pixels, width, tile=TILE):
    """[N] int in [0, G): the tile of each flat pixel index of `pixels` (row * width +
    column) in an image `width` wide, the G tiles that hold any numbered in order; a width
    of None takes runs of tile^2 consecutive flat indices as the tiles instead."""
    pixels = np.asarray(pixels, np.int64)
    if width is None:
        keys = pixels // (tile * tile)
    else:
        per_row = -(-int(width) // tile)
        keys = (pixels // width // tile) * per_row + (pixels % width) // tile
    return np.unique(keys, return_inverse=True)[1].reshape(-1)


def cluster_scores(r, jac, ids):
    """[G, p]: g_c = J_c^T r_c summed over the rows of each tile. r: [N, 3] residuals of
    N pixels; jac: [N, 3, p]; ids: [N] tile of each pixel (tile_ids)."""
    rows = np.einsum("nc,ncp->np", np.asarray(r, np.float64), np.asarray(jac, np.float64))
    scores = np.zeros((int(ids.max(initial=-1)) + 1, rows.shape[-1]))
    np.add.at(scores, ids, rows)
    return scores


def sandwich(inverse, meat, clusters):
    """G / (G - 1) inverse @ meat @ inverse: the cluster-robust covariance from
    (J^T J)^-1 [p, p], sum_c g_c g_c^T [p, p] and the number of tiles G."""
    if clusters < 2:
        return np.full_like(inverse, np.inf)
    return clusters / (clusters - 1.0) * inverse @ meat @ inverse


def widened(report):
    """The UncertaintyReport (fitting.report.uncertainty) showing, per parameter, the
    larger of the Gauss-Newton and the robust standard error, with the robust
    correlations: what the table and result.json show when the model does not explain
    the images."""
    model, robust = report.gauss_newton_std_errors, report.robust_std_errors
    shown = np.fmax(model, robust)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(robust > 0, shown / robust, 0.0)
        covariance = report.robust_covariance * np.outer(scale, scale)
    np.fill_diagonal(covariance, shown**2)
    return dataclasses.replace(report, std_errors=shown, covariance=covariance, kind="robust")

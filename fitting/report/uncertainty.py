"""What the data determine: standard errors at the optimum and identifiability warnings.

Standard errors come from the Gauss-Newton approximation of least squares at the optimum:
J = d residuals / d physical values (`jax.jacfwd` over the kept pixels' residuals, every
pixel and channel one residual), and

    covariance = sigma^2 (J^T J)^-1,   sigma^2 = RSS / (n - p)

(n residuals, p fitted scalars). This assumes the residuals are independent with equal
variance (e.g. sensor or quantization noise), that the model is right, and that the
values are the least-squares optimum. A value at a bound of its kind (fitting.spec.params.
at_bound: a coefficient at 0 or `upper`) has no Gaussian error: it gets none (NaN, listed
in `at_bound`), and the others' are computed with it held where it is. A near-singular
J^T J (condition number of its unit-diagonal scaling above `max_condition`) is reported
with the parameters that move together in its weakest directions; those directions get a
huge (not infinite) variance.

When the model does not explain the images (fitting.report.misfit) the residuals are not
independent and these standard errors are too small: the report also holds the
cluster-robust (sandwich) ones (fitting.report.robust), and `kind` says which of the two
`std_errors` are ('gauss-newton' here; fitting.report.robust.widened makes them 'robust').

Two warnings look at the data rather than at J, because they hold for any noise level:
- ka and kd are confounded when (almost) no kept pixel is unlit by every light of its
  view (N.L <= 0): then the ambient term is never seen alone;
- ks and shininess are not determined when (almost) no kept pixel has a specular part
  above `highlight_threshold` at the fitted values: there is no highlight to fit.
Warnings are listed in the report and raised with `warnings.warn` (IdentifiabilityWarning).
"""

import dataclasses
import warnings

import jax
import numpy as np

from diffshade.scene import Texture
from fitting.data.rounding import dataset_rounding
from fitting.model.batch import batched, unpadded
from fitting.model.cache import FitData
from fitting.report.robust import cluster_scores, sandwich, tile_ids
from fitting.solve.distribute import ShardedViews, fit_data
from fitting.solve.gauss_newton import normal_system
from fitting.solve.linear import fold_parts
from fitting.spec.params import FitSpec, at_bound, value_names, values_to_lights, values_to_material


class IdentifiabilityWarning(UserWarning):
    """The data cannot separate some fitted parameters."""


@dataclasses.dataclass(frozen=True)
class UncertaintyReport:
    """names: [p] readable parameter names; values, std_errors: [p]; covariance: [p, p];
    sigma2: residual variance; n_residuals, dof (= n - p); condition: of the scaled J^T J;
    warnings: identifiability messages; rounding_bound: [p] worst-case shift from 8-bit
    rounding of the targets, or None when they are not 8-bit; notes: other caveats;
    at_bound: names of the values at a bound (their std_errors, rounding_bound and
    covariance entries are NaN); gauss_newton_std_errors, robust_std_errors: [p] the two
    estimates (module docstring), robust_covariance: [p, p]; kind: which of the two
    std_errors and covariance are, 'gauss-newton' or 'robust' (then, per parameter, the
    larger of the two: fitting.report.robust.widened)."""

    names: tuple
    values: np.ndarray
    std_errors: np.ndarray
    covariance: np.ndarray
    sigma2: float
    n_residuals: int
    dof: int
    condition: float
    warnings: tuple
    rounding_bound: np.ndarray | None = None
    notes: tuple = ()
    at_bound: tuple = ()
    gauss_newton_std_errors: np.ndarray | None = None
    robust_std_errors: np.ndarray | None = None
    robust_covariance: np.ndarray | None = None
    kind: str = "gauss-newton"

    def as_dict(self) -> dict:
        """{name: (value, standard error, or None at a bound)}."""
        return {n: (float(v), None if n in self.at_bound else float(s))
                for n, v, s in zip(self.names, self.values, self.std_errors, strict=True)}

    def select(self, prefix: str) -> "UncertaintyReport":
        """The report of the parameters whose names start with `prefix` (e.g. one
        object's, 'objects[1].'): their values, standard errors and covariance block;
        warnings naming none of them are left out."""
        keep = [i for i, n in enumerate(self.names) if n.startswith(prefix)]
        pick = lambda a: None if a is None else np.asarray(a)[keep]
        block = lambda a: None if a is None else np.asarray(a)[np.ix_(keep, keep)]
        return dataclasses.replace(
            self, names=tuple(self.names[i] for i in keep), values=pick(self.values),
            std_errors=pick(self.std_errors), covariance=block(self.covariance),
            gauss_newton_std_errors=pick(self.gauss_newton_std_errors),
            robust_std_errors=pick(self.robust_std_errors),
            robust_covariance=block(self.robust_covariance),
            warnings=tuple(w for w in self.warnings if prefix in w or "objects[" not in w),
            rounding_bound=pick(self.rounding_bound))

    def table(self) -> str:
        """One line per parameter: name, value, standard error (and rounding bound)."""
        bound = self.rounding_bound
        head = "robust s.e." if self.kind == "robust" else "std. error"
        lines = [f"{'parameter':<12} {'value':>12} {head:>12}"
                 + ("" if bound is None else f" {'rounding':>10}")]
        for i, (n, (v, s)) in enumerate(self.as_dict().items()):
            lines.append(f"{n:<12} {v:>12.6g} {'at bound' if s is None else f'{s:.3g}':>12}"
                         + ("" if bound is None else f" {bound[i]:>10.3g}"))
        return "\n".join(lines + [f"warning: {w}" for w in self.warnings]
                         + [f"note: {n}" for n in self.notes])


def _system_at(values, data, spec):
    """Levenberg-Marquardt's program (gauss_newton.normal_system) at the physical values,
    with respect to them (slopes 1): one compiled program serves the fit, the standard
    errors and the misfit check."""
    leaves = jax.tree.leaves(values)
    ones = np.ones(sum(np.size(x) for x in leaves), np.asarray(leaves[0]).dtype)
    return normal_system(values, ones, batched(data), spec, "mse")


def values_jacobian(values, data: FitData, spec: FitSpec):
    """Residuals [M] and their Jacobian [M, p] with respect to the physical values, on
    the host (the kept pixels' rows of _system_at)."""
    *_, r, jac, weight = _system_at(values, data, spec)
    keep = np.asarray(weight) > 0
    return np.asarray(r)[keep], np.asarray(jac)[keep]


def view_residuals(values, data: FitData, spec: FitSpec) -> tuple:
    """Residuals (rendered - target) of every view at the physical values, on the host in
    float64: tuple of [N_v, 3] (the rows of _system_at)."""
    r = np.asarray(_system_at(values, data, spec)[3], np.float64)
    return unpadded(r.reshape(len(data.views), -1, 3), data.views)


def rows_fold(values, data, spec: FitSpec):
    """fold(fn, total) -> total = fn(total, (r [V, N, 3], d r / d values [V, N, 3, p]),
    weight [V, N], view [V], target [V, N, 3]) over blocks of `data`'s views, in host
    memory (float64; a FitData's Jacobian in its own dtype), 0 in the padding. A FitData
    is one block, _system_at on every view (computed once here, whatever the number of
    folds); sharded views (fitting.solve.distribute.ShardedViews) are taken a chunk at a time,
    computed per fold (ShardedViews.rows_fold), so that a chunked fit's report holds one
    chunk's rows."""
    if isinstance(data, ShardedViews) and data.local:
        return lambda fn, total: data.rows_fold(values, spec, fn, total)
    data = fit_data(data)  # (several processes: every view at once, as each holds all)
    *_, r, jac, weight = _system_at(values, data, spec)
    n = len(data.views)
    r = np.asarray(r, np.float64).reshape(n, -1, 3)
    block = ((r, np.asarray(jac).reshape(*r.shape, -1)),  # float64 once its rows are kept
             np.asarray(weight).reshape(r.shape)[..., 0], np.arange(n), np.zeros(r.shape))
    for i, view in enumerate(data.views):
        block[3][i, :view.target.shape[0]] = np.asarray(view.target, np.float64)
    return lambda fn, total: fn(total, *block)


def _kept(weight, rows):
    """[V * N * 3] bool: the kept pixel-channels of a block's rows."""
    return np.broadcast_to(weight[..., None] > 0, rows.shape[:3]).reshape(-1)


def _pixel_counts(values, data, spec: FitSpec, highlight_threshold):
    """(kept pixels unlit by every light of their view, kept pixels whose specular part at
    the values exceeds highlight_threshold in some channel), from the linear solve's
    program (fitting.solve.linear.view_parts, a chunk at a time for sharded views)."""
    base = fit_data(data)
    material = values_to_material(values, spec, base.material)
    # a kd map counts as a uniform kd here: the question is where light falls
    kd = material.kd.texels[0, 0] if isinstance(material.kd, Texture) else material.kd
    unit_kd = dataclasses.replace(material, kd=np.ones(np.shape(kd), np.asarray(kd).dtype))
    lights = values_to_lights(values, spec, base.lights) if "lights" in values else None

    def add(total, parts, weight, view, target):
        kept = weight > 0
        return (total[0] + int(np.sum(kept & (np.max(parts.diffuse, -1) <= 1e-9))),
                total[1] + int(np.sum(kept & (np.max(parts.specular, -1) > highlight_threshold))))

    return fold_parts(unit_kd, lights, data, spec, add, (0, 0))


def _data_warnings(values, data, spec, highlight_threshold, min_pixels):
    unlit, bright = _pixel_counts(values, data, spec, highlight_threshold)
    found = []
    if spec.ka is not None and spec.kd is not None and unlit < min_pixels:
        found.append(f"ka and kd are confounded: {unlit} kept pixels are unlit by every "
                     "light (N.L <= 0), so the ambient term is never seen alone; add a "
                     "light or view that leaves part of the object in shadow")
    has_specular = spec.ks is not None or fit_data(data).material.ks is not None
    if has_specular and (spec.ks is not None or spec.shininess) and bright < min_pixels:
        found.append(f"ks and shininess are not determined: {bright} kept pixels have a "
                     f"specular part above {highlight_threshold}; add lights or views "
                     "whose highlights fall on the object (or the surface is not shiny)")
    return found


def _scaled_inverse(jtj, max_condition):
    """(J^T J)^-1 through its unit-diagonal scaling, with eigenvalues floored so that
    confounded directions get a huge variance; returns (inverse, condition, eigen pairs)."""
    if len(jtj) == 0:
        return np.zeros((0, 0)), 1.0, []
    scale = np.sqrt(np.diag(jtj))
    scale = np.where(scale > 0, scale, 1.0)
    corr = jtj / np.outer(scale, scale)
    eigval, eigvec = np.linalg.eigh(corr)
    top = max(eigval[-1], 1e-300)
    condition = top / max(eigval[0], 1e-300 * top)
    floored = np.maximum(eigval, top * 1e-15)
    inverse = (eigvec / floored) @ eigvec.T / np.outer(scale, scale)
    weak = [eigvec[:, i] for i in range(len(eigval)) if eigval[i] * max_condition < top]
    return inverse, condition, weak


def _conditioning_warnings(jtj, names, condition, weak):
    found = []
    dead = [n for n, d in zip(names, np.diag(jtj), strict=True) if d <= 0]
    if dead:
        found.append(f"{', '.join(dead)} have no effect on any kept pixel")
    for vec in weak:
        involved = [n for n, c in zip(names, vec, strict=True) if abs(c) > 0.3 and n not in dead]
        if len(involved) > 1:
            found.append(f"J^T J is near-singular (condition {condition:.2e}): the data do "
                         f"not separate {', '.join(involved)}")
    return found


def _tile_meat(rows, weight, view, pixels, widths):
    """(sum over the block's tiles of g_c g_c^T [p, p], the number of tiles): the robust
    covariance's middle (fitting.report.robust); a view's kept pixels are its first rows."""
    r, jac = rows
    meat, count = 0.0, 0
    for i, v in enumerate(view):
        n = int(np.sum(weight[i] > 0))
        if n:
            ids = tile_ids(np.asarray(pixels[v])[:n], None if widths is None else widths[v])
            scores = cluster_scores(r[i, :n], jac[i, :n], ids)
            meat, count = meat + scores.T @ scores, count + len(scores)
    return meat, count


def _sums(fold, size, pixels, widths):
    """J^T J, RSS, the number of residuals, the tiles' meat and their number."""

    def add(total, rows, weight, view, target):
        r, jac = rows
        keep = _kept(weight, r)
        flat_r = r.reshape(-1)[keep]
        flat_jac = np.asarray(jac.reshape(-1, jac.shape[-1])[keep], np.float64)
        meat, count = _tile_meat(rows, weight, view, pixels, widths)
        return (total[0] + flat_jac.T @ flat_jac, total[1] + float(flat_r @ flat_r),
                total[2] + flat_r.size, total[3] + meat, total[4] + count)

    zeros = np.zeros((size, size))
    return fold(add, (zeros, 0.0, 0, zeros, 0))


def _embedded(block, free):
    """[p_free, p_free] -> [p, p] with NaN in the rows and columns of values at a bound."""
    out = np.full((free.size, free.size), np.nan)
    out[np.ix_(free, free)] = block
    return out


def uncertainty(values: dict, data, spec: FitSpec, *, widths=None, rounding=None,
                highlight_threshold=0.01, min_pixels=10, max_condition=1e6,
                warn=True, eliminated=None) -> UncertaintyReport:
    """Standard errors of the physical `values` (the optimum of a fit on `data`, a
    FitData or its ShardedViews: then J^T J and the rounding bound are summed a chunk of
    views at a time), Gauss-Newton and robust, and identifiability warnings (see module
    docstring). widths: each view's image width, for the robust estimate's pixel tiles
    (None: runs of consecutive pixels, fitting.report.robust.tile_ids). rounding: each
    view's full-image Rounding for the rounding bound (kept_rounding; None: from the
    targets' codes). eliminated: (share [p, p], unknowns) of unknowns fitted beside the
    values and marginalised (a fit's map texels: fitting.report.texel_share): share is
    subtracted from J^T J (its Schur complement) and unknowns from the degrees of
    freedom; the robust estimate and the rounding bound use that inverse with J's rows
    (the texels held there)."""
    fold = rows_fold(values, data, spec)
    names = tuple(value_names(values))
    free = ~at_bound(values, spec)
    pixels = [v.pixels for v in fit_data(data).views]
    full, rss, n, meat, tiles = _sums(fold, len(names), pixels, widths)
    p = int(free.sum())
    dof = max(n - p, 1)
    if eliminated is not None:
        full, dof = full - eliminated[0], max(n - p - int(eliminated[1]), 1)
    sigma2 = rss / dof
    jtj = full[np.ix_(free, free)]
    inverse, condition, weak = _scaled_inverse(jtj, max_condition)
    covariance = _embedded(sigma2 * inverse, free)
    robust = _embedded(sandwich(inverse, meat[np.ix_(free, free)], tiles), free)
    found = _data_warnings(values, data, spec, highlight_threshold, min_pixels)
    found += _conditioning_warnings(jtj, tuple(np.array(names)[free]), condition, weak)
    if warn:
        for message in found:
            warnings.warn(message, IdentifiabilityWarning, stacklevel=2)
    flat = np.concatenate([np.ravel(np.asarray(x, np.float64))
                           for x in jax.tree.leaves(values)])
    bound, notes = _rounding(fold, free, inverse, kept_rounding(data, rounding))
    if bound is not None:
        bound = _scatter(bound, free)
    std_errors = np.sqrt(np.diag(covariance))
    return UncertaintyReport(names, flat, std_errors, covariance, sigma2, n, dof,
                             float(condition), tuple(found), bound, notes,
                             tuple(np.array(names)[~free]), std_errors,
                             np.sqrt(np.diag(robust)), robust)


def _scatter(free_values, free):
    out = np.full(free.shape, np.nan)
    out[free] = free_values
    return out


def kept_rounding(data, rounding=None):
    """Per view of `data` (a FitData or its ShardedViews), the Rounding
    (fitting.data.rounding) of its kept pixels' targets: `rounding` (one full-image
    Rounding per view, e.g. fitting.data.rounding.dataset_rounding of the dataset's views,
    which carries an undistorted photo's) at the kept pixels, or, when None, read from the
    kept targets' 8-bit codes; None when the targets have no known rounding."""
    views = fit_data(data).views
    if rounding is None:
        return dataset_rounding(views)
    return tuple(r.at(np.asarray(v.pixels)) for r, v in zip(rounding, views, strict=True))


def _rounding(fold, free, inverse, rounding):
    """8-bit targets: rounding is no independent noise (a flat region rounds one way), so
    bound its effect instead: the linearized estimate moves by (J^T J)^-1 J^T delta for
    target errors |delta_i| <= shift_i (kept_rounding: half a code step, or its bilinear mix
    for an undistorted photo), at most |(J^T J)^-1 J^T| @ shift, summed over the rows of
    `fold` (rows_fold; a second pass over a sharded fit's chunks, once (J^T J)^-1 is
    known)."""
    if rounding is None:
        return None, ()

    def add(total, rows, weight, view, target):
        jac = rows[1]
        for i, v in enumerate(view):
            n = int(np.sum(weight[i] > 0))  # a view's kept pixels are its first rows
            if n:
                rows_i = np.asarray(jac[i, :n].reshape(-1, jac.shape[-1])[:, free], np.float64)
                total = total + np.abs(inverse @ rows_i.T) @ rounding[v].shift[:n].reshape(-1)
        return total

    bound = fold(add, np.zeros(int(free.sum())))
    return bound, (f"targets are {rounding[0].source}: rounding errors are not "
                   "independent (a flat region rounds one way), so the standard errors "
                   "understate the error; rounding_bound is the worst-case shift it can cause",)

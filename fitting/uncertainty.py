"""What the data determine: standard errors at the optimum and identifiability warnings.

Standard errors come from the Gauss-Newton approximation of least squares at the optimum:
J = d residuals / d physical values (`jax.jacfwd` over the kept pixels' residuals, every
pixel and channel one residual), and

    covariance = sigma^2 (J^T J)^-1,   sigma^2 = RSS / (n - p)

(n residuals, p fitted scalars). This assumes the residuals are independent with equal
variance (e.g. sensor or quantization noise), that the model is right, and that the
values are the least-squares optimum. A value at a bound of its kind (fitting.params.
at_bound: a coefficient at 0 or `upper`) has no Gaussian error: it gets none (NaN, listed
in `at_bound`), and the others' are computed with it held where it is. A near-singular
J^T J (condition number of its unit-diagonal scaling above `max_condition`) is reported
with the parameters that move together in its weakest directions; those directions get a
huge (not infinite) variance.

Two warnings look at the data rather than at J, because they hold for any noise level:
- ka and kd are confounded when (almost) no kept pixel is unlit by every light of its
  view (N.L <= 0): then the ambient term is never seen alone;
- ks and shininess are not determined when (almost) no kept pixel has a specular part
  above `highlight_threshold` at the fitted values: there is no highlight to fit.
Warnings are listed in the report and raised with `warnings.warn` (IdentifiabilityWarning).
"""

import dataclasses
import warnings

import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from diffshade.color import decode, encode
from diffshade.compile_cache import stored_jit
from fitting.cache import FitData, pixel_parts
from fitting.gauss_newton import jacobian_matrix
from fitting.loss import values_residuals
from fitting.params import (
    FitSpec,
    at_bound,
    value_names,
    values_to_lights,
    values_to_material,
)


class IdentifiabilityWarning(UserWarning):
    """The data cannot separate some fitted parameters."""


@dataclasses.dataclass(frozen=True)
class UncertaintyReport:
    """names: [p] readable parameter names; values, std_errors: [p]; covariance: [p, p];
    sigma2: residual variance; n_residuals, dof (= n - p); condition: of the scaled J^T J;
    warnings: identifiability messages; rounding_bound: [p] worst-case shift from 8-bit
    rounding of the targets, or None when they are not 8-bit; notes: other caveats;
    at_bound: names of the values at a bound (their std_errors, rounding_bound and
    covariance entries are NaN)."""

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
        return dataclasses.replace(
            self, names=tuple(self.names[i] for i in keep), values=pick(self.values),
            std_errors=pick(self.std_errors),
            covariance=self.covariance[np.ix_(keep, keep)],
            warnings=tuple(w for w in self.warnings if prefix in w or "objects[" not in w),
            rounding_bound=pick(self.rounding_bound))

    def table(self) -> str:
        """One line per parameter: name, value, standard error (and rounding bound)."""
        bound = self.rounding_bound
        lines = [f"{'parameter':<12} {'value':>12} {'std. error':>12}"
                 + ("" if bound is None else f" {'rounding':>10}")]
        for i, (n, (v, s)) in enumerate(self.as_dict().items()):
            lines.append(f"{n:<12} {v:>12.6g} {'at bound' if s is None else f'{s:.3g}':>12}"
                         + ("" if bound is None else f" {bound[i]:>10.3g}"))
        return "\n".join(lines + [f"warning: {w}" for w in self.warnings]
                         + [f"note: {n}" for n in self.notes])


def _residual_vector(values, data, spec):
    return jnp.concatenate([r.reshape(-1) for r in values_residuals(values, spec, data)])


@stored_jit(static_argnames=("spec",))
def values_jacobian(values, data: FitData, spec: FitSpec):
    """Residuals [M] and their Jacobian [M, p] with respect to the physical values."""
    return jacobian_matrix(lambda v: _residual_vector(v, data, spec), values)


@stored_jit(static_argnames=("spec",))
def _pixel_counts(values, data: FitData, spec: FitSpec, highlight_threshold):
    """(kept pixels unlit by every light of their view, kept pixels whose specular part at
    the values exceeds highlight_threshold in some channel)."""
    material = values_to_material(values, spec, data.material)
    unit_kd = dataclasses.replace(material, kd=jnp.ones_like(material.kd))
    lights = values_to_lights(values, spec, data.lights)
    unlit = bright = 0
    for samples, light in zip(data.views, lights, strict=True):
        parts = pixel_parts(unit_kd, light, data.global_ambient, samples, data.settings)
        unlit = unlit + jnp.sum(jnp.max(parts.diffuse, -1) <= 1e-9)
        bright = bright + jnp.sum(jnp.max(parts.specular, -1) > highlight_threshold)
    return unlit, bright


def _data_warnings(values, data, spec, highlight_threshold, min_pixels):
    unlit, bright = (int(n) for n in _pixel_counts(values, data, spec, highlight_threshold))
    found = []
    if spec.ka is not None and spec.kd is not None and unlit < min_pixels:
        found.append(f"ka and kd are confounded: {unlit} kept pixels are unlit by every "
                     "light (N.L <= 0), so the ambient term is never seen alone; add a "
                     "light or view that leaves part of the object in shadow")
    has_specular = spec.ks is not None or data.material.ks is not None
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


def uncertainty(values: dict, data: FitData, spec: FitSpec, *, highlight_threshold=0.01,
                min_pixels=10, max_condition=1e6, warn=True) -> UncertaintyReport:
    """Standard errors of the physical `values` (the optimum of a fit on `data`) and
    identifiability warnings (see module docstring)."""
    r, jac = (np.asarray(a, np.float64) for a in values_jacobian(values, data, spec))
    names = tuple(value_names(values))
    free = ~at_bound(values, spec)
    n, p = r.shape[0], int(free.sum())
    dof = max(n - p, 1)
    sigma2 = float(r @ r) / dof
    jtj = jac[:, free].T @ jac[:, free]
    inverse, condition, weak = _scaled_inverse(jtj, max_condition)
    covariance = np.full((len(names), len(names)), np.nan)
    covariance[np.ix_(free, free)] = sigma2 * inverse
    found = _data_warnings(values, data, spec, highlight_threshold, min_pixels)
    found += _conditioning_warnings(jtj, tuple(np.array(names)[free]), condition, weak)
    if warn:
        for message in found:
            warnings.warn(message, IdentifiabilityWarning, stacklevel=2)
    flat = np.asarray(ravel_pytree(values)[0], np.float64)
    bound, notes = _rounding(data, jac[:, free], inverse)
    if bound is not None:
        bound = _scatter(bound, free)
    return UncertaintyReport(names, flat, np.sqrt(np.diag(covariance)), covariance, sigma2,
                             n, dof, float(condition), tuple(found), bound, notes,
                             tuple(np.array(names)[~free]))


def _scatter(free_values, free):
    out = np.full(free.shape, np.nan)
    out[free] = free_values
    return out


def _codes_8bit(values, encoding):
    """values' 8-bit codes under `encoding`, or None when they are not all 8-bit codes."""
    codes = encode(values, encoding) * 255.0
    return np.round(codes) if np.all(np.abs(codes - np.round(codes)) < 1e-3) else None


def rounding_steps(targets):
    """Worst-case |linear target - the value before 8-bit rounding| per value of `targets`
    (linear, [...]), or (None, None) when they are not 8-bit codes; with the encoding the
    codes were found in: 'linear' (0.5 / 255 everywhere) or 'srgb' (half a code step,
    mapped through the sRGB curve: from 0.5 / 255 / 12.92 in the darks to ~0.0044 at 1)."""
    targets = np.asarray(targets, np.float64)
    if _codes_8bit(targets, "linear") is not None:
        return np.full(targets.shape, 0.5 / 255.0), "linear"
    codes = _codes_8bit(targets, "srgb")
    if codes is None:
        return None, None
    centre = decode(codes / 255.0, "srgb")
    above = decode(np.minimum(codes + 0.5, 255.0) / 255.0, "srgb") - centre
    below = centre - decode(np.maximum(codes - 0.5, 0.0) / 255.0, "srgb")
    return np.maximum(above, below), "srgb"


def _rounding(data, jac, inverse):
    """8-bit targets: rounding is no independent noise (a flat region rounds one way), so
    bound its effect instead: the linearized estimate moves by (J^T J)^-1 J^T delta for
    target errors |delta_i| <= step_i (`rounding_steps`), at most |(J^T J)^-1 J^T| @ step."""
    targets = np.concatenate([np.asarray(v.target).reshape(-1) for v in data.views])
    steps, encoding = rounding_steps(targets)
    if steps is None:
        return None, ()
    bound = np.abs(inverse @ jac.T) @ steps
    return bound, (f"targets are 8-bit ({encoding}-encoded): rounding errors are not "
                   "independent (a flat region rounds one way), so the standard errors "
                   "understate the error; rounding_bound is the worst-case shift it can cause",)

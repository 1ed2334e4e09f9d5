"""Levenberg-Marquardt on the cached residuals: the fast local solver near an optimum.

Fits have few parameters (p <= 10 for a material) and many residuals, so the Gauss-Newton
system J^T W J (p x p) is cheap: J comes from `jax.jacfwd` (p forward passes) over the
kept pixels, and the damped system is solved on the host in float64. The loss is any of
`fitting.model.loss.LOSSES`; non-quadratic ones are handled by iteratively reweighted least
squares (W = rho'(r) / 2r). A step is kept only when the true loss decreases, so the loss
history is monotone. Converged: relative decrease below `tol`, loss below `atol`, or no
decreasing step for damping up to 1e10. `lm_step` is one iteration, whose state is the
params and the damping (fitting.run drives it; `levenberg_marquardt` is the plain loop).
"""

import weakref
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from diffshade.io import LIGHT_COMPILE, stored_jit
from fitting.model.batch import batched
from fitting.model.loss import irls_weight, mean_rho, stacked_residuals
from fitting.solve.distribute import ShardedViews
from fitting.spec.params import to_values

_MAX_DAMPING = 1e10


@stored_jit(static_argnames=("spec", "kind"), compiler_options=LIGHT_COMPILE)
def normal_system(values, slopes, data, spec, kind="mse"):
    """The one Jacobian program of a fit, at the physical `values`: (loss, J^T W J [p, p],
    J^T W r [p], r [M], d r / d values [M, p], weight [M]), with J = (d r / d values) *
    slopes (slopes [p]: d values / d params, value_slopes; ones: J with respect to the
    values), W the IRLS weights of `kind`, and r every view's residuals, padded to one
    pixel count (fitting.model.batch; weight 0 in the padding, where r and its rows are 0).
    Levenberg-Marquardt (linearize) and the standard errors (fitting.report.uncertainty) share
    it."""
    def flat(v):
        r, weight = stacked_residuals(v, spec, data)
        r = r.reshape(-1)
        return r, (r, jnp.repeat(weight.reshape(-1), 3))

    columns, (r, weight) = jax.jacfwd(flat, has_aux=True)(values)
    jac_values = jnp.concatenate([c.reshape(r.shape[0], -1) for c in jax.tree.leaves(columns)],
                                 axis=1)
    jac = jac_values * slopes
    irls = weight * irls_weight(kind, r)
    loss = mean_rho(kind, [r[:, None]], [weight])
    return loss, jac.T @ (irls[:, None] * jac), jac.T @ (irls * r), r, jac_values, weight


@partial(jax.jit, static_argnames=("spec",))
def value_slopes(params, spec):
    """d values / d params of every scalar, [p] in ravel_pytree order (each value is a
    function of its own param: fitting.spec.params.TRANSFORMS)."""
    ones = jax.tree.map(jnp.ones_like, params)
    return ravel_pytree(jax.jvp(lambda p: to_values(p, spec), (params,), (ones,))[1])[0]


def linearize(params, data, spec, kind="mse"):
    """(loss, J^T W J [p, p], J^T W r [p]) at params, W the IRLS weights of `kind`; on
    sharded views (fitting.solve.distribute) summed over their chunks."""
    if isinstance(data, ShardedViews):
        return data.linearize(params, spec, kind)
    return _linearize(params, data, spec, kind)


def _linearize(params, data, spec, kind="mse"):
    return normal_system(to_values(params, spec), value_slopes(params, spec), batched(data),
                         spec, kind)[:3]


def loss_at(params, data, spec, kind="mse"):
    """The loss of `kind` at params: on the cached data from the Jacobian program itself
    (normal_system; so a fit compiles no second program for it, and the linearization at
    a step Levenberg-Marquardt accepts is already there for the next step), or on sharded
    views."""
    if isinstance(data, ShardedViews):
        return data.loss(params, spec, kind)
    return _linearize64(params, data, spec, kind)[0]


def _damped_step(hess, grad, damping):
    scale = np.diag(hess) + 1e-12 * max(np.max(np.diag(hess)), 1e-30)
    return np.linalg.solve(hess + damping * np.diag(scale), -grad)


def _decreasing_step(flat, unravel, dtype, linear, data, spec, kind, damping):
    """Raise the damping until a step lowers the loss: (flat, params, loss, damping), or
    None when no step does up to damping 1e10."""
    loss, hess, grad = linear
    while damping < _MAX_DAMPING:
        candidate = flat + _damped_step(hess, grad, damping)
        params = unravel(jnp.asarray(candidate, dtype))
        new_loss = float(loss_at(params, data, spec, kind))
        if np.isfinite(new_loss) and new_loss < loss:
            return candidate, params, new_loss, damping
        damping *= 4.0
    return None


_LAST = []  # [(key, weak reference to the data, linearization)]: the latest one


def _linearize64(params, data, spec, kind):
    """linearize in float64 on the host, remembered for the latest params (the line
    search's accepted candidate is the next step's start)."""
    key = (spec, kind, *((np.asarray(x).dtype.str, np.asarray(x).tobytes())
                         for x in jax.tree.leaves(params)))
    if _LAST and _LAST[0][0] == key and _LAST[0][1]() is data:
        return _LAST[0][2]
    linear = tuple(np.asarray(x, np.float64) for x in linearize(params, data, spec, kind))
    _LAST[:] = [(key, weakref.ref(data), linear)]
    return linear


class LMStep(NamedTuple):
    """status: 'moved' (params, loss after the step, damping to start the next with),
    'converged' (no damped step lowers the loss) or 'non-finite' (the loss, gradient or
    J^T W J at params is not finite); params, loss and damping unchanged unless moved."""

    status: str
    params: dict
    loss: float
    damping: float


def lm_step(params, data, spec, kind="mse", damping=1e-3) -> LMStep:
    """One Levenberg-Marquardt iteration from params (see LMStep)."""
    flat, unravel = ravel_pytree(params)
    linear = _linearize64(params, data, spec, kind)
    if not all(np.all(np.isfinite(x)) for x in linear):
        return LMStep("non-finite", params, float(linear[0]), damping)
    found = _decreasing_step(np.asarray(flat, np.float64), unravel, flat.dtype, linear, data,
                             spec, kind, damping)
    if found is None:
        return LMStep("converged", params, float(linear[0]), damping)
    _, params, loss, damping = found
    return LMStep("moved", params, loss, max(damping / 3.0, 1e-9))


def levenberg_marquardt(params, data, spec, kind="mse", *, steps=50, tol=1e-7, atol=1e-12,
                        damping=1e-3, callback=None):
    """Minimize the loss from `params`. Returns (params, loss history [list of float],
    converged). Stops when the relative decrease is below tol or the loss below atol;
    callback(iteration, loss, params) -> True stops early."""
    history = [float(loss_at(params, data, spec, kind))]
    for it in range(steps):
        found = lm_step(params, data, spec, kind, damping)
        if found.status != "moved":
            return params, history, found.status == "converged"
        _, params, loss, damping = found
        decrease = (history[-1] - loss) / max(history[-1], 1e-30)
        history.append(loss)
        if callback is not None and callback(it, loss, params):
            break
        if decrease < tol or loss <= atol:
            return params, history, True
    return params, history, False

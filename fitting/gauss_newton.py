"""Levenberg-Marquardt on the cached residuals: the fast local solver near an optimum.

Fits have few parameters (p <= 10 for a material) and many residuals, so the Gauss-Newton
system J^T W J (p x p) is cheap: J comes from `jax.jacfwd` (p forward passes) over the
kept pixels, and the damped system is solved on the host in float64. The loss is any of
`fitting.loss.LOSSES`; non-quadratic ones are handled by iteratively reweighted least
squares (W = rho'(r) / 2r). A step is kept only when the true loss decreases, so the loss
history is monotone. Converged: relative decrease below `tol`, loss below `atol`, or no
decreasing step for damping up to 1e10. `lm_step` is one iteration, whose state is the
params and the damping (fitting.run drives it; `levenberg_marquardt` is the plain loop).
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from diffshade.compile_cache import stored_jit
from fitting.distribute import ShardedViews
from fitting.loss import irls_weight, make_loss, mean_rho, residuals

_MAX_DAMPING = 1e10


def flat_residuals(params, spec, data):
    """All views' residuals as one vector [M] (M = 3 * kept pixels)."""
    return jnp.concatenate([r.reshape(-1) for r in residuals(params, spec, data)])


def jacobian_matrix(fn, tree):
    """fn(tree) -> [M]; returns (fn(tree) [M], d fn / d tree as [M, p]) with the columns in
    `ravel_pytree(tree)` order."""
    value = fn(tree)
    jac = jax.jacfwd(fn)(tree)
    cols = [leaf.reshape(value.shape[0], -1) for leaf in jax.tree.leaves(jac)]
    return value, jnp.concatenate(cols, axis=1)


def linearize(params, data, spec, kind="mse"):
    """(loss, J^T W J [p, p], J^T W r [p]) at params, W the IRLS weights of `kind`; on
    sharded views (fitting.distribute) summed over their chunks."""
    if isinstance(data, ShardedViews):
        return data.linearize(params, spec, kind)
    return _linearize(params, data, spec, kind)


@stored_jit(static_argnames=("spec", "kind"))
def _linearize(params, data, spec, kind="mse"):
    r, jac = jacobian_matrix(lambda p: flat_residuals(p, spec, data), params)
    w = irls_weight(kind, r)
    loss = mean_rho(kind, [r[:, None]])
    return loss, jac.T @ (w[:, None] * jac), jac.T @ (w * r)


def loss_at(params, data, spec, kind="mse"):
    """The loss of `kind` at params on the cached data (jitted), or on sharded views."""
    if isinstance(data, ShardedViews):
        return data.loss(params, spec, kind)
    return _loss_at(params, data, spec, kind)


@stored_jit(static_argnames=("spec", "kind"))
def _loss_at(params, data, spec, kind="mse"):
    return make_loss(spec, kind)(params, data)


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


def _linearize64(params, data, spec, kind):
    return tuple(np.asarray(x, np.float64) for x in linearize(params, data, spec, kind))


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

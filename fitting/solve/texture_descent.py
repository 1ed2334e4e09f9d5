"""Adam and L-BFGS on a texture's texels: the closed form's objective, descended.

`descend(method, operator, rhs, preconditioner, tol, maxiter, lr)` minimizes

    q(t) = t' H t / 2 - t' rhs,    H = operator (symmetric, positive definite)

whose minimum solves the normal equations H t = rhs of a texture solve
(fitting.solve.texture): q is the solve's objective, the data misfit plus the
smoothness prior, over two, less a constant, so its gradient H t - rhs is the gradient
of the image loss with respect to the texels. Each step costs one product with H (the
value comes from the same product: q(t) = t'(g - rhs) / 2 with g = H t - rhs).
Both methods start at t = 0 and stop where the conjugate gradients stop: when the
relative residual |H t - rhs| / |rhs| falls to `tol`, or after `maxiter` steps.

- 'adam': optax.adam on the texels themselves (their units: a kd or ks), its learning
  rate `lr` decaying by cosine to LR_FLOOR x lr over `maxiter` steps, so that the
  iterates settle instead of circling the minimum at a step of about lr.
- 'lbfgs': optax.lbfgs with its zoom line search on the texels scaled by the square root
  of the preconditioner's inverse (Jacobi: s = sqrt(diag H) t), which evens out texels
  seen by many pixels and by few, as it does for conjugate gradients.
"""

import jax
import jax.numpy as jnp
import optax

__all__ = ["DESCENT_METHODS", "DEFAULT_MAXITER", "DEFAULT_TEXEL_LR", "descend"]

DESCENT_METHODS = ("adam", "lbfgs")
DEFAULT_MAXITER = {"adam": 5000, "lbfgs": 1000}
DEFAULT_TEXEL_LR = 0.02
LR_FLOOR = 1e-3


def _quadratic(operator, rhs):
    """q(t) with its gradient from one product with H (a custom VJP: H is symmetric)."""
    @jax.custom_vjp
    def q(t):
        return 0.5 * jnp.vdot(t, operator(t) - 2.0 * rhs)

    def forward(t):
        g = operator(t) - rhs
        return 0.5 * jnp.vdot(t, g - rhs), g

    def backward(g, cotangent):
        return (cotangent * g,)
    q.defvjp(forward, backward)
    return q


def _relative(g, norm_rhs):
    return jnp.sqrt(jnp.vdot(g, g)) / jnp.maximum(norm_rhs, jnp.finfo(g.dtype).tiny)


def _loop(update, start, rhs, tol, maxiter):
    """Run update(state) -> (state, gradient) from `start` while the gradient's relative
    norm is above tol: (state, steps, relative residual). The gradient is the one at the
    state before each update."""
    norm_rhs = jnp.sqrt(jnp.vdot(rhs, rhs))

    def more(carry):
        _, residual, k = carry
        return (k < maxiter) & (residual > tol)

    def step(carry):
        state, _, k = carry
        state, g = update(state)
        return state, _relative(g, norm_rhs), k + 1
    state, residual, k = jax.lax.while_loop(more, step, (start, jnp.asarray(1.0, rhs.dtype), 0))
    return state, k, residual


def _cosine(lr, maxiter):
    """The learning rate at step k: lr down to LR_FLOOR * lr by cosine over maxiter steps
    (maxiter may be traced, which optax's own schedule does not take)."""
    def schedule(count):
        done = jnp.minimum(count, maxiter) / jnp.maximum(maxiter, 1)
        return lr * (LR_FLOOR + (1.0 - LR_FLOOR) * 0.5 * (1.0 + jnp.cos(jnp.pi * done)))
    return schedule


def _adam(operator, rhs, tol, maxiter, lr):
    optimizer = optax.adam(_cosine(lr, maxiter))
    t = jnp.zeros_like(rhs)

    def update(state):
        t, opt_state = state
        g = operator(t) - rhs
        updates, opt_state = optimizer.update(g, opt_state, t)
        return (optax.apply_updates(t, updates), opt_state), g
    (t, _), k, _ = _loop(update, (t, optimizer.init(t)), rhs, tol, maxiter)
    return t, k


def _lbfgs(operator, rhs, scale, tol, maxiter):
    """L-BFGS on s = t / scale (scale: the inverse square root of diag H)."""
    q = _quadratic(lambda s: scale * operator(scale * s), scale * rhs)
    value_and_grad = optax.value_and_grad_from_state(q)
    optimizer = optax.lbfgs()
    s = jnp.zeros_like(rhs)

    def update(state):
        s, opt_state = state
        value, g = value_and_grad(s, state=opt_state)
        updates, opt_state = optimizer.update(g, opt_state, s, value=value, grad=g,
                                              value_fn=q)
        return (optax.apply_updates(s, updates), opt_state), g / scale
    (s, _), k, _ = _loop(update, (s, optimizer.init(s)), rhs, tol, maxiter)
    return scale * s, k


def descend(method, operator, rhs, preconditioner, tol, maxiter, lr=DEFAULT_TEXEL_LR):
    """(t, steps, relative residual at t) minimizing q (module docstring). operator:
    t -> H t for t shaped as rhs; preconditioner: the inverse of diag H, rhs's shape."""
    if method == "adam":
        t, k = _adam(operator, rhs, tol, maxiter, lr)
    else:
        t, k = _lbfgs(operator, rhs, jnp.sqrt(preconditioner), tol, maxiter)
    return t, k, _relative(operator(t) - rhs, jnp.sqrt(jnp.vdot(rhs, rhs)))

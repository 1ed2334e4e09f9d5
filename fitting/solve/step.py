"""A pure, jitted optax step: step(params, opt_state, data) -> (params, opt_state, loss).

`make_step(loss_fn, optimizer)` compiles once per data shape: `data` is an argument (not a
closed-over constant), so a second call with new targets or lights reuses the executable.
Optimizers with a line search (`optax.lbfgs`) are recognised by the value and gradient they
keep in their state and are driven through `optax.value_and_grad_from_state`.

`make_optimizer` gives Adam with a learning rate per group (`optax.partition` over
`param_labels`: coefficient logits and log light colours, log-shininess, light positions),
or L-BFGS, inside `optax.apply_if_finite`: a step whose gradient is not finite is
rejected by optax (params and the inner optimizer state unchanged) and counted in the
state (`last_finite`, `notfinite_count`: the rejections in a row); the step makes a
non-finite loss a non-finite gradient, so that the guard sees it too. The guard never
gives up on its own (`NEVER_GIVE_UP`): the caller decides when to stop (fitting.run).
"""

import jax
import jax.numpy as jnp
import optax

from fitting.solve.options import OPTAX_METHODS
from fitting.spec.params import param_labels

NEVER_GIVE_UP = 2**31 - 2


def make_optimizer(method="adam", *, lr=0.05, lr_shininess=0.05, lr_position=0.02,
                   memory_size=10, guard=True) -> optax.GradientTransformation:
    """'adam': Adam per group — lr for coefficient logits and log light colours,
    lr_shininess for log-shininess, lr_position for light positions (world units);
    'lbfgs': optax.lbfgs with its zoom line search (learning rates unused). Either inside
    optax.apply_if_finite (module docstring); guard=False leaves it out (only to measure
    its cost: benchmarks/fit_step.py)."""
    if method not in OPTAX_METHODS:
        raise ValueError(f"method: got {method!r}; expected one of {OPTAX_METHODS}")
    for name, value in (("lr", lr), ("lr_shininess", lr_shininess), ("lr_position", lr_position)):
        if not (isinstance(value, (int, float)) and 0 < value < float("inf")):
            raise ValueError(f"{name}: got {value!r}; expected a positive learning rate")
    inner = (optax.lbfgs(memory_size=memory_size) if method == "lbfgs" else optax.partition(
        {"colour": optax.adam(lr), "shininess": optax.adam(lr_shininess),
         "position": optax.adam(lr_position)}, param_labels))
    return optax.apply_if_finite(inner, NEVER_GIVE_UP) if guard else inner


def _has_linesearch(opt_state):
    return optax.tree.get(opt_state, "value", None) is not None


def _strong(tree):
    """Weakly typed leaves (optax.lbfgs's init state has some) made strong: the step's
    outputs are strong, so a weak input would compile the step a second time."""
    return jax.tree.map(lambda x: x.astype(x.dtype) if getattr(x, "weak_type", False) else x,
                        tree)


def _poisoned(grads, loss):
    """grads, made NaN where the loss is not finite (for apply_if_finite to reject)."""
    return jax.tree.map(lambda g: jnp.where(jnp.isfinite(loss), g, jnp.nan), grads)


def make_step(loss_fn, optimizer=None):
    """step(params, opt_state, data) -> (params, opt_state, loss), jitted, for
    loss_fn(params, data) -> scalar; loss is the value at the incoming params.
    optimizer: an optax GradientTransformation (default: make_optimizer()); only one from
    make_optimizer (or wrapped in optax.apply_if_finite) rejects non-finite steps."""
    optimizer = make_optimizer() if optimizer is None else optimizer

    def step(params, opt_state, data):
        value_fn = lambda p: loss_fn(p, data)
        if _has_linesearch(opt_state):
            loss, grads = optax.value_and_grad_from_state(value_fn)(params, state=opt_state)
            grads = _poisoned(grads, loss)
            updates, new_state = optimizer.update(grads, opt_state, params, value=loss,
                                                  grad=grads, value_fn=value_fn)
        else:
            loss, grads = jax.value_and_grad(value_fn)(params)
            updates, new_state = optimizer.update(_poisoned(grads, loss), opt_state, params)
        return optax.apply_updates(params, updates), new_state, loss

    jitted = jax.jit(step)

    def call(params, opt_state, data):
        return jitted(params, _strong(opt_state), data)

    return call

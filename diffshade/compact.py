"""on_active: evaluate a per-fragment function only at the fragments that matter.

A soft render shades H x W x K fragment slots, but with a small gamma most slots behind
the front surface get a blend weight of exactly 0 (their colour is multiplied by 0), and
slots of background pixels hold no face at all. XLA needs static shapes, so on_active
gathers the active slots into an array of fixed `capacity`, evaluates the function there
and scatters the results back (zeros elsewhere) when at most `capacity` slots are active,
and evaluates it everywhere otherwise (`lax.cond` picks at run time; under `vmap` both
branches run). Gradients flow through either branch.
"""

import jax
import jax.numpy as jnp


def on_active(fn, active, capacity, *arrays, axis_name=None):
    """fn(*arrays) -> pytree of [N, ...] arrays, for arrays [*S, ...] and active [*S] bool
    (N = prod(S)); returns the pytree reshaped to [*S, ...]. Entries where `active` is
    False are 0 or fn's value (the caller must not depend on them).

    axis_name: the name of an enclosing `vmap` axis (a batch of views): the branch is then
    chosen once for the whole batch (compacted when every member fits), so that vmap
    keeps the `lax.cond` instead of running both branches."""
    shape = active.shape
    n = active.size
    flat = [a.reshape((n,) + a.shape[len(shape):]) for a in arrays]
    mask = jax.lax.stop_gradient(active).reshape(n)

    def compacted(flat):
        idx = jnp.nonzero(mask, size=capacity, fill_value=n)[0]
        out = fn(*[jnp.take(a, idx, axis=0, mode="clip") for a in flat])
        return jax.tree.map(
            lambda o: jnp.zeros((n,) + o.shape[1:], o.dtype).at[idx].set(o, mode="drop"), out)

    def everywhere(flat):
        return fn(*flat)

    if capacity >= n:
        out = everywhere(flat)
    else:
        fits = jnp.sum(mask) <= capacity
        if axis_name is not None:
            fits = jax.lax.pmin(fits.astype(jnp.int32), axis_name) > 0
        out = jax.lax.cond(fits, compacted, everywhere, flat)
    return jax.tree.map(lambda o: o.reshape(shape + o.shape[1:]), out)

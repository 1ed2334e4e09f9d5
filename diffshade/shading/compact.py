"""on_active: evaluate a per-fragment function only at the fragments that matter.

A soft render shades H x W x K fragment slots, but with a small gamma most slots behind
the front surface get a blend weight of exactly 0 (their colour is multiplied by 0), and
slots of background pixels hold no face at all. XLA needs static shapes, so on_active
gathers the active slots into an array of fixed `capacity`, evaluates the function there
and scatters the results back (zeros elsewhere) when at most `capacity` slots are active,
and evaluates it everywhere otherwise (`lax.cond` picks at run time; under `vmap` both
branches run). Gradients flow through either branch.

The indices of the active slots come from a compiled host kernel on the CPU backend
(`host=True`; diffshade.host.active_kernel through diffshade.host.hostcall): XLA on CPU
runs `jnp.nonzero` as a cumulative sum and a scatter over all the slots (524,288 in a
256^2, K = 8 render), which costs more than lighting the active slots; the kernel is one
pass over the mask.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend import core as jex_core

from diffshade.host.active_kernel import first_active
from diffshade.host.hostcall import host_call


def active_indices(mask, capacity, host=None):
    """(indices [capacity] int32 of the True entries of mask [N] bool, in order, padded
    with N; the number of True entries, [] int32). host: by the compiled kernel (default:
    on the CPU backend), else jnp.nonzero."""
    host = jax.default_backend() == "cpu" if host is None else host
    if not host:
        return (jnp.nonzero(mask, size=capacity, fill_value=mask.shape[0])[0].astype(jnp.int32),
                jnp.sum(mask, dtype=jnp.int32))
    shapes = (jax.ShapeDtypeStruct((capacity,), jnp.int32), jax.ShapeDtypeStruct((), jnp.int32))
    return host_call(lambda m: first_active(np.asarray(m, np.bool_), capacity), shapes, mask,
                     ffi=("active", ()))


def on_active(fn, active, capacity, *arrays, axis_name=None, host=None):
    """fn(*arrays) -> pytree of [N, ...] arrays, for arrays [*S, ...] and active [*S] bool
    (N = prod(S)); returns the pytree reshaped to [*S, ...]. Entries where `active` is
    False are 0 or fn's value (the caller must not depend on them).

    capacity: an int, or a tuple of ints in ascending order (tiers): fn runs on the
    smallest tier that holds the active entries (`lax.switch` picks at run time; each tier
    is compiled), and everywhere when none does. Derivatives go through the largest tier
    (or everywhere) only (_forward_tiers). axis_name: the name of an enclosing `vmap` axis
    (a batch of views): the branch is then chosen once for the whole batch (the smallest
    tier every member fits), so that vmap keeps the `lax.switch` instead of running every
    branch. host: find the active entries with the compiled kernel (active_indices)."""
    shape = active.shape
    n = active.size
    flat = [a.reshape((n,) + a.shape[len(shape):]) for a in arrays]
    tiers = tuple(c for c in (capacity if isinstance(capacity, tuple) else (capacity,))
                  if c < n)
    if not tiers:
        return jax.tree.map(lambda o: o.reshape(shape + o.shape[1:]), fn(*flat))
    idx, count = active_indices(jax.lax.stop_gradient(active).reshape(n), tiers[-1], host)
    if len(tiers) == 1:
        out = _on_tiers(lambda size: fn, tiers, axis_name, idx, count, flat)
    else:
        out = _forward_tiers(fn, tiers, axis_name, idx, count, flat)
    return jax.tree.map(lambda o: o.reshape(shape + o.shape[1:]), out)


def _on_tiers(fn, tiers, axis_name, idx, count, flat):
    """fn on the first `size` of the active entries' indices idx (padded with N) for the
    smallest size in tiers that holds all `count`, scattered back to N rows; or on every
    row when none does. fn(size): the function for `size` rows (N: every row)."""
    n = flat[0].shape[0]

    def compacted(size):
        def branch(flat):
            part = idx[:size]
            out = fn(size)(*[jnp.take(a, part, axis=0, mode="clip") for a in flat])
            # unique_indices: the indices in range are distinct, and the padding (N) is
            # dropped; without it, the derivative of the scatter is two more scatters and
            # a gather over the N entries (how JAX handles repeated indices)
            return jax.tree.map(lambda o: jnp.zeros((n,) + o.shape[1:], o.dtype).at[part].set(
                o, mode="drop", unique_indices=True), out)
        return branch

    def everywhere(flat):
        # checkpointed: under reverse mode, lax.cond returns the residuals of both
        # branches, zeros for the branch not taken; this branch has many residual
        # arrays of N rows, which every call of the compacted branch would write as zeros.
        # Checkpointed, it keeps only its operands and recomputes the rest when taken.
        return jax.checkpoint(fn(n))(*flat)

    # the smallest tier that holds them all; len(tiers): none does
    tier = sum((count > size).astype(jnp.int32) for size in tiers)
    if axis_name is not None:
        tier = jax.lax.pmax(tier, axis_name)
    return jax.lax.switch(tier, [compacted(size) for size in tiers] + [everywhere], flat)


def _forward_tiers(fn, tiers, axis_name, idx, count, flat):
    """_on_tiers with every tier in the forward pass, and only the largest (and
    everywhere) in a derivative: under reverse mode a `lax.switch` keeps the residuals of
    every branch (zeros for those that did not run), and the tiers' residuals differ in
    shape, so each more tier would add its own to the memory and the work of a forward +
    backward. fn's closure (every value it closes over, the integer ones included) is
    passed across the custom_jvp boundary explicitly: fn is traced once per number of
    rows, and its jaxpr's constants become arguments."""
    sizes = tiers + (flat[0].shape[0],)
    traced = {size: jax.make_jaxpr(fn, return_shape=True)(*[a[:size] for a in flat])
              for size in sizes}

    def run(tiers, consts, idx, count, flat):
        def rows(size):
            program, shapes = traced[size]
            call = jex_core.jaxpr_as_fun(jex_core.ClosedJaxpr(program.jaxpr, consts[size]))
            return lambda *arrays: jax.tree.unflatten(jax.tree.structure(shapes),
                                                      call(*arrays))
        return _on_tiers(rows, tiers, axis_name, idx, count, flat)

    @jax.custom_jvp
    def tiered(consts, idx, count, flat):
        return run(tiers, consts, idx, count, flat)

    @tiered.defjvp
    def tiered_jvp(primals, tangents):
        return jax.jvp(functools.partial(run, tiers[-1:]), primals, tangents)
    return tiered({size: traced[size][0].consts for size in sizes}, idx, count, flat)

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
pass over the mask. There too, Phong's interpolation reads the active slots' face ids and
barycentrics at their positions itself (`interpolate_rows_at`, one compiled kernel, with
on_active's `positions` and `whole`), and in its derivative the gather of the barycentrics
is `take_rows`, whose transpose (reverse mode puts the cotangents back into all the slots)
runs as a compiled kernel in parallel; XLA's own is a zero fill and a scatter-add in one
thread.
"""

import functools
import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend import core as jex_core
from jax.interpreters import ad, batching, mlir

from diffshade.host import active_kernel
from diffshade.host import fragment_kernels as kernels
from diffshade.host.active_kernel import first_active
from diffshade.host.fragment_kernels import chunks
from diffshade.host.hostcall import host_call
from diffshade.raster.interpolation import corner_values, interpolate_corners


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


def take_rows(x, idx, host=False, clip=True):
    """x[idx]: [C, ...] for x [N, ...] and idx [C] int32 whose entries in [0, N) are
    distinct; the others are clipped to 0 or N - 1 (jnp.take's mode="clip"), or with
    clip=False read as 0 (the transpose of put_rows). host: a primitive whose transpose
    (reverse mode) is the compiled kernel active_kernel.put_rows where the rows are 3
    floats (the barycentrics), else jax.numpy's scatter, whatever the transform."""
    if not host:
        return _take(x, idx, clip=clip)
    return _take_p.bind(x, idx, clip=clip)


def put_rows(rows, idx, count, host=False, clip=False):
    """[count, ...]: rows [C, ...] set at idx [C] int32 (entries in [0, count) distinct),
    zeros elsewhere; the rows of other entries are dropped, or with clip=True added to
    row 0 or count - 1 (the transpose of take_rows). host: by the compiled kernel where
    the rows are 3 floats, else jax.numpy's scatter; its transpose is take_rows."""
    if not host:
        return _put(rows, idx, count=count, clip=clip, host=False)
    return _put_p.bind(rows, idx, count=count, clip=clip)


def sum_rows(rows, idx, count, group, host=False):
    """[count, ...]: row p the sum of the rows [C, ...] whose idx [C] int32 (ascending)
    // group is p; rows of other entries (the padding) are dropped. host: by the compiled
    kernel where the rows are 3 floats (active_kernel.sum_rows), else jax.numpy's
    scatter-add, whatever the transform (XLA on CPU runs a scatter-add in one thread, at
    several times the kernel's cost). Its transpose is the gather of rows by idx // group
    (take_rows, 0 for the padding)."""
    if not host:
        return _sum(rows, idx, count=count, group=group, host=False)
    return _sum_p.bind(rows, idx, count=count, group=group)


def interpolate_rows_at(tree, table, rows, ids, weights, host=None):
    """interpolation.interpolate_rows at some fragments only: [M, C_j] leaves, the values
    of the fragments at rows [M] int32 of ids [N] int32 (-1 = empty) and weights [N, 3];
    the entries of rows in [0, N) must be distinct, the others read as empty. host: one
    compiled kernel reads the face ids and weights at `rows` itself, with no gathered copy
    of them (the gathers would cost as much as the interpolation); its derivatives are
    those of the gathers followed by interpolate_rows (_interpolate_at_jvp). Else the
    gathers in jax.numpy."""
    host = jax.default_backend() == "cpu" if host is None else host
    corners, split = corner_values(tree, table)
    weights = weights.astype(corners.dtype)
    if host:
        return split(_interpolate_at(rows, ids, weights, corners))
    ids_at, weights_at = _fragments_at(rows, ids, weights)
    return split(interpolate_corners(ids_at[:, None], weights_at[:, None], corners,
                                     host=False)[0][:, 0])


def _fragments_at(rows, ids, weights):
    """The face ids [M] (-1 at rows outside [0, N)) and weights [M, 3] of the fragments
    at rows [M] (those of an end row where the face id is -1: they are not read)."""
    inside = (rows >= 0) & (rows < ids.shape[0])
    return (jnp.where(inside, jnp.take(ids, rows, mode="clip"), -1),
            jnp.take(weights, rows, axis=0, mode="clip"))


@jax.custom_jvp
def _interpolate_at(rows, ids, weights, corners):
    """interpolate_rows_at's values [M, C] by the compiled kernel, corners [F, 3, C]."""
    shape = jax.ShapeDtypeStruct((rows.shape[0], corners.shape[2]), corners.dtype)
    at = lambda *arrays: (kernels.interpolate_at(*arrays, chunks()),)
    return host_call(at, (shape,), rows, ids, weights, corners, ffi=("interpolate_at", ()))[0]


@_interpolate_at.defjvp
def _interpolate_at_jvp(primals, tangents):
    """The tangent of the gathers and the interpolation (linear primitives: take_rows and
    interpolate_corners' jvp_p, whose transposes are put_rows and the interpolation's
    backward kernel); the forward value by the kernel."""
    rows, ids, weights, corners = primals
    _, _, d_weights, d_corners = tangents
    ids_at, weights_at = _fragments_at(rows, ids, weights)
    d_at = take_rows(d_weights, rows, host=True, clip=False)
    tangent, = interpolate_corners.prims["jvp"].bind(ids_at[:, None], weights_at[:, None],
                                                     corners, d_at[:, None], d_corners)
    return _interpolate_at(rows, ids, weights, corners), tangent[:, 0]


def _take(x, idx, *, clip):
    if clip:
        return jnp.take(x, idx, axis=0, mode="clip")
    return jnp.take(x, jnp.where(idx < 0, x.shape[0], idx), axis=0, mode="fill", fill_value=0)


def _put(rows, idx, *, count, clip, host=True):
    shape = (count,) + rows.shape[1:]
    if not host or math.prod(rows.shape[1:]) != 3 or rows.dtype not in _KERNEL_DTYPES:
        if clip:
            return jnp.zeros(shape, rows.dtype).at[jnp.clip(idx, 0, count - 1)].add(rows)
        # unique_indices: the indices in range are distinct (without it, the derivative
        # of the scatter is two more scatters and a gather: how JAX handles repeats)
        return jnp.zeros(shape, rows.dtype).at[jnp.where(idx < 0, count, idx)].set(
            rows, mode="drop", unique_indices=True)
    put = lambda i, r: (active_kernel.put_rows(i, r, count, clip, chunks()),)
    out, = host_call(put, (jax.ShapeDtypeStruct((count, 3), rows.dtype),), idx,
                     rows.reshape(-1, 3), ffi=("put_rows", (int(clip),)))
    return out.reshape(shape)


def _sum(rows, idx, *, count, group, host=True):
    shape = (count,) + rows.shape[1:]
    if not host or math.prod(rows.shape[1:]) != 3 or rows.dtype not in _KERNEL_DTYPES:
        at = jnp.where(idx < 0, count, idx // group)
        return jnp.zeros(shape, rows.dtype).at[at].add(rows, mode="drop")
    summed = lambda i, r: (active_kernel.sum_rows(i, r, count, group),)
    out, = host_call(summed, (jax.ShapeDtypeStruct((count, 3), rows.dtype),), idx,
                     rows.reshape(-1, 3), ffi=("sum_rows", (group,)))
    return out.reshape(shape)


#: the float dtypes of the put_rows and sum_rows kernels' FFI targets
_KERNEL_DTYPES = (np.dtype(np.float32), np.dtype(np.float64))
_take_p = jex_core.Primitive("take_rows")
_put_p = jex_core.Primitive("put_rows")
_sum_p = jex_core.Primitive("sum_rows")


def _linear_jvp(prim, primals, tangents, **params):
    out = prim.bind(*primals, **params)
    tangent = tangents[0]
    if type(tangent) is ad.Zero:
        return out, ad.Zero.from_primal_value(out)
    return out, prim.bind(tangent, primals[1], **params)


def _take_transpose(ct, x, idx, *, clip):
    if type(ct) is ad.Zero:
        return ad.Zero(x.aval), None
    return _put_p.bind(ct, idx, count=x.aval.shape[0], clip=clip), None


def _put_transpose(ct, rows, idx, *, count, clip):
    if type(ct) is ad.Zero:
        return ad.Zero(rows.aval), None
    return _take_p.bind(ct, idx, clip=clip), None


def _sum_transpose(ct, rows, idx, *, count, group):
    if type(ct) is ad.Zero:
        return ad.Zero(rows.aval), None
    return _take_p.bind(ct, idx // group, clip=False), None


def _take_batch(args, dims, *, clip):
    (x, idx), (x_dim, idx_dim) = args, dims
    if idx_dim is None:  # one set of indices: the batch rides along as an axis of the rows
        return _take_p.bind(jnp.moveaxis(x, x_dim, 1), idx, clip=clip), 1
    take = partial(_take, clip=clip)
    return jax.vmap(take, in_axes=(x_dim, idx_dim))(x, idx), 0


def _put_batch(args, dims, *, count, clip):
    (rows, idx), (rows_dim, idx_dim) = args, dims
    if idx_dim is None:
        return _put_p.bind(jnp.moveaxis(rows, rows_dim, 1), idx, count=count, clip=clip), 1
    put = partial(_put, count=count, clip=clip, host=False)
    return jax.vmap(put, in_axes=(rows_dim, idx_dim))(rows, idx), 0


def _sum_batch(args, dims, *, count, group):
    """One call for the batch. Indices of their own per member (a batch of views' active
    slots): member b's groups become groups b * (count + 1) onwards of one ascending list,
    its padding (and any index past its slots) the extra group after its own, dropped."""
    (rows, idx), (rows_dim, idx_dim) = args, dims
    if idx_dim is None:
        return _sum_p.bind(jnp.moveaxis(rows, rows_dim, 1), idx, count=count, group=group), 1
    rows, idx = jnp.moveaxis(rows, rows_dim, 0), jnp.moveaxis(idx, idx_dim, 0)
    members, slots = rows.shape[0], count * group
    first = jnp.arange(members, dtype=idx.dtype)[:, None] * (slots + group)
    # negative indices (first in a member's ascending list) go to the group before its
    # own (the previous member's extra one), those past its slots to its extra one
    flat = (first + jnp.where(idx < 0, -1, jnp.minimum(idx, slots))).reshape(-1)
    out = _sum_p.bind(rows.reshape((-1,) + rows.shape[2:]), flat,
                      count=members * (count + 1), group=group)
    return out.reshape((members, count + 1) + out.shape[1:])[:, :count], 0


for _prim, _impl, _shape, _transpose, _batch in (
        (_take_p, _take, lambda x, idx, clip: (idx.shape[0],) + x.shape[1:], _take_transpose,
         _take_batch),
        (_put_p, _put, lambda rows, idx, count, clip: (count,) + rows.shape[1:],
         _put_transpose, _put_batch),
        (_sum_p, _sum, lambda rows, idx, count, group: (count,) + rows.shape[1:],
         _sum_transpose, _sum_batch)):
    _prim.def_impl(_impl)
    _prim.def_abstract_eval(lambda *args, _shape=_shape, **params: jax.core.ShapedArray(
        _shape(*args, **params), args[0].dtype))
    mlir.register_lowering(_prim, mlir.lower_fun(_impl, multiple_results=False))
    ad.primitive_jvps[_prim] = partial(_linear_jvp, _prim)
    ad.primitive_transposes[_prim] = _transpose
    batching.primitive_batchers[_prim] = _batch


def on_active(fn, active, capacity, *arrays, axis_name=None, host=None, positions=False,
              whole=(), group=False):
    """fn(*arrays) -> pytree of [N, ...] arrays, for arrays [*S, ...] and active [*S] bool
    (N = prod(S)); returns the pytree reshaped to [*S, ...]. Entries where `active` is
    False are 0 or fn's value (the caller must not depend on them). positions: fn takes
    first the positions among the N of the entries it is given, [M] int32 (the active
    ones, padded with N, or all; no gather of an index array). whole: more arrays [*S, ...], handed
    to fn after the others as [N, ...], whole (fn reads them at its positions itself).
    group: return fn's values summed over the last axis of S (a pixel's K slots), each
    leaf [*S[:-1], ...]: the compacted rows are summed per group (sum_rows), never put
    back into all N (fn must then be 0 where `active` is False).

    capacity: an int, or a tuple of ints in ascending order (tiers): fn runs on the
    smallest tier that holds the active entries (`lax.switch` picks at run time; each tier
    is compiled), and everywhere when none does. Derivatives go through the largest tier
    (or everywhere) only (_forward_tiers). axis_name: the name of an enclosing `vmap` axis
    (a batch of views): the branch is then chosen once for the whole batch (the smallest
    tier every member fits), so that vmap keeps the `lax.switch` instead of running every
    branch. host: find the active entries with the compiled kernel (active_indices), and
    gather with take_rows' primitive (default: on the CPU backend)."""
    host = jax.default_backend() == "cpu" if host is None else host
    shape = active.shape
    n = active.size
    flat = [a.reshape((n,) + a.shape[len(shape):]) for a in arrays + tuple(whole)]
    tiers = tuple(c for c in (capacity if isinstance(capacity, tuple) else (capacity,))
                  if c < n)
    group = shape[-1] if group else 0
    lead = shape[:-1] if group else shape
    if not tiers:
        everywhere = (jnp.arange(n, dtype=jnp.int32),) if positions else ()
        out = jax.tree.map(partial(_grouped, group=group), fn(*everywhere, *flat))
        return jax.tree.map(lambda o: o.reshape(lead + o.shape[1:]), out)
    idx, count = active_indices(jax.lax.stop_gradient(active).reshape(n), tiers[-1], host)
    rows = (positions, len(whole), group)
    if len(tiers) == 1:
        out = _on_tiers(lambda size: fn, tiers, axis_name, idx, count, flat, host, rows)
    else:
        out = _forward_tiers(fn, tiers, axis_name, idx, count, flat, host, rows)
    return jax.tree.map(lambda o: o.reshape(lead + o.shape[1:]), out)


def _grouped(o, group):
    """o [N, ...] summed over groups of `group` consecutive rows (0: o itself)."""
    return o.reshape((-1, group) + o.shape[1:]).sum(1) if group else o


def _on_tiers(fn, tiers, axis_name, idx, count, flat, host, rows=(False, 0, 0)):
    """fn on the first `size` of the active entries' indices idx (padded with N) for the
    smallest size in tiers that holds all `count`, scattered back to N rows (or with a
    group, summed into N / group); or on every row when none does. fn(size): the function
    for `size` rows (N: every row). host: the float arrays are gathered by take_rows'
    primitive. rows: (on_active's positions, how many of the last flat arrays are its
    `whole`, its group size or 0)."""
    n = flat[0].shape[0]
    positions, whole, group = rows

    def compacted(size):
        def branch(flat):
            part = idx[:size]
            where = (part,) if positions else ()
            gathered = flat[:len(flat) - whole]
            out = fn(size)(*where, *[take_rows(a, part, host and jnp.issubdtype(a.dtype,
                                                                                 jnp.inexact))
                                     for a in gathered], *flat[len(gathered):])
            # the padding (N) is dropped. XLA's scatter-set (its zero fill apart) costs
            # no more than the kernel here, and the forward pass then compiles no kernel
            if group:
                return jax.tree.map(lambda o: sum_rows(o, part, n // group, group, host), out)
            return jax.tree.map(lambda o: put_rows(o, part, n), out)
        return branch

    def everywhere(flat):
        # checkpointed: under reverse mode, lax.cond returns the residuals of both
        # branches, zeros for the branch not taken; this branch has many residual
        # arrays of N rows, which every call of the compacted branch would write as zeros.
        # Checkpointed, it keeps only its operands and recomputes the rest when taken.
        everywhere = (jnp.arange(n, dtype=jnp.int32),) if positions else ()
        out = jax.checkpoint(fn(n))(*everywhere, *flat)
        return jax.tree.map(partial(_grouped, group=group), out)

    # the smallest tier that holds them all; len(tiers): none does
    tier = sum((count > size).astype(jnp.int32) for size in tiers)
    if axis_name is not None:
        tier = jax.lax.pmax(tier, axis_name)
    return jax.lax.switch(tier, [compacted(size) for size in tiers] + [everywhere], flat)


def _forward_tiers(fn, tiers, axis_name, idx, count, flat, host, rows=(False, 0, 0)):
    """_on_tiers with every tier in the forward pass, and only the largest (and
    everywhere) in a derivative: under reverse mode a `lax.switch` keeps the residuals of
    every branch (zeros for those that did not run), and the tiers' residuals differ in
    shape, so each more tier would add its own to the memory and the work of a forward +
    backward. fn's closure (every value it closes over, the integer ones included) is
    passed across the custom_jvp boundary explicitly: fn is traced once per number of
    rows, and its jaxpr's constants become arguments. rows: as _on_tiers'."""
    sizes = tiers + (flat[0].shape[0],)
    positions, whole, _ = rows
    where = lambda size: (jax.ShapeDtypeStruct((size,), jnp.int32),) if positions else ()
    gathered = len(flat) - whole
    traced = {size: jax.make_jaxpr(fn, return_shape=True)(
        *where(size), *[a[:size] for a in flat[:gathered]], *flat[gathered:])
        for size in sizes}

    # the constants the tiers share (the values fn closes over: a texture, say) go across
    # once: a value given twice would get two cotangents, each its own array, then summed
    shared, slots = [], {}
    for const in (c for size in sizes for c in traced[size][0].consts):
        if id(const) not in slots:
            slots[id(const)] = len(shared)
            shared.append(const)
    picks = {size: [slots[id(c)] for c in traced[size][0].consts] for size in sizes}

    def run(tiers, consts, idx, count, flat):
        def sized(size):
            program, shapes = traced[size]
            call = jex_core.jaxpr_as_fun(jex_core.ClosedJaxpr(
                program.jaxpr, [consts[i] for i in picks[size]]))
            return lambda *arrays: jax.tree.unflatten(jax.tree.structure(shapes),
                                                      call(*arrays))
        return _on_tiers(sized, tiers, axis_name, idx, count, flat, host, rows)

    @jax.custom_jvp
    def tiered(consts, idx, count, flat):
        return run(tiers, consts, idx, count, flat)

    @tiered.defjvp
    def tiered_jvp(primals, tangents):
        return jax.jvp(functools.partial(run, tiers[-1:]), primals, tangents)
    return tiered(shared, idx, count, flat)

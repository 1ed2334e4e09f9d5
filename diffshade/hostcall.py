"""host_call: `jax.pure_callback` that keeps float64 arrays float64.

Under the `jax.enable_x64()` context manager (thread-local), XLA may run a callback on one
of its own threads, where x64 is off: jax then hands the callback float64 operands
converted to float32, silently, and rejects the float64 results it declared. host_call
moves every float64 array across the boundary bit-cast to uint32 pairs (which no dtype
canonicalization touches) and casts it back on the other side, so callbacks see exactly
the arrays they were given, whichever way x64 was enabled.

Callbacks run one at a time (a lock): XLA may start independent callbacks (say, of two
views rendered in one jit) on two threads at once, and numba's fallback threading layer
(workqueue, used where neither OpenMP nor TBB is installed) aborts the process on
concurrent parallel kernels.

Called outside any trace (every argument a concrete array), host_call runs `fn` at once
on the NumPy arrays: nothing is compiled. A program that contains a callback cannot be
kept in JAX's persistent compilation cache (diffshade.compile_cache), so code that runs
a host kernel on fixed inputs (the fitting cache's candidate search, fitting.cache) calls
it this way, between jitted programs that have no callback.
"""

import threading

import jax
import jax.numpy as jnp
import numpy as np

_LOCK = threading.Lock()


def _is64(dtype):
    return np.dtype(dtype) == np.float64


def _pack(x):
    """float64 [...] -> uint32 [..., 2] (other dtypes unchanged)."""
    return jax.lax.bitcast_convert_type(x, jnp.uint32) if _is64(x.dtype) else x


def _unpack(x, was64):
    return np.asarray(x).view(np.float64)[..., 0] if was64 else np.asarray(x)


def _canonical(x):
    """x as a NumPy array of the dtype jnp.asarray would give it (float32 for a Python
    float unless x64 is on), without running a JAX program."""
    x = np.asarray(x)
    return x.astype(jax.dtypes.canonicalize_dtype(x.dtype), copy=False)


def host_call(fn, result_shapes, *args, batched=False):
    """fn(*numpy arrays) -> tuple of numpy arrays shaped like result_shapes (a tuple of
    jax.ShapeDtypeStruct); run under jit and vmap as pure_callback does.

    Under vmap, fn runs once per batch member (one after another), unless `batched`: fn
    then gets the whole batch in one call, every argument with the same leading batch
    axes (of size 1 where that argument is not batched; pure_callback's "expand_dims"),
    and returns results with leading axes of the broadcast batch shape.

    Called outside a trace, fn runs at once on NumPy arrays: nothing is compiled."""
    if not any(isinstance(a, jax.core.Tracer) for a in args):  # eager: run it now
        with _LOCK:
            results = fn(*[_canonical(a) for a in args])
        return tuple(jax.device_put(np.ascontiguousarray(r, s.dtype).reshape(s.shape))
                     for r, s in zip(results, result_shapes, strict=True))
    args = [jnp.asarray(a) for a in args]
    args_64 = [_is64(a.dtype) for a in args]
    outs_64 = [_is64(s.dtype) for s in result_shapes]
    packed = tuple(jax.ShapeDtypeStruct(s.shape + (2,), np.uint32) if is64 else s
                   for s, is64 in zip(result_shapes, outs_64, strict=True))
    ndims = [a.ndim for a in args]

    def host(*host_args):
        values = [_unpack(a, is64) for a, is64 in zip(host_args, args_64, strict=True)]
        lead = np.broadcast_shapes(*(v.shape[:v.ndim - n] for v, n in
                                     zip(values, ndims, strict=True)))
        with _LOCK:
            results = fn(*values)
        out = []
        for r, s, is64 in zip(results, result_shapes, outs_64, strict=True):
            r = np.ascontiguousarray(r, s.dtype).reshape(lead + s.shape)
            out.append(r.view(np.uint32).reshape(lead + s.shape + (2,)) if is64 else r)
        return tuple(out)
    results = jax.pure_callback(host, packed, *[_pack(a) for a in args],
                                vmap_method="expand_dims" if batched else "sequential")
    return tuple(jax.lax.bitcast_convert_type(r, jnp.float64) if is64 else r
                 for r, is64 in zip(results, outs_64, strict=True))

"""host_call: `jax.pure_callback` that keeps float64 arrays float64, or an XLA FFI call.

Where the caller names an FFI target of ffi.py (the rasterizer's kernels do), host_call
binds its primitive with the operands as they are and lowers it, on the CPU, to a custom
call of that target: XLA runs the compiled handler on its own buffers (no Python, no GIL,
no copy; ffi.py). `fn` then serves eager calls, other platforms, and DIFFSHADE_FFI=0 in
the environment (read when a program is traced). Where the handlers cannot be used (a
jaxlib whose FFI API the call frame's layout does not hold for, xla_ffi.supported; numba's
workqueue threading layer), host_call takes the callback path and says why in a
FallbackWarning, once per reason. What follows is the callback path.

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

Under jit, host_call is its own primitive, lowered as jax.pure_callback is (XLA calls
back into Python) but handing `fn` the operands as XLA gives them: pure_callback first
copies every operand into a new JAX array (`device_put`), ~0.1 ms per MB, ~6 ms per
forward + backward pass of a 256^2 soft render. Its vmap rule is pure_callback's
("sequential", or "expand_dims" when batched). The primitive's lowering uses JAX internals
(jax._src.callback._callback_op_sharding, mlir.emit_python_callback and its keywords), so
it is used where this JAX has them (`_no_copy`); where it does not, host_call is
jax.pure_callback itself, with a FallbackWarning once.

Called outside any trace (every argument a concrete array), host_call runs `fn` at once
on the NumPy arrays: nothing is compiled (the FFI targets are not used: compiling a
handler costs about as much again as compiling its kernel, the first time on a machine,
and a fit's eager search needs only the kernel). A program that contains a callback
cannot be kept in JAX's persistent compilation cache (diffshade.io.compile_cache), so code
that runs a host kernel on fixed inputs (the fitting cache's candidate search,
fitting.model.cache) calls it this way, between jitted programs that have no callback.
"""

import inspect
import os
import threading
import warnings

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend.core import Primitive
from jax.interpreters import batching, mlir

try:
    from jax._src import callback as jax_callback
except ImportError:  # another JAX's internals
    jax_callback = None

_LOCK = threading.Lock()
#: DIFFSHADE_FFI=0 in the environment: the kernels run through the Python callback only
FFI_SWITCH = "DIFFSHADE_FFI"
#: the keyword arguments the no-copy lowering passes to mlir.emit_python_callback
_EMIT_KEYWORDS = ("has_side_effect", "returns_token", "sharding")
_WARNED = set()


class FallbackWarning(RuntimeWarning):
    """host_call runs a host kernel by a slower path than the one it was built for: as a
    Python callback instead of an XLA FFI target, or through jax.pure_callback (which
    copies every operand) instead of its own callback primitive. The message says why."""


def _warn_once(message):
    if message not in _WARNED:
        _WARNED.add(message)
        warnings.warn(message, FallbackWarning, stacklevel=4)


def _no_copy_missing():
    """None where this JAX has the internals host_call's callback primitive is lowered
    with, else what is missing (a sentence)."""
    if jax_callback is None or not hasattr(jax_callback, "_callback_op_sharding"):
        return "jax._src.callback._callback_op_sharding is missing"
    emit = getattr(mlir, "emit_python_callback", None)
    if emit is None:
        return "jax.interpreters.mlir.emit_python_callback is missing"
    missing = set(_EMIT_KEYWORDS) - set(inspect.signature(emit).parameters)
    if missing:
        return f"mlir.emit_python_callback takes no {', '.join(sorted(missing))}"
    return None


def _no_copy():
    """Whether host_call may use its own callback primitive (else jax.pure_callback, with
    a FallbackWarning once)."""
    missing = _no_copy_missing()
    if missing is not None:
        _warn_once(f"diffshade's host callbacks copy their operands (jax.pure_callback): "
                   f"JAX {jax.__version__}: {missing}")
    return missing is None


def _ffi_target(base, args):
    """The FFI target of ffi.py that host_call may run for `base` and these operands, or
    None (also where the environment sets DIFFSHADE_FFI=0). Where a target exists but
    the handlers cannot be used (ffi.unavailable): None, and a FallbackWarning once."""
    from diffshade.host import ffi as handlers  # (it imports the kernels' modules)

    if os.environ.get(FFI_SWITCH) == "0":
        return None
    target = handlers.target_for(base, args)
    if target is None:
        return None
    why = handlers.unavailable()
    if why is not None:
        _warn_once(f"diffshade's host kernels run as Python callbacks, not XLA FFI targets: "
                   f"{why}")
        return None
    return target


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


def host_call(fn, result_shapes, *args, batched=False, ffi=None):
    """fn(*numpy arrays) -> tuple of numpy arrays shaped like result_shapes (a tuple of
    jax.ShapeDtypeStruct); run under jit and vmap as pure_callback does.

    Under vmap, fn runs once per batch member (one after another), unless `batched`: fn
    then gets the whole batch in one call, every argument with the same leading batch
    axes (of size 1 where that argument is not batched; pure_callback's "expand_dims"),
    and returns results with leading axes of the broadcast batch shape.

    ffi: (base, attributes), the same computation as an XLA FFI target of ffi.py
    (ffi.target_for) with int attributes: under jit on the CPU, XLA then calls the
    compiled handler instead of fn (no Python, no copies); fn still serves eager calls
    and other platforms.

    Called outside a trace, fn runs at once on NumPy arrays: nothing is compiled."""
    if not any(isinstance(a, jax.core.Tracer) for a in args):  # eager: run it now
        with _LOCK:
            results = fn(*[_canonical(a) for a in args])
        return tuple(jax.device_put(np.ascontiguousarray(r, s.dtype).reshape(s.shape))
                     for r, s in zip(results, result_shapes, strict=True))
    args = [jnp.asarray(a) for a in args]
    target = None if ffi is None else _ffi_target(ffi[0], args)
    # to an FFI target, operands and results cross as they are (the handler runs in XLA,
    # whatever the x64 state of its thread); to a callback, float64 bit-cast (above)
    args_64 = [_is64(a.dtype) and target is None for a in args]
    outs_64 = [_is64(s.dtype) and target is None for s in result_shapes]
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
    if target is not None:
        return tuple(_host_p.bind(*args, fn=host, result_shapes=tuple(result_shapes),
                                  batched=batched, ffi=(target, tuple(ffi[1]))))
    if _no_copy():
        results = _host_p.bind(*[_pack(a) for a in args], fn=host, result_shapes=packed,
                               batched=batched, ffi=None)
    else:
        results = jax.pure_callback(host, packed, *[_pack(a) for a in args],
                                    vmap_method="expand_dims" if batched else "sequential")
    return tuple(jax.lax.bitcast_convert_type(r, jnp.float64) if is64 else r
                 for r, is64 in zip(results, outs_64, strict=True))


_host_p = Primitive("diffshade_host_call")
_host_p.multiple_results = True


@_host_p.def_impl
def _host_impl(*args, fn, result_shapes, batched, ffi):
    return [jnp.asarray(r) for r in fn(*[np.asarray(a) for a in args])]


@_host_p.def_abstract_eval
def _host_avals(*args, fn, result_shapes, batched, ffi):
    return [jax.core.ShapedArray(s.shape, s.dtype) for s in result_shapes]


def _host_lowering(ctx, *operands, fn, result_shapes, batched, ffi):
    if ffi is not None and tuple(ctx.module_context.platforms) == ("cpu",):
        from diffshade.host import ffi as handlers  # (it imports the kernels' modules)

        return handlers.lowering(ctx, operands, *ffi)
    if not _no_copy():  # an FFI call lowered for another platform, under another JAX
        call = lambda *args: jax.pure_callback(fn, tuple(result_shapes), *args)
        return mlir.lower_fun(call, multiple_results=True)(ctx, *operands)
    # where the callback runs in a sharded program: as pure_callback decides
    sharding = jax_callback._callback_op_sharding(ctx.module_context.axis_context, None,
                                                  ctx.avals_out)
    results, _, _ = mlir.emit_python_callback(
        ctx, fn, None, list(operands), ctx.avals_in, ctx.avals_out, has_side_effect=False,
        returns_token=False, sharding=sharding)
    return results


def _host_batch(args, dims, *, fn, result_shapes, batched, ffi):
    """pure_callback's vmap methods: one call with the batch axes leading (unbatched
    arguments get an axis of size 1) when `batched`, else one call per batch member."""
    size = next(a.shape[d] for a, d in zip(args, dims, strict=True) if d is not None)
    args = [a if d is None else jnp.moveaxis(a, d, 0) for a, d in zip(args, dims, strict=True)]
    shapes = tuple(jax.ShapeDtypeStruct((size,) + s.shape, s.dtype) for s in result_shapes)
    if batched:
        args = [a[None] if d is None else a for a, d in zip(args, dims, strict=True)]
        out = _host_p.bind(*args, fn=fn, result_shapes=shapes, batched=True, ffi=ffi)
        return out, [0] * len(out)
    mapped = [i for i, d in enumerate(dims) if d is not None]

    def one(members):
        full = list(args)
        for i, member in zip(mapped, members, strict=True):
            full[i] = member
        return _host_p.bind(*full, fn=fn, result_shapes=result_shapes, batched=False, ffi=ffi)
    out = jax.lax.map(one, [args[i] for i in mapped])
    return out, [0] * len(out)


mlir.register_lowering(_host_p, _host_lowering, cacheable=False)
batching.primitive_batchers[_host_p] = _host_batch

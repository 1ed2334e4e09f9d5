"""FragmentOp: a per-fragment op with compiled host kernels that keeps every JAX transform.

An op is given three implementations of one function of the fragments' face ids and of
float arrays: `native` in jax.numpy, and a compiled host `forward` and `backward` (its
vector-Jacobian product). `FragmentOp.__call__(..., host=False)` is just `native`, so
every transform works as JAX makes it work. With host=True the op is three JAX
primitives, each with the rules JAX needs:

    op_p   forward kernel.       jvp: op_p for the primal, jvp_p for the tangent.
    jvp_p  the tangent map, linear in the tangents; evaluated with jax.jvp of `native`
           (forward mode is rarely the hot path).  transpose: vjp_p.
    vjp_p  backward kernel, linear in the cotangents.  transpose: jvp_p.

Reverse mode therefore runs the forward and backward kernels only, forward mode the
forward kernel plus JAX's tangent code; higher orders differentiate jvp_p and vjp_p
through `native` (jvp rules from jax.jvp of the native maps). Batching (vmap, jacfwd,
vmap of grad) folds the batch into one kernel call: B images of H rows become one image of
B*H rows (the kernels take the pixel position modulo H*W), and the per-face arrays of the
B batch members are concatenated with face ids offset by b*F. jvp_p batches with jax.vmap
of its native map. Under `jit` the kernels run through a host callback (hostcall.py);
they are CPU code, which is why render picks host=True only on the CPU backend.

Argument kinds: the first argument is always `ids` [H, W, K] int32 (-1 = empty); each
float argument is 'pixel' ([H, W, K, ...], like ids) or 'face' ([F, ...], indexed by ids);
every output is 'pixel'. Static parameters (Python values) go as keyword arguments.

Saved values: the forward kernel may return, after the op's outputs, `saved` more
per-pixel arrays (of any dtype) that only its backward reads, so that the backward does
not redo work the forward did (the geometry's nearest edges). op_p returns them too, and
jvp_p and vjp_p take them after the args, as primal (non-linear) arguments: reverse mode
keeps them as residuals of the forward. They have no tangent, the native maps never see
them, and FragmentOp.__call__ does not return them.
"""

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

from diffshade.host.hostcall import host_call


@dataclasses.dataclass(frozen=True)
class FragmentOp:
    """name; kinds: tuple of 'pixel' / 'face', one per float argument; native(ids, *args,
    **params) -> tuple of arrays (jax.numpy); forward(ids, *args, **params) -> tuple of
    numpy arrays (the outputs, then the `saved` values), and backward(ids, *args, *saved,
    *cotangents, **params) -> tuple of numpy arrays shaped like args (host kernels, given
    numpy arrays); out_avals(ids, *args, **params) -> tuple of jax.ShapeDtypeStruct of
    the forward kernel's results (the outputs, then the saved values)."""

    name: str
    kinds: tuple
    native: object
    forward: object
    backward: object
    out_avals: object
    #: (prefix, names of the int params): the kernels as XLA FFI targets of ffi.py,
    #: prefix_forward and prefix_backward, given those params as attributes; None: the
    #: host callback only
    ffi: tuple = None
    #: how many of the forward kernel's last results are saved values for its backward,
    #: not outputs of the op (module docstring)
    saved: int = 0

    def __post_init__(self):
        prims = {p: Primitive(f"{self.name}_{p}") for p in ("op", "jvp", "vjp")}
        object.__setattr__(self, "prims", prims)
        for prim in prims.values():
            prim.multiple_results = True
        n = len(self.kinds) + self.saved
        _define(prims["op"], self._forward_host, self._forward_avals,
                self._fold_batch(prims["op"], self.kinds))
        _define(prims["jvp"], self._jvp_native, self._jvp_avals, self._jvp_batch)
        _define(prims["vjp"], self._backward_host, self._vjp_avals,
                self._fold_batch(prims["vjp"], self.kinds))
        ad.primitive_jvps[prims["op"]] = self._op_jvp
        ad.primitive_jvps[prims["jvp"]] = partial(self._native_jvp, self._jvp_native)
        ad.primitive_jvps[prims["vjp"]] = partial(self._native_jvp, self._vjp_native)
        ad.primitive_transposes[prims["jvp"]] = partial(self._transpose, prims["vjp"], n)
        ad.primitive_transposes[prims["vjp"]] = partial(self._transpose, prims["jvp"], n)

    def __call__(self, ids, *args, host, **params):
        """The op's outputs (a tuple), by the host kernels or by `native`."""
        if not host:
            return tuple(self.native(ids, *args, **params))
        out = self.prims["op"].bind(ids, *args, **params)
        return tuple(out[:len(out) - self.saved])

    # -- evaluation ---------------------------------------------------------------------

    def _forward_avals(self, ids, *args, **params):
        return tuple(self.out_avals(ids, *args, **params))

    def _ffi(self, stage, params):
        """host_call's ffi argument of the forward or backward kernel."""
        if self.ffi is None:
            return None
        prefix, names = self.ffi
        return f"{prefix}_{stage}", tuple(int(params[name]) for name in names)

    def _forward_host(self, ids, *args, **params):
        return host_call(partial(self.forward, **params), self._forward_avals(ids, *args,
                                                                              **params),
                         ids, *args, ffi=self._ffi("forward", params))

    def _output_avals(self, ids, *args, **params):
        """The avals of the op's outputs (not the saved values), args: the float args."""
        avals = self._forward_avals(ids, *args, **params)
        return avals[:len(avals) - self.saved]

    def _jvp_avals(self, ids, *args, **params):
        return self._output_avals(ids, *args[:len(self.kinds)], **params)

    def _jvp_native(self, ids, *args, **params):
        n = len(self.kinds)
        fn = lambda *primals: tuple(self.native(ids, *primals, **params))
        return jax.jvp(fn, tuple(args[:n]), tuple(args[n + self.saved:]))[1]

    def _vjp_avals(self, ids, *args, **params):
        return tuple(jax.ShapeDtypeStruct(a.shape, a.dtype) for a in args[:len(self.kinds)])

    def _backward_host(self, ids, *args, **params):
        return host_call(partial(self.backward, **params), self._vjp_avals(ids, *args,
                                                                           **params),
                         ids, *args, ffi=self._ffi("backward", params))

    def _vjp_native(self, ids, *args, **params):
        n = len(self.kinds)
        fn = lambda *primals: tuple(self.native(ids, *primals, **params))
        return jax.vjp(fn, *args[:n])[1](tuple(args[n + self.saved:]))

    # -- differentiation ----------------------------------------------------------------

    def _op_jvp(self, primals, tangents, **params):
        ids, *args = primals
        out = self.prims["op"].bind(ids, *args, **params)
        saved = out[len(out) - self.saved:]
        tangents = [ad.instantiate_zeros(t) for t in tangents[1:]]
        out_tangents = self.prims["jvp"].bind(ids, *args, *saved, *tangents, **params)
        return out, [*out_tangents, *(ad.Zero(jax.typeof(v).to_tangent_aval()) for v in saved)]

    def _transpose(self, other, n, cotangents, ids, *args, **params):
        """jvp_p and vjp_p are each other's transpose in their last arguments (tangents of
        the args, or cotangents of the outputs); the first n args are primal values (the
        float args, then the saved values)."""
        primals = args[:n]
        if any(ad.is_undefined_primal(a) for a in (ids, *primals)):
            raise NotImplementedError(f"{self.name}: transposed in a non-linear argument")
        avals = self._avals_of(other, ids, primals, params)
        cotangents = [_zeros_if_symbolic(c, a) for c, a in zip(cotangents, avals, strict=True)]
        result = other.bind(ids, *primals, *cotangents, **params)
        return (None,) * (1 + n) + tuple(result)

    def _avals_of(self, other, ids, primals, params):
        """The avals of `other`'s linear inputs: the outputs of the primitive transposed."""
        primals = primals[:len(self.kinds)]
        if other is self.prims["vjp"]:
            return self._output_avals(ids, *primals, **params)
        return tuple(jax.ShapeDtypeStruct(p.shape, p.dtype) for p in primals)

    def _native_jvp(self, native_fn, primals, tangents, **params):
        """A jvp rule of jvp_p or vjp_p from jax.jvp of its native map (used for
        second-order derivatives); the saved values are constants there."""
        ids, *args = primals
        n, end = len(self.kinds), len(self.kinds) + self.saved
        saved = args[n:end]
        fn = lambda *a: tuple(native_fn(ids, *a[:n], *saved, *a[n:], **params))
        tangents = [ad.instantiate_zeros(t) for t in tangents[1:]]
        return jax.jvp(fn, (*args[:n], *args[end:]), (*tangents[:n], *tangents[end:]))

    # -- batching -----------------------------------------------------------------------

    def _jvp_batch(self, args, dims, **params):
        out = jax.vmap(partial(self._jvp_native, **params), in_axes=tuple(dims))(*args)
        return out, (0,) * len(out)

    def _fold_batch(self, prim, kinds):
        """A batching rule that folds the batch into one call of `prim` (module docstring);
        kinds: of the op's float arguments. Every output, per pixel or per face, splits back
        along its leading axis."""
        def rule(args, dims, **params):
            size = next(a.shape[d] for a, d in zip(args, dims, strict=True)
                        if d is not None)
            ids, *floats = [_batch_first(a, d, size) for a, d in zip(args, dims, strict=True)]
            # cotangents of the outputs follow the kinds: they are all 'pixel'
            faces = next((a.shape[1] for a, k in zip(floats, kinds, strict=False)
                          if k == "face"), 0)
            offset = jnp.arange(size, dtype=ids.dtype) * faces
            ids = jnp.where(ids >= 0, ids + offset.reshape((size,) + (1,) * (ids.ndim - 1)), -1)
            out = prim.bind(_merge(ids), *[_merge(a) for a in floats], **params)
            return [a.reshape((size, -1) + a.shape[1:]) for a in out], (0,) * len(out)
        return rule


def _define(prim, impl, avals, batch_rule):
    """impl (JAX code) serves eager calls and lowering; avals gives the output types."""
    prim.def_impl(impl)
    prim.def_abstract_eval(lambda *args, **params: tuple(
        jax.core.ShapedArray(s.shape, s.dtype) for s in avals(*args, **params)))
    mlir.register_lowering(prim, mlir.lower_fun(impl, multiple_results=True))
    batching.primitive_batchers[prim] = batch_rule


def _zeros_if_symbolic(ct, aval):
    if type(ct) is ad.Zero:
        return jnp.zeros(aval.shape, aval.dtype)
    return ct


def _batch_first(x, dim, size):
    """x with its batch axis first ([size, ...]), broadcast when it is not batched."""
    if dim is None:
        return jnp.broadcast_to(x, (size,) + x.shape)
    return jnp.moveaxis(x, dim, 0)


def _merge(x):
    """[B, N, ...] -> [B * N, ...]."""
    return x.reshape((x.shape[0] * x.shape[1],) + x.shape[2:])

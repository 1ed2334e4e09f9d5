"""Gradient-safe numerical helpers used everywhere in diffshade.

Every helper keeps both the forward value and the gradient finite for every input,
including the points where the naive expression is undefined (zero vectors, 0 ** s,
division by zero). The technique is the "double where": the unsafe operand is replaced
by a harmless value *before* the unsafe operation, and the result is selected after it,
so the discarded branch never produces inf/NaN that would leak into the gradient.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

__all__ = ["clamp01", "dot", "float_dtype", "float_dtype_of", "representable", "safe_div",
           "safe_norm", "safe_normalize", "safe_pow", "safe_sqrt", "tiny"]


def tiny(dtype) -> float:
    """A threshold well above underflow for `dtype`: 1e-12 for float32, 1e-30 for float64."""
    return 1e-30 if jnp.dtype(dtype) == jnp.float64 else 1e-12


@jax.custom_jvp
def _dot3(a, b):
    # explicit component products: XLA on CPU vectorizes this about ten times better than
    # a reduction over a minor axis of size 3
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


@functools.partial(_dot3.defjvp, symbolic_zeros=True)
def _dot3_jvp(primals, tangents):
    # the tangent is written as a reduction so that its transpose (reverse mode) is a
    # broadcast, not the slice -> pad -> add chain the component form would transpose to;
    # a constant operand (a symbolic zero tangent) adds no term
    (a, b), (da, db) = primals, tangents
    product = _add_known(None if _zero(da) else da * b, None if _zero(db) else a * db)
    return _dot3(a, b), jnp.sum(product, axis=-1)


def _zero(tangent):
    """Whether a custom_jvp rule's tangent (symbolic_zeros=True) is a symbolic zero."""
    return isinstance(tangent, SymbolicZero)


def _add_known(a, b):
    """a + b, where either may be None (absent); not both."""
    return b if a is None else a if b is None else a + b


def dot(a, b, keepdims=False):
    """Dot product over the last axis of size 3: [..., 3] x [..., 3] -> [...] (or [..., 1]).

    The operands broadcast against each other inside the product only: a direction
    shared by every sample ([3]) stays one vector, and reverse mode keeps no copy of it
    per sample."""
    out = _dot3(a, b)
    return out[..., None] if keepdims else out


def safe_sqrt(x):
    """sqrt(x) for x > tiny, 0 otherwise, with a finite gradient everywhere. x: [...] float."""
    ok = x > tiny(x.dtype)
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), 0.0)


def safe_norm(v, keepdims=False):
    """Euclidean norm of v: [..., 3] float, finite gradient at v = 0 (where it returns 0).

    The cut-off is |v| <= tiny, as in safe_normalize: a threshold on the squared norm
    (safe_sqrt's) would zero every vector shorter than sqrt(tiny), e.g. 1e-6 in float32,
    and so the edges' cross products, face areas and vertex normals of a small mesh.
    """
    sq = dot(v, v, keepdims)
    ok = sq > tiny(v.dtype) ** 2
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)


def _inverse_norm(v):
    """1 / |v| [..., 1] for v: [..., 3] float; 0 where |v| <= tiny."""
    sq = dot(v, v, keepdims=True)
    ok = sq > tiny(v.dtype) ** 2
    return jnp.where(ok, 1.0 / jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)


@jax.custom_jvp
def _unit(v):
    return v * _inverse_norm(v)


@_unit.defjvp
def _unit_jvp(primals, tangents):
    # d(v/|v|) = (dv - u (u.dv)) / |v|, u = v/|v|: reverse mode keeps u and 1/|v| only
    # (autodiff of the expression keeps its masks, squares and quotients too); 1/|v| = 0
    # where |v| <= tiny, so the tangent is 0 there
    (v,), (dv,) = primals, tangents
    inverse = _inverse_norm(v)
    unit = v * inverse
    # u.dv as a reduction: its transpose reads u whole, not u's three components apart
    return unit, inverse * (dv - unit * jnp.sum(unit * dv, axis=-1, keepdims=True))


def safe_normalize(v, fallback=None):
    """v / |v| for v: [..., 3] float; `fallback` (default zeros) where |v| is ~0.

    The gradient is finite everywhere; at the fallback points it is zero.
    """
    unit = _unit(v)
    if fallback is None:
        return unit
    ok = dot(v, v, keepdims=True) > tiny(v.dtype) ** 2
    return jnp.where(ok, unit, jnp.broadcast_to(fallback, v.shape).astype(v.dtype))


def safe_div(num, den, fallback=0.0):
    """num / den where |den| > tiny, `fallback` elsewhere; finite gradient everywhere."""
    ok = jnp.abs(den) > tiny(den.dtype)
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), fallback)


@jax.custom_jvp
def safe_pow(base, exponent):
    """base ** exponent for base > 0, 0 for base <= 0 (OpenGL's specular rule).

    Computed as exp(exponent * log(base)) with the base clamped away from 0 inside the
    branch that is kept, so d/dbase and d/dexponent stay finite for exponent in (0, inf),
    including exponents far below 1 (where b**(s-1) blows up at b -> 0) and above 1000.
    exponent == 0 gives 1 wherever base > 0.
    """
    return _pow_parts(base, exponent)[0]


def _pow_parts(base, exponent):
    """(base ** exponent, the clamped base, its log): safe_pow's value and what its
    derivatives reuse."""
    ok = base > tiny(base.dtype)
    safe_base = jnp.where(ok, base, 1.0)
    log_base = jnp.log(safe_base)
    return jnp.where(ok, jnp.exp(exponent * log_base), 0.0), safe_base, log_base


@functools.partial(safe_pow.defjvp, symbolic_zeros=True)
def _safe_pow_jvp(primals, tangents):
    # d(b^s) = b^s (s db / b + log(b) ds), from the power itself (0 where b <= tiny, which
    # zeroes both terms there); a constant exponent (a symbolic zero tangent) compiles no
    # log term
    (base, exponent), (d_base, d_exponent) = primals, tangents
    power, safe_base, log_base = _pow_parts(base, exponent)
    tangent = _add_known(None if _zero(d_base) else power * (exponent / safe_base) * d_base,
                         None if _zero(d_exponent) else power * log_base * d_exponent)
    return power, jnp.broadcast_to(tangent, power.shape)


@jax.custom_jvp
def clamp01(x):
    """Clip to [0, 1]; the gradient is 1 inside and 0 outside (no straight-through trick),
    1/2 at 0 and at 1 (where jnp.clip's max and min split a tie)."""
    return jnp.clip(x, 0.0, 1.0)


@clamp01.defjvp
def _clamp01_jvp(primals, tangents):
    # jnp.clip's own rule keeps the slopes of its max and of its min, two arrays shaped
    # like x, for reverse mode; this one a single factor
    (x,), (dx,) = primals, tangents
    ends = (x == 0.0) | (x == 1.0)
    slope = jnp.where(ends, 0.5, jnp.where((x > 0.0) & (x < 1.0), 1.0, 0.0))
    return clamp01(x), slope.astype(dx.dtype) * dx


def representable(values, dtype=None):
    """[...] bool: finite once stored as `dtype` (default: the default float dtype).

    Builders check their input with this rather than np.isfinite: 1e39 is finite in
    float64 but overflows float32 to inf, which no safe helper can recover from.
    """
    limit = np.finfo(float_dtype() if dtype is None else dtype).max
    return np.abs(np.asarray(values, np.float64)) <= limit  # False for NaN and inf


def float_dtype():
    """The default float dtype: float64 under `jax_enable_x64`, else float32."""
    return jnp.result_type(float)


def float_dtype_of(values):
    """The float dtype a builder stores `values` in: float32 for float32 input, else the
    default float dtype (float64 under `jax_enable_x64`, else float32) — so float64 input
    stays float64 under x64, and lists, integers and parsed text take the default."""
    return jnp.dtype(jnp.float32) if getattr(values, "dtype", None) == np.float32 else float_dtype()

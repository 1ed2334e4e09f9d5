"""The gradient-safe helpers' own derivative rules (custom JVPs), in float64.

safe_normalize, safe_pow, clamp01 and dot carry hand-written JVPs that keep fewer values
for reverse mode than autodiff of their expressions would. Each is checked against central
finite differences (jax.test_util.check_grads, forward and reverse, to second order) away
from its kinks, and against autodiff of the plain expression (the rules they replaced) at
the hard points: a zero vector, a base at or below 0, exponent 0, a clamp input exactly at
0 or 1, an operand shared by every sample.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from diffshade.numerics import clamp01, dot, safe_normalize, safe_pow, tiny

pytestmark = pytest.mark.usefixtures("x64")


def plain_normalize(v):
    sq = jnp.sum(v * v, -1, keepdims=True)
    ok = sq > tiny(v.dtype) ** 2
    return v * jnp.where(ok, 1.0 / jnp.sqrt(jnp.where(ok, sq, 1.0)), 0.0)


def plain_pow(base, exponent):
    ok = base > tiny(base.dtype)
    return jnp.where(ok, jnp.exp(exponent * jnp.log(jnp.where(ok, base, 1.0))), 0.0)


def jacobians(fn, *args):
    """Reverse- and forward-mode Jacobians of fn w.r.t. every argument."""
    argnums = tuple(range(len(args)))
    return jax.jacrev(fn, argnums)(*args), jax.jacfwd(fn, argnums)(*args)


def assert_same_jacobians(fn, reference, *args):
    for got, want in zip(jacobians(fn, *args), jacobians(reference, *args), strict=True):
        for g, w in zip(got, want, strict=True):
            np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-14)
            assert np.isfinite(g).all()


def test_safe_normalize_matches_finite_differences():
    v = jnp.array([[0.3, -1.2, 0.5], [2.0, 0.1, -0.7]])
    check_grads(safe_normalize, (v,), order=2, modes=("fwd", "rev"))


@pytest.mark.parametrize("v", [[0.0, 0.0, 0.0], [1e-40, 0.0, 0.0], [0.0, 3.0, -4.0]])
def test_safe_normalize_derivative_at_zero_and_unit_length(v):
    v = jnp.array(v)
    assert_same_jacobians(safe_normalize, plain_normalize, v)
    if not np.any(np.asarray(v)[1:]):  # |v| <= tiny: the fallback, with a zero gradient
        assert not np.any(jax.jacrev(safe_normalize)(v))


@pytest.mark.parametrize("exponent", [0.3, 1.0, 20.0, 1000.0])
def test_safe_pow_matches_finite_differences(exponent):
    base = jnp.array([0.2, 0.55, 0.93, 1.0])
    # a small step: b^1000 bends sharply
    check_grads(lambda b, s: safe_pow(b, s), (base, jnp.asarray(exponent)), order=2,
                modes=("fwd", "rev"), eps=1e-6, rtol=1e-5)


@pytest.mark.parametrize("exponent", [0.0, 0.3, 20.0])
def test_safe_pow_derivatives_at_and_below_zero_base(exponent):
    base = jnp.array([-0.5, 0.0, 1e-40, 1e-6, 0.7])
    exponent = jnp.full(base.shape, exponent)
    assert_same_jacobians(safe_pow, plain_pow, base, exponent)
    d_base, d_exponent = jax.jacrev(lambda b, s: jnp.sum(safe_pow(b, s)), (0, 1))(base, exponent)
    assert not np.any(d_base[:3]) and not np.any(d_exponent[:3])


def test_safe_pow_with_a_constant_exponent_compiles_no_log_term():
    # the spot exponent or a fixed shininess: its derivative term is not built at all
    base = jnp.array([0.4, 0.8])
    grad = jax.grad(lambda b: jnp.sum(safe_pow(b, 3.0)))
    logs = str(jax.make_jaxpr(grad)(base)).count("log ")
    assert logs == str(jax.make_jaxpr(lambda b: safe_pow(b, 3.0))(base)).count("log ")
    np.testing.assert_allclose(grad(base), 3.0 * base ** 2, rtol=1e-12)


def test_clamp01_slope_is_one_inside_zero_outside_and_half_at_the_ends():
    x = jnp.array([-0.5, 0.0, 0.25, 0.999, 1.0, 1.5])
    slope = jax.vmap(jax.grad(clamp01))(x)
    np.testing.assert_array_equal(slope, [0.0, 0.5, 1.0, 1.0, 0.5, 0.0])
    np.testing.assert_array_equal(clamp01(x), jnp.clip(x, 0.0, 1.0))
    assert_same_jacobians(clamp01, lambda y: jnp.clip(y, 0.0, 1.0), x)


def test_dot_of_a_shared_direction_with_many_samples():
    normals = jnp.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -1.0, 0.0]])
    light = jnp.array([0.3, -0.4, 0.5])
    plain = lambda n, d: jnp.sum(n * d, -1)
    assert dot(normals, light).shape == (3,) and dot(light, normals, True).shape == (3, 1)
    assert_same_jacobians(dot, plain, normals, light)
    assert_same_jacobians(dot, plain, light, normals)
    check_grads(dot, (normals, light), order=2, modes=("fwd", "rev"))

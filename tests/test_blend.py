"""blend.soft_weights / soft_alpha / soft_blend against the SoftRas formulas written
naively (products and plain exponentials, float64, at settings where they cannot
overflow), and their gradients against float64 central differences; and the same through
jit, grad, jvp and vmap (they are plain jax.numpy)."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffshade.composite.blend import (
    BACKGROUND_EPS,
    log_coverages,
    normalized_inverse_depth,
    soft_alpha,
    soft_blend,
    soft_weights,
)
from diffshade.raster.fragments import Fragments

pytestmark = pytest.mark.usefixtures("x64")

NEAR, FAR, SIGMA, GAMMA = 0.5, 20.0, 1.5, 0.05


def _frags(seed=0, shape=(3, 4, 5)):
    rng = np.random.default_rng(seed)
    ids = rng.integers(-1, 9, size=shape).astype(np.int32)
    ids[0, 0] = -1  # a pixel with no face
    depth = rng.uniform(0.6, 15.0, size=shape)
    dist = rng.normal(0.0, 2.0, size=shape)
    return Fragments(jnp.asarray(ids), jnp.zeros(shape + (3,)), jnp.asarray(depth),
                     jnp.asarray(ids >= 0), jnp.zeros((), jnp.int32), jnp.asarray(dist))


def _naive(frags, colours, background, sigma, gamma):
    """(slot weights, background weight, rgba) from the module docstring's formulas."""
    valid = np.asarray(frags.valid)
    d = 1.0 / (1.0 + np.exp(-np.asarray(frags.dist) / sigma))
    zt = np.clip((1.0 / np.asarray(frags.depth) - 1.0 / FAR) / (1.0 / NEAR - 1.0 / FAR), 0, 1)
    num = np.where(valid, d * np.exp(zt / gamma), 0.0)
    bg = np.exp(BACKGROUND_EPS / gamma)
    total = num.sum(-1) + bg
    slots, bg_weight = num / total[..., None], bg / total
    rgb = (slots[..., None] * colours).sum(-2) + bg_weight[..., None] * background
    alpha = 1.0 - np.prod(np.where(valid, 1.0 - d, 1.0), -1)
    return slots, bg_weight, np.concatenate([rgb, alpha[..., None]], -1)


def test_weights_alpha_and_blend_equal_the_naive_formulas():
    frags = _frags()
    rng = np.random.default_rng(1)
    colours, background = rng.random(frags.face_ids.shape + (3,)), rng.random(3)
    slots, bg_weight = soft_weights(frags, NEAR, FAR, SIGMA, GAMMA)
    want_slots, want_bg, want_rgba = _naive(frags, colours, background, SIGMA, GAMMA)
    np.testing.assert_allclose(np.asarray(slots), want_slots, rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(np.asarray(bg_weight), want_bg, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(soft_alpha(frags, SIGMA)), want_rgba[..., 3],
                               rtol=1e-12, atol=1e-15)
    rgba = jax.jit(soft_blend)(jnp.asarray(colours), frags, jnp.asarray(background), NEAR, FAR,
                               SIGMA, GAMMA)
    np.testing.assert_allclose(np.asarray(rgba), want_rgba, rtol=1e-12, atol=1e-15)
    # the empty pixel shows the background alone
    np.testing.assert_allclose(np.asarray(rgba)[0, 0], np.append(background, 0.0), atol=1e-15)


def _loss(dist, depth, colours, sigma, gamma, frags, weights):
    moved = dataclasses.replace(frags, dist=dist, depth=depth)
    rgba = soft_blend(colours, moved, jnp.array([0.2, 0.3, 0.4]), NEAR, FAR, sigma, gamma)
    return jnp.sum(weights * rgba)


def test_gradients_equal_central_differences():
    frags = _frags(2)
    rng = np.random.default_rng(3)
    colours = jnp.asarray(rng.random(frags.face_ids.shape + (3,)))
    weights = jnp.asarray(rng.normal(size=frags.face_ids.shape[:2] + (4,)))
    args = (frags.dist, frags.depth, colours, jnp.asarray(SIGMA), jnp.asarray(GAMMA))
    loss = lambda *a: _loss(*a, frags, weights)
    grads = jax.jit(jax.grad(loss, argnums=tuple(range(5))))(*args)
    h = 1e-6
    for seed in range(3):
        directions = [jnp.asarray(np.random.default_rng(10 + seed).normal(size=np.shape(a)))
                      for a in args]
        plus = loss(*[a + h * v for a, v in zip(args, directions, strict=True)])
        minus = loss(*[a - h * v for a, v in zip(args, directions, strict=True)])
        numeric = (plus - minus) / (2 * h)
        analytic = sum(jnp.sum(g * v) for g, v in zip(grads, directions, strict=True))
        np.testing.assert_allclose(float(analytic), float(numeric), rtol=1e-7, atol=1e-9)
    # forward mode agrees with reverse mode
    tangent = tuple(jnp.ones_like(a) for a in args)
    _, jvp = jax.jvp(loss, args, tangent)
    np.testing.assert_allclose(float(jvp), float(sum(jnp.sum(g) for g in grads)), rtol=1e-12)


def test_vmap_equals_a_loop():
    frags = [_frags(seed) for seed in (4, 5)]
    stacked = jax.tree.map(lambda *a: jnp.stack(a), *frags)
    got = jax.vmap(lambda f: soft_weights(f, NEAR, FAR, SIGMA, GAMMA))(stacked)
    for i, one in enumerate(frags):
        want = soft_weights(one, NEAR, FAR, SIGMA, GAMMA)
        for g, w in zip(got, want, strict=True):
            np.testing.assert_allclose(np.asarray(g[i]), np.asarray(w), rtol=1e-14)


def test_float32_log_coverages_match_float64_log_sigmoid():
    """log D and log(1 - D) in float32 (log(1 + exp(-|x|)), not log1p) are within 2.5e-7
    of float64's log_sigmoid(+-x), from deep inside to far outside a face, and so are
    their derivatives."""
    x = np.concatenate([-np.logspace(-8, 4, 200), [0.0], np.logspace(-8, 4, 200)])
    frags = Fragments(*(None,) * 5, dist=jnp.asarray(x, jnp.float32))
    log_d, log_clear = log_coverages(frags, 1.0)
    assert log_d.dtype == jnp.float32
    want = jax.nn.log_sigmoid(jnp.asarray(np.float32(x), jnp.float64))
    np.testing.assert_allclose(np.asarray(log_d, np.float64), want, rtol=1e-6, atol=2.5e-7)
    np.testing.assert_allclose(np.asarray(log_clear, np.float64),
                               jax.nn.log_sigmoid(-jnp.asarray(np.float32(x), jnp.float64)),
                               rtol=1e-6, atol=2.5e-7)
    # the derivatives, x = 0 (the kink of min(+-x, 0) and |x|) included
    x32 = jnp.asarray(x, jnp.float32)
    for out, sign in ((0, 1.0), (1, -1.0)):
        grad = jax.vmap(jax.grad(lambda d, out=out: log_coverages(
            dataclasses.replace(frags, dist=d), 1.0)[out]))(x32)
        np.testing.assert_allclose(np.asarray(grad, np.float64),
                                   sign * jax.nn.sigmoid(-sign * jnp.asarray(x32, jnp.float64)),
                                   rtol=1e-6, atol=2.5e-7)


@pytest.mark.parametrize("near", [1e-20, 1e-30])
def test_zt_derivative_for_a_tiny_near_plane_is_finite_in_float32(near):
    """zt's derivative with respect to near against its closed form, float32 operands
    (the module runs with x64 on; float32 arrays stay float32): written with 1 / near, its
    derivative -1 / near^2 overflowed float32 below ~1e-19, a NaN gradient."""
    depth = jnp.array([0.5, 3.0, 50.0], jnp.float32)
    grad = jax.grad(lambda n: jnp.sum(normalized_inverse_depth(depth, n, jnp.float32(100.0))))(
        jnp.float32(near))
    assert grad.dtype == jnp.float32
    # d/dn [n (f - z) / (z (f - n))] = (f - z) f / (z (f - n)^2)
    z, f = np.asarray(depth, np.float64), 100.0
    want = np.sum((f - z) * f / (z * (f - near) ** 2))
    assert np.isfinite(float(grad)) and np.isclose(float(grad), want, rtol=1e-5), (grad, want)

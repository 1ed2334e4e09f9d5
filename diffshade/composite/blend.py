"""blend: per-fragment colours -> an RGBA image over a background colour.

Hard mode keeps the nearest fragment: alpha = coverage in {0, 1} and
rgb = alpha * colour + (1 - alpha) * background.

Soft mode is SoftRas aggregation (Liu et al., ICCV 2019). For the K candidates of a pixel,
with d2 the signed squared distance in pixels^2 (positive inside):
    D_k = sigmoid(d2_k / sigma)                    (coverage; sigma in pixels^2)
    w_k = D_k exp(zt_k / gamma) / (sum_j D_j exp(zt_j / gamma) + exp(eps / gamma))
    rgb = sum_k w_k c_k + w_bg * background,       w_bg = exp(eps / gamma) / (...)
    alpha = 1 - prod_k (1 - D_k)
zt = (1/z - 1/far) / (1/near - 1/far) is the normalized inverse depth (1 at the near plane,
0 at the far plane). Everything is computed in log space: log D = log_sigmoid(d2 / sigma),
the weights are a softmax (which subtracts the per-pixel maximum), and
log(1 - D) = log_sigmoid(-d2 / sigma); so tiny sigma and gamma cannot overflow.
"""

import jax
import jax.numpy as jnp

from diffshade.numerics import safe_div

BACKGROUND_EPS = 1e-3


def hard_blend(colours, frags, background):
    """colours: [H, W, K, 3]; background: [3] -> [H, W, 4] RGBA from the nearest slot."""
    alpha = frags.valid[..., 0, None].astype(colours.dtype)
    rgb = alpha * colours[..., 0, :] + (1.0 - alpha) * background
    return jnp.concatenate([rgb, alpha], axis=-1)


def normalized_inverse_depth(depth, near, far):
    """zt in [0, 1] (1 = near plane) of eye-space depth: [...] -> [...].
    (1/z - 1/far) / (1/near - 1/far), written (1/z - 1/far) near far / (far - near): the
    same number, but with no 1/near, whose derivative -1/near^2 overflows float32 for a
    near plane below ~1e-19 (a NaN gradient with respect to near); the per-element work
    is as before (a reciprocal, a subtraction, a product by a scalar)."""
    inv = safe_div(jnp.ones_like(depth), depth)
    return jnp.clip((inv - 1.0 / far) * (near * far / (far - near)), 0.0, 1.0)


def log_coverages(frags, sigma):
    """(log D, log(1 - D)) [H, W, K] of every slot (module docstring; the slots must then
    be masked with frags.valid). Both are jax.nn.log_sigmoid written out,
    log_sigmoid(+-x) = min(+-x, 0) - log(1 + exp(-|x|)), so that under one jit XLA computes
    the shared exp and log once for the weights and the alpha. log(1 + e) rather than
    log1p(e): e = exp(-|x|) is in (0, 1], so 1 + e loses at most half an ulp of 1 (an
    absolute error below 1.2e-7 in float32 on a log-probability, a relative one on D), and
    XLA on CPU vectorizes log but evaluates log1p as a slower series with branches (the
    costliest loop of the blend weights). |x| is written max(x, -x): at x = 0 its
    derivative is then 0 (JAX splits a tie between the two), with min(+-x, 0)'s +-1/2 the
    exact sigmoid(-+x) = +-1/2; jnp.abs's derivative there is 1, which made log D's
    derivative 1 instead of 1/2 on a pixel exactly on an edge."""
    x = frags.dist / sigma
    tail = jnp.log(1.0 + jnp.exp(-jnp.maximum(x, -x)))
    return jnp.minimum(x, 0.0) - tail, jnp.minimum(-x, 0.0) - tail


def soft_weights(frags, near, far, sigma, gamma):
    """The aggregation weights of soft_blend: (per slot [H, W, K], the background's
    [H, W]), a softmax of the logits log D_k + zt_k / gamma and the background's
    (module docstring). The background's logit is kept apart rather than concatenated to
    the K others, and the two parts are returned apart: under jit(grad), XLA on CPU runs
    the concatenation, and the slicing of its derivative, as index arithmetic per element
    in every fusion that reads the [H, W, K + 1] array, forward and backward
    (docs/soft-rasterization.md, "How it works")."""
    zt = normalized_inverse_depth(frags.depth, near, far)
    logits = jnp.where(frags.valid, log_coverages(frags, sigma)[0] + zt / gamma, -jnp.inf)
    bg = jnp.asarray(BACKGROUND_EPS / gamma, logits.dtype)
    top = jax.lax.stop_gradient(jnp.maximum(jnp.max(logits, -1), bg))
    unnormalized = jnp.exp(logits - top[..., None])
    unnormalized_bg = jnp.exp(bg - top)
    total = jnp.sum(unnormalized, -1) + unnormalized_bg
    return unnormalized / total[..., None], unnormalized_bg / total


def soft_alpha(frags, sigma):
    """alpha = 1 - prod_k (1 - D_k) [H, W] of soft_blend, in log space (module
    docstring)."""
    log_clear = jnp.sum(jnp.where(frags.valid, log_coverages(frags, sigma)[1], 0.0), -1)
    return 1.0 - jnp.exp(log_clear)


def soft_blend(colours, frags, background, near, far, sigma, gamma, weights=None,
               summed=None):
    """colours: [H, W, K, 3]; background: [3]; sigma (pixels^2), gamma: scalars
    -> [H, W, 4] RGBA by SoftRas aggregation (module docstring). The colours of fragments
    whose weight is exactly 0 do not matter (render may leave them 0). weights: the
    soft_weights, when the caller has them already. summed: sum_k w_k c_k [H, W, 3], when
    the caller has it (colours are then not read)."""
    slots, bg_weight = soft_weights(frags, near, far, sigma, gamma) if weights is None \
        else weights
    if summed is None:
        summed = jnp.sum(slots[..., None] * colours, -2)
    rgb = summed + bg_weight[..., None] * background
    return jnp.concatenate([rgb, soft_alpha(frags, sigma)[..., None]], axis=-1)

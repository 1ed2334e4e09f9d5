"""Transparency: I = (1 - kt) I_refl + kt I_trans, composited over the K fragment layers.

Only scenes whose material (or back material) has a `kt` come here; an opaque scene
compiles none of it (render.py asks `layers_needed`). docs/transparency.md derives both
modes; in short, with layers nearest first, c_k the lit colour and kt_k the transmittance
(RGB) of layer k:

- hard: front-to-back compositing over the layers of the pixel,
      rgb = sum_k T_k (1 - kt_k) c_k + T_K background,   T_0 = 1, T_{k+1} = T_k kt_k,
  so the nearest opaque layer (kt = 0) ends it. alpha = 1 - mean_rgb(T_K) (opacity).
- soft: SoftRas aggregation applied recursively. What lies behind layer k is the SoftRas
  blend B_k of the layers behind it (by more than BEHIND_MARGIN times the blend's own
  depth scale gamma) and the background; layer k shows
  (1 - kt_k) c_k + kt_k B_k, and the pixel is the SoftRas blend of those over all layers.
  Computed from the farthest layer forward, every blend a softmax of logits, so tiny
  gamma cannot overflow. kt = 0 gives soft_blend exactly (to rounding).
  alpha = 1 - prod_k (1 - D_k (1 - mean_rgb(kt_k))).
Layers beyond K are dropped (Fragments.dropped counts them): what they would have shown
is replaced by the background.
"""

import functools

import jax
import jax.numpy as jnp

from diffshade.composite.blend import BACKGROUND_EPS, normalized_inverse_depth
from diffshade.shading.samples import object_ids


def _materials(scene):
    front = [scene.material]
    return front + ([scene.back_material] if scene.two_sided and scene.back_material else [])


def is_transparent(scene) -> bool:
    """Whether any material the scene renders with has a kt (a static, structural fact)."""
    return any(m.kt is not None for m in _materials(scene))


def layers_needed(scene, settings) -> int:
    """Fragment slots per pixel for hard raster: 1 (z-buffer) for an opaque scene, else
    settings.faces_per_pixel layers to composite."""
    return settings.faces_per_pixel if is_transparent(scene) else 1


def fragment_kt(scene, frags):
    """[H, W, K, 3] transmittance of each fragment (the back material's on back faces under
    two-sided lighting; 0 for a material without kt), or None for an opaque scene. In a
    scene of several objects (materials stacked [O, ...]) each fragment takes its
    object's kt."""
    if not is_transparent(scene):
        return None
    shape = frags.face_ids.shape + (3,)
    dtype = frags.bary.dtype
    ids = object_ids(scene, True, frags.face_ids)

    def of(mat):
        if mat.kt is None:
            return jnp.zeros(shape, dtype)
        kt = mat.kt if ids is None else jnp.take(mat.kt, ids, axis=0, mode="clip")
        return jnp.broadcast_to(kt, shape).astype(dtype)
    mats = _materials(scene)
    if len(mats) == 1:
        return of(mats[0])
    return jnp.where(frags.front[..., None], of(mats[0]), of(mats[1]))


def layer_weights(kt, valid):
    """Hard compositing's weights: kt [..., K, 3] (layers nearest first), valid [..., K]
    bool -> (T_k (1 - kt_k) [..., K, 3] per valid layer, T_K [..., 3]); the colour is
    sum_k weights_k c_k + T_K background. Shared with the fitting cache."""
    transmit = jnp.ones(kt.shape[:-2] + (3,), kt.dtype)
    weights = []
    for k in range(kt.shape[-2]):
        opacity = jnp.where(valid[..., k, None], 1.0 - kt[..., k, :], 0.0)
        weights.append(transmit * opacity)
        transmit = transmit * (1.0 - opacity)
    return jnp.stack(weights, -2), transmit


def hard_composite(colours, kt, frags, background):
    """colours, kt: [H, W, K, 3] (layers nearest first); background: [3] -> [H, W, 4]."""
    weights, transmit = layer_weights(kt, frags.valid)
    rgb = jnp.sum(weights * colours, -2) + transmit * background
    return jnp.concatenate([rgb, 1.0 - jnp.mean(transmit, -1, keepdims=True)], -1)


def _by_depth(frags, *per_slot):
    """per_slot arrays [H, W, K, ...] reordered nearest first (empty slots last)."""
    key = jnp.where(frags.valid, frags.depth, jnp.inf)
    order = jax.lax.stop_gradient(jnp.argsort(key, axis=-1))

    def take(a):
        idx = order.reshape(order.shape + (1,) * (a.ndim - order.ndim))
        return jnp.take_along_axis(a, idx, axis=order.ndim - 1)
    return [take(a) for a in per_slot]


#: a layer is behind another where its normalized inverse depth is lower by more than
#: BEHIND_MARGIN * gamma: layers closer than that are one surface (SoftRas blends them as
#: peers, e.g. the two faces at a shared edge), not one seen through the other. A hard
#: test: a soft one would leave the peers, the nearest layers, the largest blend weight.
BEHIND_MARGIN = 4.0


def soft_composite(colours, kt, frags, background, near, far, sigma, gamma):
    """colours, kt: [H, W, K, 3]; background: [3]; sigma (pixels^2), gamma: scalars ->
    [H, W, 4] RGBA, the recursive SoftRas aggregation of the module docstring."""
    zt = normalized_inverse_depth(frags.depth, near, far)
    logits = jnp.where(frags.valid, jax.nn.log_sigmoid(frags.dist / sigma) + zt / gamma,
                       -jnp.inf)
    cover = jnp.where(frags.valid, jax.nn.sigmoid(frags.dist / sigma), 0.0)
    colours, kt, logits, cover, zt = _by_depth(frags, colours, kt, logits, cover, zt)
    bg_logit = jnp.full(logits.shape[:-1] + (1,), BACKGROUND_EPS / gamma, logits.dtype)
    background = jnp.broadcast_to(background, colours.shape[:-2] + (3,)).astype(colours.dtype)
    k_slots = colours.shape[-2]
    shown = [None] * k_slots
    for k in reversed(range(k_slots)):
        behind = _blend_behind(k, logits, zt, gamma, shown, bg_logit, background)
        shown[k] = (1.0 - kt[..., k, :]) * colours[..., k, :] + kt[..., k, :] * behind
    layers = jnp.stack(shown, -2)
    weights = jax.nn.softmax(jnp.concatenate([logits, bg_logit], -1), axis=-1)
    rgb = jnp.sum(weights[..., :-1, None] * layers, -2) + weights[..., -1:] * background
    opacity = cover * (1.0 - jnp.mean(kt, -1))
    clear = functools.reduce(lambda acc, k: acc * (1.0 - opacity[..., k]), range(k_slots),
                             jnp.ones(opacity.shape[:-1], opacity.dtype))
    return jnp.concatenate([rgb, 1.0 - clear[..., None]], -1)


def _blend_behind(k, logits, zt, gamma, shown, bg_logit, background):
    """B_k: the SoftRas blend of the layers behind layer k (by more than BEHIND_MARGIN
    gamma) and the background: [H, W, 3]."""
    later = logits[..., k + 1:]
    if later.shape[-1] == 0:
        return background
    gap = jax.lax.stop_gradient(zt[..., k, None] - zt[..., k + 1:])
    later = jnp.where(gap > BEHIND_MARGIN * gamma, later, -jnp.inf)
    weights = jax.nn.softmax(jnp.concatenate([later, bg_logit], -1), axis=-1)
    rgb = weights[..., -1:] * background
    for j in range(k + 1, logits.shape[-1]):
        rgb = rgb + weights[..., j - k - 1, None] * shown[j]
    return rgb

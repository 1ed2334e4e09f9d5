"""interpolate: vertex or face attributes -> per-fragment values.

Vertex attributes are blended with the fragments' perspective-correct barycentrics; face
attributes are gathered by face id. Empty slots (face id -1) get zeros.
"""

import jax.numpy as jnp


def interpolate(attrs, faces, frags):
    """attrs: [V, C] vertex attributes; faces: [F, 3] -> [H, W, K, C]."""
    corner = jnp.take(attrs, jnp.take(faces, jnp.maximum(frags.face_ids, 0), axis=0), axis=0)
    bary = frags.bary[..., None]
    # explicit sum over the 3 corners: see numerics.dot for why
    values = (bary[..., 0, :] * corner[..., 0, :] + bary[..., 1, :] * corner[..., 1, :]
              + bary[..., 2, :] * corner[..., 2, :])
    return jnp.where(frags.valid[..., None], values, 0.0)


def gather_faces(face_attrs, frags):
    """face_attrs: [F, C] -> [H, W, K, C]."""
    values = jnp.take(face_attrs, jnp.maximum(frags.face_ids, 0), axis=0)
    return jnp.where(frags.valid[..., None], values, 0.0)

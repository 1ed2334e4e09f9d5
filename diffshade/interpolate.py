"""interpolate: vertex or face attributes -> per-fragment values.

Vertex attributes are blended with the fragments' perspective-correct barycentrics; face
attributes are gathered by face id. Empty slots (face id -1) get zeros.

The blend of vertex attributes is a `jax.custom_vjp` op with compiled forward and backward
kernels (fragment_kernels.py): its backward is a scatter-add into the faces' corners, which
XLA on CPU runs serially and slowly. JAX differentiates the gather of vertex attributes to
face corners ([F, 3, C], small) around it.
"""

import jax
import jax.numpy as jnp
import numpy as np

from diffshade import fragment_kernels as kernels
from diffshade.hostcall import host_call


@jax.custom_vjp
def interpolate_corners(ids, bary, corners):
    """sum_i bary_i * corners[face, i] per fragment: ids [H, W, K] int (-1 = empty),
    bary [H, W, K, 3], corners [F, 3, C] -> [H, W, K, C] (zeros in empty slots)."""
    shape = jax.ShapeDtypeStruct(ids.shape + corners.shape[-1:], corners.dtype)

    def host(ids, bary, corners):
        k = ids.shape[-1]
        return (kernels.interpolate_forward(ids.reshape(-1, k), bary.reshape(-1, k, 3),
                                            corners, kernels.chunks()),)
    return host_call(host, (shape,), ids, bary.astype(corners.dtype), corners)[0]


def _interpolate_fwd(ids, bary, corners):
    return interpolate_corners(ids, bary, corners), (ids, bary, corners)


def _interpolate_bwd(residuals, g_out):
    ids, bary, corners = residuals
    shapes = (jax.ShapeDtypeStruct(bary.shape, corners.dtype),
              jax.ShapeDtypeStruct(corners.shape, corners.dtype))

    def host(ids, bary, corners, g_out):
        k, c = ids.shape[-1], corners.shape[-1]
        return kernels.interpolate_backward(ids.reshape(-1, k), bary.reshape(-1, k, 3),
                                            corners, g_out.reshape(-1, k, c), kernels.chunks())
    g_bary, g_corners = host_call(host, shapes, ids, bary.astype(corners.dtype), corners,
                                  g_out.astype(corners.dtype))
    return None, g_bary.astype(bary.dtype), g_corners


interpolate_corners.defvjp(_interpolate_fwd, _interpolate_bwd)


def interpolate(attrs, faces, frags):
    """attrs: [V, C] vertex attributes; faces: [F, 3] -> [H, W, K, C]."""
    return interpolate_corners(frags.face_ids, frags.bary, jnp.take(attrs, faces, axis=0))


def interpolate_tree(tree, faces, frags):
    """`interpolate` every [V, C_i] leaf of a pytree in one pass over the fragments (one
    kernel call forward and one backward instead of one per leaf): [H, W, K, C_i] leaves."""
    leaves, treedef = jax.tree.flatten(tree)
    values = interpolate(jnp.concatenate(leaves, -1), faces, frags)
    splits = np.cumsum([leaf.shape[-1] for leaf in leaves])[:-1]
    return treedef.unflatten(jnp.split(values, splits, -1))


def gather_faces(face_attrs, frags):
    """face_attrs: [F, C] -> [H, W, K, C]."""
    values = jnp.take(face_attrs, jnp.maximum(frags.face_ids, 0), axis=0)
    return jnp.where(frags.valid[..., None], values, 0.0)

"""interpolate: vertex or face attributes -> per-fragment values.

Vertex attributes are blended with the fragments' perspective-correct barycentrics; face
attributes are gathered by face id. Empty slots (face id -1) get zeros.

The blend of vertex attributes is a FragmentOp (hostop.py) with compiled forward and
backward kernels (fragment_kernels.py), or the same sum in jax.numpy: its backward is a
scatter-add into the faces' corners, which XLA on CPU runs serially and slowly. JAX
differentiates the gather of vertex attributes to face corners ([F, 3, C], small) around
it.
"""

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.host import fragment_kernels as kernels
from diffshade.host.hostop import FragmentOp


def _interpolate_native(ids, bary, corners):
    """interpolate_corners in jax.numpy."""
    c = jnp.take(corners, jnp.maximum(ids, 0), axis=0)
    b = bary.astype(corners.dtype)[..., None]
    # explicit sum over the 3 corners: see numerics.dot for why
    values = b[..., 0, :] * c[..., 0, :] + b[..., 1, :] * c[..., 1, :] + b[..., 2, :] * c[..., 2, :]
    return (jnp.where((ids >= 0)[..., None], values, 0.0),)


def _interpolate_avals(ids, bary, corners):
    return (jax.ShapeDtypeStruct(ids.shape + corners.shape[-1:], corners.dtype),)


def _interpolate_forward(ids, bary, corners):
    k = ids.shape[-1]
    return (kernels.interpolate_forward(ids.reshape(-1, k), bary.reshape(-1, k, 3), corners,
                                        kernels.chunks()),)


def _interpolate_backward(ids, bary, corners, g_out):
    k, c = ids.shape[-1], corners.shape[-1]
    return kernels.interpolate_backward(ids.reshape(-1, k), bary.reshape(-1, k, 3), corners,
                                        g_out.reshape(-1, k, c), kernels.chunks())


#: sum_i bary_i * corners[face, i] per fragment: ids [H, W, K] int (-1 = empty), bary
#: [H, W, K, 3], corners [F, 3, C] (one dtype) -> ([H, W, K, C],) (zeros in empty slots).
interpolate_corners = FragmentOp("interpolate_corners", ("pixel", "face"), _interpolate_native,
                                 _interpolate_forward, _interpolate_backward, _interpolate_avals,
                                 ffi=("interpolate", ()))


def interpolate_rows(tree, table, ids, weights, host=None):
    """sum_i weights[..., i] * leaf[table[ids, i]] for every [S, C_j] leaf of a pytree, in
    one pass over the fragments: table [T, 3] int, ids [H, W, K] int (-1 = empty), weights
    [H, W, K, 3] -> [H, W, K, C_j] leaves. host as in `interpolate`."""
    host = jax.default_backend() == "cpu" if host is None else host
    corners, split = corner_values(tree, table)
    return split(interpolate_corners(ids, weights.astype(corners.dtype), corners, host=host)[0])


def corner_values(tree, table):
    """(corners [T, 3, C] of all the [S, C_j] leaves of a pytree side by side, at the rows
    of table [T, 3] int; a function that splits values [..., C] back into that pytree)."""
    leaves, treedef = jax.tree.flatten(tree)
    corners = jnp.take(jnp.concatenate(leaves, -1), table, axis=0)
    splits = np.cumsum([leaf.shape[-1] for leaf in leaves])[:-1]
    return corners, lambda values: treedef.unflatten(jnp.split(values, splits, -1))


def interpolate(attrs, faces, frags, host=None):
    """attrs: [V, C] vertex attributes; faces: [F, 3] -> [H, W, K, C]. host: run as
    compiled host kernels (default: on the CPU backend), else in jax.numpy (hostop.py)."""
    return interpolate_rows(attrs, faces, frags.face_ids, frags.bary, host)


def interpolate_tree(tree, faces, frags, host=None):
    """`interpolate` every [V, C_i] leaf of a pytree in one pass over the fragments (one
    kernel call forward and one backward instead of one per leaf): [H, W, K, C_i] leaves."""
    return interpolate_rows(tree, faces, frags.face_ids, frags.bary, host)


def gather_faces(face_attrs, frags):
    """face_attrs: [F, C] -> [H, W, K, C]."""
    values = jnp.take(face_attrs, jnp.maximum(frags.face_ids, 0), axis=0)
    return jnp.where(frags.valid[..., None], values, 0.0)

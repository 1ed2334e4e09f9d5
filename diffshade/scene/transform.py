"""Affine transforms of points and normals by a 4x4 model matrix.

Normals transform by the inverse transpose of the matrix's upper 3x3 block (then are
renormalized), so that they stay perpendicular to the surface under non-uniform scale.
That inverse is written out (cofactors over the determinant), not jnp.linalg.inv: XLA
lowers inv to a LAPACK call, whose lowering imports SciPy's linalg (a tenth of a second
or more at every start) and whose compiled program the command line's program store
cannot keep (diffshade.io.compile_cache).
Used where objects are placed in the world (diffshade.scene.objects) and where the camera
projects them (diffshade.raster.projection).
"""

import jax.numpy as jnp

from diffshade.numerics import safe_normalize


def transform_points(matrix, points):
    """Affine transform of points: matrix [4, 4], points [..., 3] -> [..., 3]."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def inverse_transpose(block):
    """The inverse transpose of a 3x3 block [3, 3]: its cofactors over its determinant."""
    rows = block[0], block[1], block[2]
    cofactors = jnp.stack([jnp.cross(rows[1], rows[2]), jnp.cross(rows[2], rows[0]),
                           jnp.cross(rows[0], rows[1])])
    return cofactors / jnp.dot(rows[0], cofactors[0])


def transform_normals(matrix, normals):
    """Normals under the inverse transpose of matrix[:3, :3], renormalized: [..., 3]."""
    inv_t = inverse_transpose(matrix[:3, :3])
    return safe_normalize(normals @ inv_t.T)

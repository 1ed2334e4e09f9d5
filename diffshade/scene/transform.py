"""Affine transforms of points and normals by a 4x4 model matrix.

Normals transform by the inverse transpose of the matrix's upper 3x3 block (then are
renormalized), so that they stay perpendicular to the surface under non-uniform scale.
Used where objects are placed in the world (diffshade.scene.objects) and where the camera
projects them (diffshade.raster.projection).
"""

import jax.numpy as jnp

from diffshade.numerics import safe_normalize


def transform_points(matrix, points):
    """Affine transform of points: matrix [4, 4], points [..., 3] -> [..., 3]."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def transform_normals(matrix, normals):
    """Normals under the inverse transpose of matrix[:3, :3], renormalized: [..., 3]."""
    inv_t = jnp.linalg.inv(matrix[:3, :3]).T
    return safe_normalize(normals @ inv_t.T)

"""project: model -> world -> eye -> clip coordinates, and world-space normals.

Vertices are transformed by the model matrix M, normals by the inverse transpose of its
upper 3x3 block (then renormalized), so that they stay perpendicular to the surface under
non-uniform scale. Clip coordinates feed the rasterizer; world positions, normals and the
eye-space depth feed interpolation and shading.
"""

import dataclasses

import jax
import jax.numpy as jnp

from diffshade.numerics import safe_normalize
from diffshade.scene.camera import projection_matrix, view_matrix


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Projected:
    """clip: [V, 4] (X, Y, Z, W); world: [V, 3]; normals: [V, 3] unit world normals;
    depth: [V] eye-space distance along the view axis (-z_eye)."""

    clip: jax.Array
    world: jax.Array
    normals: jax.Array
    depth: jax.Array


def transform_points(matrix, points):
    """Affine transform of points: matrix [4, 4], points [..., 3] -> [..., 3]."""
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def transform_normals(matrix, normals):
    """Normals under the inverse transpose of matrix[:3, :3], renormalized: [..., 3]."""
    inv_t = jnp.linalg.inv(matrix[:3, :3]).T
    return safe_normalize(normals @ inv_t.T)


def project(scene) -> Projected:
    """Project the scene's mesh: returns Projected (all arrays indexed by vertex)."""
    world = transform_points(scene.model, scene.mesh.vertices)
    normals = transform_normals(scene.model, scene.mesh.normals)
    eye = transform_points(view_matrix(scene.camera), world)
    homog = jnp.concatenate([eye, jnp.ones_like(eye[:, :1])], axis=1)
    clip = homog @ projection_matrix(scene.camera).T
    return Projected(clip=clip, world=world, normals=normals, depth=-eye[:, 2])

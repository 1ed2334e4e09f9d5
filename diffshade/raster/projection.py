"""project: model -> world -> eye -> clip coordinates, and world-space normals.

Vertices are transformed by the model matrix M, normals by the inverse transpose of its
upper 3x3 block (then renormalized), so that they stay perpendicular to the surface under
non-uniform scale. Clip coordinates feed the rasterizer; world positions, normals and the
eye-space depth feed interpolation and shading.
"""

import dataclasses

import jax
import jax.numpy as jnp

from diffshade.scene.camera import projection_matrix, view_matrix
from diffshade.scene.transform import transform_normals, transform_points


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Projected:
    """clip: [V, 4] (X, Y, Z, W); world: [V, 3]; normals: [V, 3] unit world normals;
    depth: [V] eye-space distance along the view axis (-z_eye)."""

    clip: jax.Array
    world: jax.Array
    normals: jax.Array
    depth: jax.Array


def project(scene) -> Projected:
    """Project the scene's mesh: returns Projected (all arrays indexed by vertex)."""
    world = transform_points(scene.model, scene.mesh.vertices)
    normals = transform_normals(scene.model, scene.mesh.normals)
    eye = transform_points(view_matrix(scene.camera), world)
    homog = jnp.concatenate([eye, jnp.ones_like(eye[:, :1])], axis=1)
    clip = homog @ projection_matrix(scene.camera).T
    return Projected(clip=clip, world=world, normals=normals, depth=-eye[:, 2])

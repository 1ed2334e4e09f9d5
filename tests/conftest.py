"""Shared fixtures for the renderer tests.

float64: the renderer tests compare against float64 references with tight tolerances, so
they run under `jax.enable_x64(True)`, scoped to each test by the `x64` fixture (a test
module opts in with `pytestmark = pytest.mark.usefixtures("x64")`). It is a context
manager, not a session-wide `jax.config.update`, so that it does not leak into other test
modules that expect JAX's float32 default. Scenes must be built *inside* the test (or in
a fixture that depends on `x64`), because builders take the default float dtype at call
time. A float32 test in such a module nests `with jax.enable_x64(False):` and builds its
scene inside that block.

`mesh` builds a Mesh from plain arrays in the current default float dtype with the
normals given as they are (`mesh_from_arrays` computes or renormalizes them), so that
closed-form tests see exactly the vertices and normals they wrote down.
"""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffshade.mesh import Mesh
from diffshade.numerics import float_dtype

# The command line turns JAX's persistent compilation cache on (diffshade.compile_cache).
# Tests run it in-process and in subprocesses; they must not write into the user's cache
# folder, nor switch the cache on for the rest of the session.
os.environ["DIFFSHADE_COMPILE_CACHE"] = "0"


@pytest.fixture
def x64():
    with jax.enable_x64(True):
        yield


def make_mesh(vertices, faces, normals=None):
    """Mesh with vertices [V, 3], faces [F, 3] and normals [V, 3] (default: every vertex
    gets the unit normal of the first face, right for planar meshes)."""
    verts = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int32)
    if normals is None:
        tri = verts[faces[0]]
        normals = np.broadcast_to(np.cross(tri[1] - tri[0], tri[2] - tri[0]), verts.shape)
    normals = np.asarray(normals, np.float64)
    normals = normals / np.linalg.norm(normals, axis=-1, keepdims=True)
    dt = float_dtype()
    return Mesh(jnp.asarray(verts, dt), jnp.asarray(faces), jnp.asarray(normals, dt))


@pytest.fixture
def mesh():
    """The `make_mesh` builder (see the module docstring)."""
    return make_mesh

"""rasterize: per pixel, the K nearest faces with perspective-correct barycentrics and depth.

Two stages. The search (which faces cover which pixel, nearest first) is discrete and
non-differentiable; a compiled kernel (candidates.py) runs it on the host through
`jax.pure_callback` (hostcall.py), under `jit` and `vmap`. Everything computed *from* the chosen
face ids is differentiable with respect to vertices and camera: barycentrics from 2D
homogeneous edge functions (equivalent to the lecture notes' perspective correction
b_i/w_i / sum_j b_j/w_j), the soft signed distance and the eye-space depth. The
per-fragment part is a `jax.custom_vjp` op whose forward and backward are compiled kernels
(fragment_kernels.py); JAX differentiates the per-face setup feeding it.

The returned `Fragments` is an ordinary pytree: cache it when geometry and camera are
fixed and pass it back to `render_fragments` (fitting materials then never re-rasterizes).
"""

import dataclasses
import math
from functools import partial

import jax
import jax.numpy as jnp

from diffshade import fragment_kernels as kernels
from diffshade.candidates import find_candidates
from diffshade.hostcall import host_call
from diffshade.numerics import dot, safe_div, tiny
from diffshade.project import Projected


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Fragments:
    """face_ids: [H, W, K] int32 (-1 = empty, nearest first); bary: [H, W, K, 3]
    perspective-correct barycentrics; depth: [H, W, K] eye-space depth; front: [H, W, K]
    bool, the face is counter-clockwise on screen; dropped: [] int32 covering fragments
    beyond K; dist: [H, W, K] signed squared screen distance (soft mode only)."""

    face_ids: jax.Array
    bary: jax.Array
    depth: jax.Array
    front: jax.Array
    dropped: jax.Array
    dist: jax.Array | None = None

    @property
    def valid(self):
        """[H, W, K] bool: the slot holds a face."""
        return self.face_ids >= 0


def face_edge_coefficients(clip, faces):
    """Per face, rows (v_j x v_k) of the adjugate of [X Y W]: [F, 3, 3]; and det: [F]."""
    xyw = jnp.take(clip[:, jnp.array([0, 1, 3])], faces, axis=0)
    coeffs = jnp.stack([jnp.cross(xyw[:, j], xyw[:, k]) for j, k in ((1, 2), (2, 0), (0, 1))], 1)
    return coeffs, dot(coeffs[:, 0], xyw[:, 0])


def soft_radius(settings) -> float:
    """Soft footprint radius in pixels: where sigmoid(-d^2 / sigma) falls to the threshold t,
    d^2 = sigma * ln((1 - t) / t)."""
    t = settings.soft_threshold
    return math.sqrt(settings.sigma * math.log((1.0 - t) / t))


def search_faces(clip, faces, camera, k, settings, radius_px=0.0):
    """Host-side candidate search under jit: (face_ids [H, W, k] int32, dropped [] int32)."""
    shapes = (jax.ShapeDtypeStruct((camera.height, camera.width, k), jnp.int32),
              jax.ShapeDtypeStruct((), jnp.int32))
    search = partial(find_candidates, width=camera.width, height=camera.height, k=k,
                     cull_backfaces=settings.cull_backfaces, radius_px=radius_px,
                     sigma=settings.sigma, gamma=settings.gamma,
                     perspective=camera.projection == "perspective")
    clip, near, far = jax.lax.stop_gradient((clip, camera.near, camera.far))
    return host_call(search, shapes, clip, faces, near, far)


def _screen_positions(clip, width, height):
    """Pixel coordinates (x right, y down) of the vertices: [V, 2]."""
    x = (safe_div(clip[:, 0], clip[:, 3]) + 1.0) * (width / 2.0)
    y = (1.0 - safe_div(clip[:, 1], clip[:, 3])) * (height / 2.0)
    return jnp.stack([x, y], -1)


def _flat_ids(ids):
    return ids.reshape(-1, ids.shape[-1])


def _geometry_args(corner_w, corner_z, coeffs, scr, width, height, soft):
    """The kernels' per-face and static arguments (fragment_kernels.geometry_forward)."""
    return (corner_w, corner_z, coeffs, scr, width, height, soft, tiny(coeffs.dtype),
            kernels.chunks())


@partial(jax.custom_vjp, nondiff_argnums=(5, 6, 7))
def fragment_geometry(ids, corner_w, corner_z, coeffs, scr, width, height, soft):
    """Per fragment: barycentrics [H, W, K, 3] (clamped to the triangle in soft mode), the
    interpolated depth [H, W, K] and the signed squared distance in pixels^2 to the
    triangle's boundary [H, W, K] (soft; zeros in hard mode), from per-face inputs:
    corner_w [F, 3] clip W and corner_z [F, 3] eye-space depth of the corners, coeffs
    [F, 3, 3] edge coefficients (face_edge_coefficients), scr [F, 3, 2] corner pixel
    positions. Forward and backward are compiled kernels (fragment_kernels.py); JAX
    differentiates the per-face inputs."""
    dtype = coeffs.dtype
    shapes = (jax.ShapeDtypeStruct(ids.shape + (3,), dtype), jax.ShapeDtypeStruct(ids.shape, dtype),
              jax.ShapeDtypeStruct(ids.shape, dtype))

    def host(ids, *per_face):
        return kernels.geometry_forward(_flat_ids(ids),
                                        *_geometry_args(*per_face, width, height, soft))
    return host_call(host, shapes, ids, corner_w, corner_z, coeffs, scr)


def _geometry_fwd(ids, corner_w, corner_z, coeffs, scr, width, height, soft):
    out = fragment_geometry(ids, corner_w, corner_z, coeffs, scr, width, height, soft)
    return out, (ids, corner_w, corner_z, coeffs, scr)


def _geometry_bwd(width, height, soft, residuals, cotangents):
    ids, *per_face = residuals
    shapes = tuple(jax.ShapeDtypeStruct(a.shape, a.dtype) for a in per_face)

    def host(ids, corner_w, corner_z, coeffs, scr, g_bary, g_depth, g_dist):
        k = ids.shape[-1]
        args = _geometry_args(corner_w, corner_z, coeffs, scr, width, height, soft)
        return kernels.geometry_backward(_flat_ids(ids), *args, g_bary.reshape(-1, k, 3),
                                         g_depth.reshape(-1, k), g_dist.reshape(-1, k))
    return (None,) + host_call(host, shapes, ids, *per_face, *cotangents)


fragment_geometry.defvjp(_geometry_fwd, _geometry_bwd)


def fragments_from_ids(proj: Projected, faces, face_ids, dropped, soft=False) -> Fragments:
    """Differentiable fragment geometry of the chosen faces (see module docstring).

    soft=True: barycentrics of pixels outside a triangle are clamped to it in screen space
    (negative ones set to 0, renormalized), then corrected for perspective, and the signed
    squared distance `dist` is computed. (Clamping the perspective-correct barycentrics
    instead goes wrong where the pixel's ray meets the triangle's plane behind the eye:
    they all flip sign there.)
    """
    height, width, _ = face_ids.shape
    valid = face_ids >= 0
    ids = jnp.maximum(face_ids, 0)
    coeffs, det = face_edge_coefficients(proj.clip, faces)
    corner_w = jnp.take(proj.clip[:, 3], faces)
    corner_z = jnp.take(proj.depth, faces)
    scr = jnp.take(_screen_positions(proj.clip, width, height), faces, axis=0)
    bary, depth, dist = fragment_geometry(face_ids, corner_w, corner_z, coeffs, scr, width,
                                          height, soft)
    return Fragments(face_ids, bary, depth, valid & (jnp.take(det, ids) > 0), dropped,
                     dist if soft else None)


def rasterize(proj: Projected, faces, camera, settings) -> Fragments:
    """Hard mode: the nearest covering face per pixel (K = 1, z-buffer). Soft mode: up to
    settings.faces_per_pixel faces whose soft footprint reaches the pixel, ranked by their
    weight in the soft blend (candidates.find_candidates)."""
    if settings.raster == "soft":
        k, radius = settings.faces_per_pixel, soft_radius(settings)
    else:
        k, radius = 1, 0.0
    face_ids, dropped = search_faces(proj.clip, faces, camera, k, settings, radius)
    return fragments_from_ids(proj, faces, face_ids, dropped, soft=settings.raster == "soft")

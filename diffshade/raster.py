"""rasterize: per pixel, the K nearest faces with perspective-correct barycentrics and depth.

Two stages. The search (which faces cover which pixel, nearest first) is discrete and
non-differentiable; it runs in numpy on the host through `jax.pure_callback`
(candidates.py) and works under `jit` and `vmap`. Everything computed *from* the chosen
face ids is plain JAX and differentiable with respect to vertices and camera:
barycentrics from 2D homogeneous edge functions (equivalent to the lecture notes'
perspective correction b_i/w_i / sum_j b_j/w_j) and the eye-space depth.

The returned `Fragments` is an ordinary pytree: cache it when geometry and camera are
fixed and pass it back to `render_fragments` (fitting materials then never re-rasterizes).
"""

import dataclasses
import math
from functools import partial

import jax
import jax.numpy as jnp

from diffshade.camera import pixel_centers_ndc
from diffshade.candidates import find_candidates
from diffshade.numerics import dot, safe_div
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
    operands = jax.lax.stop_gradient((clip, camera.near, camera.far))
    return jax.pure_callback(search, shapes, operands[0], faces, operands[1], operands[2],
                             vmap_method="sequential")


def _screen_positions(clip, width, height):
    """Pixel coordinates (x right, y down) of the vertices: [V, 2]."""
    x = (safe_div(clip[:, 0], clip[:, 3]) + 1.0) * (width / 2.0)
    y = (1.0 - safe_div(clip[:, 1], clip[:, 3])) * (height / 2.0)
    return jnp.stack([x, y], -1)


def _segment_dist2(p, a, b):
    """Squared distance from points p to segments ab: [..., 2] -> [...]."""
    edge, rel = b - a, p - a
    len2 = edge[..., 0] ** 2 + edge[..., 1] ** 2
    t = jnp.clip(safe_div(rel[..., 0] * edge[..., 0] + rel[..., 1] * edge[..., 1], len2), 0, 1)
    d = rel - t[..., None] * edge
    return d[..., 0] ** 2 + d[..., 1] ** 2


def signed_dist2(clip, faces, ids, inside, width, height):
    """SoftRas's signed squared distance (pixels^2) from each pixel centre to its candidate
    triangle's boundary, positive inside: [H, W, K]."""
    scr = jnp.take(_screen_positions(clip, width, height), jnp.take(faces, ids, axis=0), axis=0)
    ys, xs = jnp.meshgrid(jnp.arange(height) + 0.5, jnp.arange(width) + 0.5, indexing="ij")
    p = jnp.stack([xs, ys], -1).astype(clip.dtype)[:, :, None, :]
    d01 = _segment_dist2(p, scr[..., 0, :], scr[..., 1, :])
    d12 = _segment_dist2(p, scr[..., 1, :], scr[..., 2, :])
    d20 = _segment_dist2(p, scr[..., 2, :], scr[..., 0, :])
    # where, not jnp.minimum: under jit(grad) XLA may recompute an operand with other
    # rounding, and jax 0.10's min rule (bitwise operand == result) then drops its gradient
    d2 = _pick_min(_pick_min(d01, d12), d20)
    return jnp.where(inside, d2, -d2)


def _pick_min(a, b):
    return jnp.where(a <= b, a, b)


def _clamped_bary(edge, w):
    """Soft mode's barycentrics: clamp to the triangle in *screen* space, then correct for
    perspective. edge: [..., 3] homogeneous edge functions; w: [..., 3] vertex clip W.

    Screen-space barycentrics are proportional to edge_i * w_i; clamping the
    perspective-correct ones instead goes wrong where the pixel's ray meets the triangle's
    plane behind the eye (they all flip sign there). Returns (bary [..., 3], inside [...]).
    """
    screen = edge * w
    screen = safe_div(screen, (screen[..., 0] + screen[..., 1] + screen[..., 2])[..., None])
    inside = jnp.all(screen >= 0, -1)
    screen = jnp.maximum(screen, 0.0)
    persp = safe_div(screen, w)
    return safe_div(persp, (persp[..., 0] + persp[..., 1] + persp[..., 2])[..., None]), inside


def fragments_from_ids(proj: Projected, faces, face_ids, dropped, soft=False) -> Fragments:
    """Differentiable fragment geometry of the chosen faces (see module docstring).

    soft=True: barycentrics of pixels outside a triangle are clamped to it (negative ones
    set to 0, renormalized) and the signed squared distance `dist` is computed.
    """
    height, width, _ = face_ids.shape
    valid = face_ids >= 0
    ids = jnp.maximum(face_ids, 0)
    coeffs, det = face_edge_coefficients(proj.clip, faces)
    ndc = pixel_centers_ndc(width, height, proj.clip.dtype)
    p = jnp.concatenate([ndc, jnp.ones_like(ndc[..., :1])], -1)[:, :, None, None, :]
    edge = dot(jnp.take(coeffs, ids, axis=0), p)
    bary = safe_div(edge, (edge[..., 0] + edge[..., 1] + edge[..., 2])[..., None])
    dist = None
    if soft:
        bary, inside = _clamped_bary(edge, jnp.take(proj.clip[:, 3], jnp.take(faces, ids, axis=0)))
        dist = jnp.where(valid, signed_dist2(proj.clip, faces, ids, inside, width, height), 0.0)
    bary = jnp.where(valid[..., None], bary, 0.0)
    depth = dot(bary, jnp.take(proj.depth, jnp.take(faces, ids, axis=0), axis=0))
    return Fragments(face_ids, bary, depth, valid & (jnp.take(det, ids) > 0), dropped, dist)


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

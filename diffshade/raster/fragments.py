"""rasterize: per pixel, the K nearest faces with perspective-correct barycentrics and depth.

Two stages. The search (which faces cover which pixel, nearest first) is discrete and
non-differentiable: diffshade.raster.search. Everything computed *from* the chosen face ids is
differentiable with respect to vertices and camera: barycentrics from 2D homogeneous edge
functions (equivalent to the lecture notes' perspective correction b_i/w_i / sum_j
b_j/w_j), the soft signed distance and the eye-space depth. The per-fragment part is a
FragmentOp (hostop.py): compiled forward and backward kernels (fragment_kernels.py) with
every JAX transform rule, or the same arithmetic in jax.numpy (`_geometry_native`); JAX
differentiates the per-face setup feeding it.

The returned `Fragments` is an ordinary pytree: cache it when geometry and camera are
fixed and pass it back to `render_fragments` (fitting materials then never re-rasterizes).
"""

import dataclasses

import jax
import jax.numpy as jnp

from diffshade.host import fragment_kernels as kernels
from diffshade.host.hostop import FragmentOp
from diffshade.numerics import dot, safe_div, tiny
from diffshade.raster.projection import Projected
from diffshade.raster.search import search_depth, search_faces


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


def _screen_positions(clip, width, height):
    """Pixel coordinates (x right, y down) of the vertices: [V, 2]."""
    x = (safe_div(clip[:, 0], clip[:, 3]) + 1.0) * (width / 2.0)
    y = (1.0 - safe_div(clip[:, 1], clip[:, 3])) * (height / 2.0)
    return jnp.stack([x, y], -1)


def _pixel_grid(height, width, dtype, count=None):
    """Per pixel [R, W, 1]: NDC x, NDC y and pixel-centre coordinates px, py, for R = count
    rows (default: height) of B = R / height images of height rows stacked (a batch folded
    into one call, hostop.py): row r is row r mod height of its image."""
    count = height if count is None else count
    rows = jnp.arange(count) if count == height else jnp.arange(count) % height
    rows = rows.astype(dtype)[:, None, None]
    cols = jnp.arange(width, dtype=dtype)[None, :, None]
    x = jnp.broadcast_to((2.0 * cols + 1.0) / width - 1.0, (count, width, 1))
    y = jnp.broadcast_to(1.0 - (2.0 * rows + 1.0) / height, (count, width, 1))
    return x, y, jnp.broadcast_to(cols + 0.5, x.shape), jnp.broadcast_to(rows + 0.5, x.shape)


def _normalized(v):
    """v / sum(v) over the last axis of 3 (0 where the sum is ~0)."""
    return safe_div(v, (v[..., 0] + v[..., 1] + v[..., 2])[..., None])


def _segment_dist2(px, py, a, b):
    """Squared distance from (px, py) [...] to the segments ab ([..., 2] each): [...]."""
    ex, ey = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    rx, ry = px - a[..., 0], py - a[..., 1]
    t = jnp.clip(safe_div(rx * ex + ry * ey, ex * ex + ey * ey), 0.0, 1.0)
    dx, dy = rx - t * ex, ry - t * ey
    return dx * dx + dy * dy


def _pick_min(a, b):
    # where, not jnp.minimum: under jit(grad) XLA may recompute an operand with other
    # rounding, and jax 0.10's min rule (bitwise operand == result) then drops its gradient
    return jnp.where(a <= b, a, b)


def _geometry_native(ids, corner_w, corner_z, coeffs, scr, *, width, height, soft):
    """fragment_geometry in jax.numpy: the same arithmetic as the kernels
    (fragment_kernels.geometry_forward)."""
    valid = ids >= 0
    f = jnp.maximum(ids, 0)
    # ids may hold a folded batch (hostop.py): forward mode over vmap evaluates the jvp
    # of the folded call natively
    x, y, px, py = _pixel_grid(height, width, coeffs.dtype, ids.shape[0])
    c = jnp.take(coeffs, f, axis=0)
    edge = c[..., 0] * x[..., None] + c[..., 1] * y[..., None] + c[..., 2]
    dist = jnp.zeros(ids.shape, coeffs.dtype)
    if not soft:
        bary = _normalized(edge)
    else:
        w = jnp.take(corner_w, f, axis=0)
        screen = _normalized(edge * w)
        # where, not jnp.maximum: see _pick_min; and no gradient at 0, as the kernel
        bary = _normalized(safe_div(jnp.where(screen > 0.0, screen, 0.0), w))
        s = jnp.take(scr, f, axis=0)
        d2 = _pick_min(_pick_min(_segment_dist2(px, py, s[..., 0, :], s[..., 1, :]),
                                 _segment_dist2(px, py, s[..., 1, :], s[..., 2, :])),
                       _segment_dist2(px, py, s[..., 2, :], s[..., 0, :]))
        dist = jnp.where(valid, jnp.where(jnp.all(screen >= 0.0, -1), d2, -d2), 0.0)
    bary = jnp.where(valid[..., None], bary, 0.0)
    return bary, dot(bary, jnp.take(corner_z, f, axis=0)), dist


def _geometry_avals(ids, corner_w, corner_z, coeffs, scr, **params):
    """bary, depth and dist, then the saved nearest edges (int8)."""
    dtype = coeffs.dtype
    return (jax.ShapeDtypeStruct(ids.shape + (3,), dtype), jax.ShapeDtypeStruct(ids.shape, dtype),
            jax.ShapeDtypeStruct(ids.shape, dtype), jax.ShapeDtypeStruct(ids.shape, jnp.int8))


def _kernel_args(corner_w, corner_z, coeffs, scr, width, height, soft):
    """The kernels' per-face and static arguments (fragment_kernels.geometry_forward)."""
    return (corner_w, corner_z, coeffs, scr, width, height, soft, tiny(coeffs.dtype),
            kernels.chunks())


def _geometry_forward(ids, *per_face, width, height, soft):
    k = ids.shape[-1]
    return kernels.geometry_forward(ids.reshape(-1, k),
                                    *_kernel_args(*per_face, width, height, soft))


def _geometry_backward(ids, corner_w, corner_z, coeffs, scr, edge, g_bary, g_depth, g_dist, *,
                       width, height, soft):
    k = ids.shape[-1]
    args = _kernel_args(corner_w, corner_z, coeffs, scr, width, height, soft)
    return kernels.geometry_backward(ids.reshape(-1, k), *args, edge.reshape(-1, k),
                                     g_bary.reshape(-1, k, 3), g_depth.reshape(-1, k),
                                     g_dist.reshape(-1, k))


#: Per fragment: barycentrics [H, W, K, 3] (clamped to the triangle in soft mode), the
#: interpolated eye-space depth [H, W, K] and the signed squared distance in pixels^2 to
#: the triangle's boundary [H, W, K] (soft; zeros in hard mode), from the face ids
#: [H, W, K] and per-face inputs: corner_w [F, 3] clip W and corner_z [F, 3] eye-space
#: depth of the corners, coeffs [F, 3, 3] edge coefficients (face_edge_coefficients), scr
#: [F, 3, 2] corner pixel positions. Static: width, height, soft. The forward kernel hands
#: each fragment's nearest edge to the backward (a saved value, hostop.py).
fragment_geometry = FragmentOp("fragment_geometry", ("face",) * 4, _geometry_native,
                               _geometry_forward, _geometry_backward, _geometry_avals,
                               ffi=("geometry", ("width", "height", "soft")), saved=1)


def fragments_from_ids(proj: Projected, faces, face_ids, dropped, soft=False,
                       host=None) -> Fragments:
    """Differentiable fragment geometry of the chosen faces (see module docstring).

    soft=True: barycentrics of pixels outside a triangle are clamped to it in screen space
    (negative ones set to 0, renormalized), then corrected for perspective, and the signed
    squared distance `dist` is computed. (Clamping the perspective-correct barycentrics
    instead goes wrong where the pixel's ray meets the triangle's plane behind the eye:
    they all flip sign there.)
    host: run the per-fragment geometry as compiled host kernels (default: on the CPU
    backend), else in jax.numpy (hostop.py).
    """
    host = jax.default_backend() == "cpu" if host is None else host
    height, width, _ = face_ids.shape
    valid = face_ids >= 0
    ids = jnp.maximum(face_ids, 0)
    coeffs, det = face_edge_coefficients(proj.clip, faces)
    corner_w = jnp.take(proj.clip[:, 3], faces)
    corner_z = jnp.take(proj.depth, faces)
    scr = jnp.take(_screen_positions(proj.clip, width, height), faces, axis=0)
    bary, depth, dist = fragment_geometry(face_ids, corner_w, corner_z, coeffs, scr, host=host,
                                          width=width, height=height, soft=soft)
    return Fragments(face_ids, bary, depth, valid & (jnp.take(det, ids) > 0), dropped,
                     dist if soft else None)


def rasterize(proj: Projected, faces, camera, settings, layers=1) -> Fragments:
    """Hard mode: the `layers` nearest covering faces per pixel, nearest first (1: a
    z-buffer; transparency composites several). Soft mode: up to settings.faces_per_pixel
    faces whose soft footprint reaches the pixel, ranked by their weight in the soft blend
    (candidates.find_candidates)."""
    soft = settings.raster == "soft"
    face_ids, dropped = search_faces(proj.clip, faces, camera, search_depth(settings, layers),
                                     settings, soft)
    return fragments_from_ids(proj, faces, face_ids, dropped, soft=soft,
                              host=settings.use_host_kernels())

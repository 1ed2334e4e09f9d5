"""A dense, naive soft rasterizer: the oracle for diffshade's soft mode on tiny scenes.

For every pixel centre and EVERY face (an O(pixels x faces) computation, no candidate
search, no K) it redoes, in plain jax.numpy (differentiable, float64 under x64):
- projection: model matrix, then diffshade.scene.camera.view_matrix / projection_matrix (tested
  elsewhere); pixel coordinates x = (X/W + 1) width/2, y = (1 - Y/W) height/2, pixel
  centres at (col + 0.5, row + 0.5);
- screen-space barycentrics lam_i = area(p, s_j, s_k) / area(s_0, s_1, s_2); inside when
  all lam_i >= 0; d2 = min over the three edges of the squared point-segment distance;
  dist = +d2 inside, -d2 outside (pixels^2);
- clamped barycentrics: lam clamped at 0 and renormalized; perspective correction
  b_i = (lam_i / w_i) / sum_j (lam_j / w_j); eye depth sum_i b_i depth_i; NDC depth
  sum_i lam_i z_i / w_i (NDC z is affine in screen space);
- reach: |d2| <= r^2 = sigma ln((1 - t) / t) or inside, NDC depth in [-1, 1], and the
  face not culled: no vertex behind the near plane (Z + W < 0), non-zero screen area,
  back faces (clockwise on screen) only when cull_backfaces is off;
- colours with diffshade.shading.lighting.shade (the lighting core is tested elsewhere): Phong at
  the interpolated point and normal, Gouraud from clamped vertex colours, flat at the
  centroid with the face normal, flat_last from the last vertex; OpenGL's two-sided rule;
- aggregation written out literally, with the largest exponent m factored out:
      D = sigmoid(dist / sigma),  zt = clip((1/z - 1/far) / (1/near - 1/far), 0, 1)
      e_f = D_f exp((zt_f - m) / gamma) for reached faces, 0 otherwise
      e_bg = exp((eps - m) / gamma),  rgb = (sum_f e_f c_f + e_bg bg) / (sum_f e_f + e_bg)
      alpha = 1 - prod over reached faces of (1 - D_f)
Optionally only the `k` reached faces of largest weight log D + zt / gamma are kept, as
the real implementation does when K is too small (for small gamma: the nearest).

Nothing from diffshade.raster.fragments, candidates, interpolate, blend or render is used.
"""

import math

import jax
import jax.numpy as jnp

from diffshade.scene.camera import projection_matrix, view_matrix
from diffshade.shading.lighting import shade

BACKGROUND_EPS = 1e-3


def reach_radius2(sigma, threshold):
    """Squared footprint radius in pixels^2: where sigmoid(-r^2 / sigma) = threshold."""
    return sigma * math.log((1.0 - threshold) / threshold)


def _cross2(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _unit(v):
    return v / jnp.sqrt(jnp.sum(v * v, -1, keepdims=True))


def _segment_dist2(p, a, b):
    """Squared distance from points p [..., 2] to segments ab [..., 2]."""
    ab = b - a
    len2 = jnp.maximum(jnp.sum(ab * ab, -1), jnp.finfo(ab.dtype).tiny)
    t = jnp.clip(jnp.sum((p - a) * ab, -1) / len2, 0.0, 1.0)
    d = p - (a + t[..., None] * ab)
    return jnp.sum(d * d, -1)


def face_table(scene, settings):
    """Per-face projected data (dict of [F, 3, ...] arrays) and which faces may be drawn."""
    model, mesh, cam = scene.model, scene.mesh, scene.camera
    world = mesh.vertices @ model[:3, :3].T + model[:3, 3]
    normals = _unit(mesh.normals @ jnp.linalg.inv(model[:3, :3]))
    eye = world @ view_matrix(cam)[:3, :3].T + view_matrix(cam)[:3, 3]
    clip = jnp.concatenate([eye, jnp.ones_like(eye[:, :1])], 1) @ projection_matrix(cam).T
    tri_clip = clip[mesh.faces]
    w = tri_clip[..., 3]
    visible = jnp.all(tri_clip[..., 2] + w >= 0.0, -1) & jnp.all(w > 0.0, -1)
    w_safe = jnp.where(visible[:, None], w, 1.0)
    ndc = tri_clip[..., :3] / w_safe[..., None]
    screen = jnp.stack([(ndc[..., 0] + 1.0) * cam.width / 2.0,
                        (1.0 - ndc[..., 1]) * cam.height / 2.0], -1)
    # counter-clockwise in NDC (y up) = the front face, as OpenGL decides
    area_ndc = _cross2(ndc[:, 1, :2] - ndc[:, 0, :2], ndc[:, 2, :2] - ndc[:, 0, :2])
    front = area_ndc > 0.0
    usable = visible & (area_ndc != 0.0)
    if settings.cull_backfaces:
        usable = usable & front
    return {"screen": screen, "w": w_safe, "zndc": ndc[..., 2], "depth": -eye[mesh.faces][..., 2],
            "world": world[mesh.faces], "normals": normals[mesh.faces], "vertex_world": world,
            "vertex_normals": normals, "front": front, "usable": usable}


def pixel_centres(width, height, dtype):
    """Pixel coordinates (x right, y down) of every pixel centre: [H * W, 2]."""
    ys, xs = jnp.meshgrid(jnp.arange(height, dtype=dtype) + 0.5,
                          jnp.arange(width, dtype=dtype) + 0.5, indexing="ij")
    return jnp.stack([xs.ravel(), ys.ravel()], -1)


def pixel_geometry(table, centres, radius2):
    """Every (pixel, face) pair: dict of [N, F] arrays (bary: [N, F, 3]): dist, inside,
    bary, depth, zndc, reach, ray_hits_plane."""
    p = centres[:, None, None, :]
    s = table["screen"][None]
    s_j, s_k = jnp.roll(s, -1, axis=2), jnp.roll(s, -2, axis=2)
    area = _cross2(s[:, :, 1] - s[:, :, 0], s[:, :, 2] - s[:, :, 0])
    area = jnp.where(table["usable"], area, 1.0)
    lam = _cross2(s_j - p, s_k - p) / area[..., None]
    inside = jnp.all(lam >= 0.0, -1)
    d2 = _segment_dist2(p, s, s_j)
    # a gather, not jnp.min: min's gradient tests operand == result bitwise, which XLA's
    # rematerialization can break under jit (jax issue #40564)
    d2 = jnp.take_along_axis(d2, jnp.argmin(d2, -1)[..., None], -1)[..., 0]
    lam_c = jnp.maximum(lam, 0.0)
    lam_c = lam_c / jnp.sum(lam_c, -1, keepdims=True)
    persp = lam_c / table["w"][None]
    bary = persp / jnp.sum(persp, -1, keepdims=True)
    zndc = jnp.sum(lam_c * table["zndc"][None], -1)
    # the pixel's eye ray meets the face's plane in front of the eye
    ray_hits_plane = jnp.sum(lam / table["w"][None], -1) > 0.0
    reach = (table["usable"][None] & (inside | (d2 <= radius2))
             & (zndc >= -1.0) & (zndc <= 1.0))
    return {"dist": jnp.where(inside, d2, -d2), "inside": inside, "bary": bary,
            "depth": jnp.sum(bary * table["depth"][None], -1), "zndc": zndc, "reach": reach,
            "ray_hits_plane": ray_hits_plane}


def normalized_inverse_depth(depth, near, far):
    """zt = clip((1/z - 1/far) / (1/near - 1/far), 0, 1) of eye depth z: [...]."""
    return jnp.clip((1.0 / depth - 1.0 / far) / (1.0 / near - 1.0 / far), 0.0, 1.0)


def blend_logit(geom, near, far, sigma, gamma):
    """log D + zt / gamma: the log of a fragment's (unnormalized) weight in the blend."""
    zt = normalized_inverse_depth(geom["depth"], near, far)
    return jax.nn.log_sigmoid(geom["dist"] / sigma) + zt / gamma


def best_k(reach, logit, k):
    """reach restricted to the k faces of largest blend weight (ties: lowest id): [N, F]."""
    key = jnp.where(reach, logit, -jnp.inf)
    ids = jnp.arange(key.shape[-1])
    ahead = (key[:, None, :] > key[:, :, None]) | (
        (key[:, None, :] == key[:, :, None]) & (ids[None, None, :] < ids[:, None]))
    rank = jnp.sum(ahead & reach[:, None, :], -1)
    return reach & (rank < k)


def _lit(scene, settings, points, normals, front):
    """Clamped colour with OpenGL's two-sided rule; front: [...] bool."""
    material = scene.material
    if scene.two_sided:
        normals = jnp.where(front[..., None], normals, -normals)
        back = material if scene.back_material is None else scene.back_material
        material = jax.tree.map(
            lambda f, b: jnp.where(front.reshape(front.shape + (1,) * jnp.ndim(f)), f, b),
            material, back)
    if scene.local_viewer:
        view = _unit(scene.camera.eye - points)
    else:
        view = jnp.broadcast_to(_unit(scene.camera.eye - scene.camera.target), points.shape)
    total = shade(material, scene.lights, scene.global_ambient, points, normals, view,
                  settings).total
    return jnp.clip(total, 0.0, 1.0) if settings.clamp else total


def _vertex_colours(scene, settings, table, side):
    n = table["vertex_world"].shape[0]
    return _lit(scene, settings, table["vertex_world"], table["vertex_normals"],
                jnp.full(n, side))


def _per_vertex(scene, settings, table, pick):
    """Per (pixel, face) colour from per-vertex colours lit as front (and back) faces."""
    faces = scene.mesh.faces
    front_c = pick(_vertex_colours(scene, settings, table, True)[faces])
    if not scene.two_sided:
        return front_c
    back_c = pick(_vertex_colours(scene, settings, table, False)[faces])
    return jnp.where(table["front"][None, :, None], front_c, back_c)


def face_colours(scene, settings, table, geom):
    """Colour of every (pixel, face) pair by settings.shading: [N, F, 3]."""
    bary = geom["bary"][..., None]
    front = jnp.broadcast_to(table["front"][None], geom["dist"].shape)
    if settings.shading == "phong":
        points = jnp.sum(bary * table["world"][None], -2)
        normals = _unit(jnp.sum(bary * table["normals"][None], -2))
        return _lit(scene, settings, points, normals, front)
    if settings.shading == "gouraud":
        return _per_vertex(scene, settings, table, lambda c: jnp.sum(bary * c[None], -2))
    if settings.shading == "flat_last":
        return _per_vertex(scene, settings, table,
                           lambda c: jnp.broadcast_to(c[None, :, 2], bary.shape[:-2] + (3,)))
    tri = table["world"]
    normals = _unit(jnp.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
    colours = _lit(scene, settings, tri.mean(1), normals, table["front"])
    return jnp.broadcast_to(colours[None], bary.shape[:-2] + (3,))


def aggregate(geom, keep, colours, background, near, far, sigma, gamma):
    """SoftRas aggregation over the kept faces (module docstring): [N, 4]."""
    x = geom["dist"] / sigma
    cover, clear = jax.nn.sigmoid(x), jax.nn.sigmoid(-x)
    zt = normalized_inverse_depth(geom["depth"], near, far)
    # m only keeps exp() in range: the result does not depend on it
    m = jax.lax.stop_gradient(jnp.maximum(jnp.max(jnp.where(keep, zt, -jnp.inf), -1),
                                          BACKGROUND_EPS))
    e = jnp.where(keep, cover * jnp.exp(jnp.where(keep, zt - m[:, None], 0.0) / gamma), 0.0)
    e_bg = jnp.exp((BACKGROUND_EPS - m) / gamma)
    total = jnp.sum(e, -1) + e_bg
    colours = jnp.where(keep[..., None], colours, 0.0)  # faces never reached may be NaN
    rgb = (jnp.sum(e[..., None] * colours, -2) + e_bg[:, None] * background) / total[:, None]
    alpha = 1.0 - jnp.prod(jnp.where(keep, clear, 1.0), -1)
    return jnp.concatenate([rgb, alpha[:, None]], -1)


def _render_block(scene, settings, table, centres, sigma, gamma, k):
    geom = pixel_geometry(table, centres, reach_radius2(sigma, settings.soft_threshold))
    cam = scene.camera
    keep = geom["reach"]
    if k is not None:
        keep = best_k(keep, blend_logit(geom, cam.near, cam.far, sigma, gamma), k)
    colours = face_colours(scene, settings, table, geom)
    return aggregate(geom, keep, colours, scene.background, cam.near, cam.far, sigma, gamma)


def soft_reference(scene, settings, sigma=None, gamma=None, k=None, block_rows=None,
                   row_range=None):
    """The soft render of `scene`: [H, W, 4] RGBA (rows row_range = (start, stop) only:
    [stop - start, W, 4]).

    settings: RenderSettings (shading, clamp, cull_backfaces, soft_threshold, ...);
    sigma, gamma: override the settings' values (they may be traced, so that one jit serves
    many values); k: keep only the k reached faces of largest blend weight per pixel
    (None: all);
    block_rows: process that many image rows at a time (a divisor of the number of rows;
    each block is rematerialized in the backward pass), to bound memory.
    """
    sigma = settings.sigma if sigma is None else sigma
    gamma = settings.gamma if gamma is None else gamma
    cam = scene.camera
    dtype = scene.mesh.vertices.dtype
    start, stop = (0, cam.height) if row_range is None else row_range
    rows = stop - start
    table = face_table(scene, settings)
    centres = pixel_centres(cam.width, cam.height, dtype)[start * cam.width:stop * cam.width]
    block = lambda c: _render_block(scene, settings, table, c, sigma, gamma, k)
    if block_rows is None:
        return block(centres).reshape(rows, cam.width, 4)
    if rows % block_rows:
        raise ValueError(f"block_rows: got {block_rows}; expected a divisor of the number of "
                         f"rows {rows}")
    blocks = centres.reshape(rows // block_rows, block_rows * cam.width, 2)
    return jax.lax.map(jax.checkpoint(block), blocks).reshape(rows, cam.width, 4)


def dense_fragments(scene, settings, sigma=None):
    """Every (pixel, face) pair's geometry (pixel_geometry) and blend logit (blend_logit,
    with settings.gamma) as [H, W, F] arrays; sigma overrides settings.sigma."""
    cam = scene.camera
    sigma = settings.sigma if sigma is None else sigma
    table = face_table(scene, settings)
    geom = pixel_geometry(table, pixel_centres(cam.width, cam.height, scene.mesh.vertices.dtype),
                          reach_radius2(sigma, settings.soft_threshold))
    geom["logit"] = blend_logit(geom, cam.near, cam.far, sigma, settings.gamma)
    return {name: a.reshape((cam.height, cam.width) + a.shape[1:]) for name, a in geom.items()}


"""Shadow maps: hidden-surface removal from the light's position (the lecture notes' method).

A light with shadows=True gets a depth map of the scene, rendered from the light with the
project's own rasterizer (hard z-buffer, one face per texel): a cube of six 90 degree
perspective maps for a point light, one perspective map over the cone for a spot, one
orthographic map fitted to the scene's bounding sphere for a directional light. Shading
multiplies the light's diffuse and specular terms by the visibility of each point; its
ambient term stays, so a shadowed point keeps only the ambient terms.

Lookup: the shading point is projected into the map (for a cube, into the face of its
major axis); d is its depth along that map's axis, texel(d) the world size of one texel
there, and bias = shadow_bias * texel(d) * (1 + tan(theta)) with theta the angle of
incidence (slope-scaled: a surface seen at a grazing angle changes depth fast across a
texel). Hard raster: the nearest texel; lit iff d <= d_map + bias (a step). Soft raster:
percentage-closer filtering, the bilinear weights of the four nearest texels applied to
sigmoid((d_map + bias - d) / (shadow_softness * texel(d))): smooth in the point, the
light and the map's depths, so gradients flow with respect to light and geometry.
(Filtering the comparisons rather than the depths: averaging an occluder's depth with
its receiver's would invent a surface in between.) Points outside a map, and texels that
hold no surface, are lit.

Which face a texel holds is a discrete search, as in any rasterization; its depth is
differentiable in the vertices and the light. An occluder's depth therefore has a
gradient; its silhouette's sideways motion acts only through the point's projection.

`visibility(shadow_map, points, normals, light_dir, settings)` takes any map. An area or
sphere light with shadows (diffshade.shading.area) gets one cube map per sample point
(`area_maps`: `point_map` in a loop over the light's `sample_points`, so S samples cost
S times a point light's six maps), and `sampled_visibility` averages the per-sample
visibilities weighted by each sample's unshadowed diffuse contribution: in soft raster
every sample's test is the smooth one above, so the penumbra is smooth too.
"""

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp

from diffshade.numerics import dot, safe_div, safe_norm, safe_normalize, tiny
from diffshade.raster.fragments import rasterize
from diffshade.raster.projection import Projected
from diffshade.scene.camera import Camera, projection_matrix, view_matrix
from diffshade.scene.lights import SHADOW_SPOT_CUTOFF, shadow_flags
from diffshade.scene.transform import transform_points
from diffshade.shading.area import KINDS as AREA_KINDS
from diffshade.shading.area import from_point, sample_points

#: the cube's faces: (axis the face looks along, its up vector)
CUBE_FACES = (((1, 0, 0), (0, 1, 0)), ((-1, 0, 0), (0, 1, 0)), ((0, 1, 0), (0, 0, 1)),
              ((0, -1, 0), (0, 0, 1)), ((0, 0, 1), (0, 1, 0)), ((0, 0, -1), (0, 1, 0)))
#: tan(theta) in the slope-scaled bias is capped (theta ~ 84 degrees): beyond it the light
#: grazes the surface and its diffuse term is ~0 anyway
MAX_SLOPE = 10.0


@partial(jax.tree_util.register_dataclass, data_fields=["depth", "view", "proj", "texel"],
         meta_fields=["perspective"])
@dataclasses.dataclass(frozen=True)
class ShadowMap:
    """depth: [M, S, S] depth along each map's axis of the nearest surface (beyond `far`
    where a texel holds none), row 0 at the top; view: [M, 4, 4] world -> light eye;
    proj: [M, 4, 4] eye -> clip; texel: [] a texel's world size per unit depth
    (perspective) or in world units (orthographic). M = 6 (cube) or 1."""

    depth: jax.Array
    view: jax.Array
    proj: jax.Array
    texel: jax.Array
    perspective: bool


def _bounds(world):
    """Centre [3] and radius [] of a sphere around the vertices [V, 3], both smooth in the
    vertices (the framing moves the texel grid and sets the texel size, which the
    filtered visibility and the bias depend on, so it is differentiated like the rest):
    the mean, and the p-norm of the distances from it (p = 32: at least the largest
    distance and at most V^(1/32) times it), scaled by their maximum so that no power
    overflows; the p-norm does not depend on that scale, so it carries no gradient."""
    centre = jnp.mean(world, 0)
    dist = safe_norm(world - centre)
    scale = jax.lax.stop_gradient(jnp.maximum(jnp.max(dist), tiny(world.dtype) ** 0.25))
    return centre, scale * jnp.sum((dist / scale) ** 32) ** (1.0 / 32)


def _depth_map(world, faces, camera, settings):
    """[S, S] depth of the nearest surface along the camera's axis (4 * far where empty)."""
    eye = transform_points(view_matrix(camera), world)
    clip = jnp.concatenate([eye, jnp.ones_like(eye[:, :1])], 1) @ projection_matrix(camera).T
    frags = rasterize(Projected(clip, world, world, -eye[:, 2]), faces, camera, settings)
    return jnp.where(frags.valid[..., 0], frags.depth[..., 0], 4.0 * camera.far)


def _map_settings(settings):
    """The maps' raster: z-buffer, both sides of every face occlude."""
    return dataclasses.replace(settings, raster="hard", cull_backfaces=False)


def _up_for(direction):
    """An up vector not parallel to `direction` [3]."""
    unit = safe_normalize(direction)
    y, x = jnp.array([0.0, 1.0, 0.0], unit.dtype), jnp.array([1.0, 0.0, 0.0], unit.dtype)
    return jnp.where(jnp.abs(unit[1]) > 0.9, x, y)


def _build(cameras, world, faces, settings, texel, perspective):
    """ShadowMap of the cameras (one Camera whose leaves have a leading map axis)."""
    settings = _map_settings(settings)
    depth = jax.vmap(lambda cam: _depth_map(world, faces, cam, settings))(cameras)
    return ShadowMap(depth, jax.vmap(view_matrix)(cameras),
                     jax.vmap(projection_matrix)(cameras), texel, perspective)


def _cameras(eye, target, up, fov_y, near, far, ortho_height, size, projection):
    """One Camera of M maps from [M, 3] eye, target, up and [M] or [] scalars."""
    m = eye.shape[0]
    row = lambda v: jnp.broadcast_to(jnp.asarray(v, eye.dtype), (m,))
    zeros = jnp.zeros((m, 5), eye.dtype)
    return Camera(eye, target, up, row(fov_y), row(near), row(far), row(ortho_height),
                  zeros[:, :2], row(1.0), zeros, size, size, projection)


def _range_from(position, world):
    """near, far of a map at `position` holding the whole scene."""
    centre, radius = _bounds(world)
    far = 1.01 * (safe_norm(position - centre) + radius)
    return 1e-3 * far, far


def point_map(position, world, faces, settings) -> ShadowMap:
    """Cube map (six 90 degree frusta) of the mesh world [V, 3], faces [F, 3] seen from
    `position` [3]."""
    axes = jnp.asarray([a for a, _ in CUBE_FACES], world.dtype)
    ups = jnp.asarray([u for _, u in CUBE_FACES], world.dtype)
    near, far = _range_from(position, world)
    eye = jnp.broadcast_to(position, axes.shape)
    size = settings.shadow_map_size
    cams = _cameras(eye, eye + axes, ups, 90.0, near, far, 1.0, size, "perspective")
    return _build(cams, world, faces, settings, jnp.asarray(2.0 / size, world.dtype), True)


def spot_map(position, direction, cutoff, world, faces, settings) -> ShadowMap:
    """One perspective map around `direction` [3] from `position` [3], covering the cone
    of half-angle `cutoff` [] degrees (at most SHADOW_SPOT_CUTOFF) and its edge: 1 degree
    beyond it, or 8 edge widths for settings.spot_edge 'smooth' (at most 85 degrees)."""
    edge = 8.0 * settings.spot_softness if settings.spot_edge == "smooth" else 1.0
    fov = 2.0 * jnp.minimum(jnp.minimum(cutoff, SHADOW_SPOT_CUTOFF) + edge, 85.0)
    near, far = _range_from(position, world)
    size = settings.shadow_map_size
    cams = _cameras(position[None], (position + safe_normalize(direction))[None],
                    _up_for(direction)[None], fov, near, far, 1.0, size, "perspective")
    texel = 2.0 * jnp.tan(jnp.deg2rad(fov) / 2.0) / size
    return _build(cams, world, faces, settings, texel, True)


def directional_map(direction, world, faces, settings) -> ShadowMap:
    """Orthographic map along `direction` [3] fitted to the mesh's bounding sphere."""
    centre, radius = _bounds(world)
    eye = centre - 2.0 * radius * safe_normalize(direction)
    size = settings.shadow_map_size
    cams = _cameras(eye[None], centre[None], _up_for(direction)[None], 90.0, 0.5 * radius,
                    3.5 * radius, 2.0 * radius, size, "orthographic")
    return _build(cams, world, faces, settings, 2.0 * radius / size, False)


def area_maps(kind, light, world, faces, settings) -> ShadowMap:
    """One cube map per sample point of an area or sphere light (a single light): a
    ShadowMap whose leaves have a leading sample axis S (depth [S, 6, size, size]). Built
    by a loop over the samples (`lax.map`), so that the rasterization's intermediates
    (its fragments) are held for one sample's maps at a time, not S-fold as a vmap would."""
    points, _ = sample_points(kind, light)
    return jax.lax.map(lambda q: point_map(q, world, faces, settings), points)


def _light_map(kind, group, i, world, faces, settings):
    """The map of light i of a stacked group (only the fields a map needs are read)."""
    if kind in AREA_KINDS:
        light = jax.tree.map(lambda a: a[i], group)
        return area_maps(kind, light, world, faces, settings)
    if kind == "point":
        return point_map(group.position[i], world, faces, settings)
    if kind == "spot":
        return spot_map(group.position[i], group.direction[i], group.cutoff[i], world, faces,
                        settings)
    return directional_map(group.direction[i], world, faces, settings)


def shadow_maps(scene, settings):
    """{(kind, index in its group): ShadowMap} for every light of `scene` with shadows (for
    an area or sphere light, `area_maps`), or None when none has: nothing is then
    rasterized from the lights."""
    maps = {}
    world = transform_points(scene.model, scene.mesh.vertices)
    for kind in ("directional", "point", "spot", *AREA_KINDS):
        group = getattr(scene.lights, kind)
        if group is None:
            continue
        count = jax.tree.leaves(group)[0].shape[0]
        for i, flag in enumerate(shadow_flags(group, count)):
            if flag:
                maps[(kind, i)] = _light_map(kind, group, i, world, scene.mesh.faces, settings)
    return maps or None


def _select(values, index):
    """values [..., M, C] at index [...] along M: [..., C]."""
    return jnp.take_along_axis(values, index[..., None, None], axis=-2)[..., 0, :]


def _texel_coords(shadow_map, points):
    """Per point: its map index [...] int, continuous texel coordinates (x, y) [...] each
    (texel centres at integers), depth d [...] along the map's axis, and inside [...]."""
    view, proj = shadow_map.view, shadow_map.proj
    eye = jnp.einsum("mij,...j->...mi", view[:, :3, :3], points) + view[:, :3, 3]
    homog = jnp.concatenate([eye, jnp.ones_like(eye[..., :1])], -1)
    clip = jnp.einsum("mij,...mj->...mi", proj, homog)
    index = jnp.argmax(-eye[..., 2], axis=-1)
    eye, clip = _select(eye, index), _select(clip, index)
    ndc = safe_div(clip[..., :2], clip[..., 3:])
    size = shadow_map.depth.shape[-1]
    x = (ndc[..., 0] + 1.0) * (size / 2.0) - 0.5
    y = (1.0 - ndc[..., 1]) * (size / 2.0) - 0.5
    depth = -eye[..., 2]
    inside = jnp.all(jnp.abs(ndc) <= 1.0, -1)
    if shadow_map.perspective:
        inside = inside & (depth > 0.0)
    return index, x, y, depth, inside


def _map_depth(shadow_map, index, col, row):
    """The map's depth at integer texel (col, row) of map `index`, clamped to the edge."""
    size = shadow_map.depth.shape[-1]
    col, row = jnp.clip(col, 0, size - 1), jnp.clip(row, 0, size - 1)
    flat = (index * size + row) * size + col
    return jnp.take(shadow_map.depth.reshape(-1), flat, axis=0)


def visibility(shadow_map: ShadowMap, points, normals, light_dir, settings):
    """How much of the light reaches each point: [..., 1] in [0, 1]. points, normals,
    light_dir (unit, towards the light): [..., 3] world space; settings: raster mode,
    shadow_bias and shadow_softness (module docstring)."""
    index, x, y, depth, inside = _texel_coords(shadow_map, points)
    # double where: a point outside the map (at the light itself, say: an empty fragment
    # slot interpolates to the origin) must not divide by its depth even in the branch
    # the final `where` discards, or its gradient turns 0 * inf into NaN
    depth, x, y = (jnp.where(inside, v, fill) for v, fill in ((depth, 1.0), (x, 0.0), (y, 0.0)))
    texel = shadow_map.texel * depth if shadow_map.perspective else shadow_map.texel
    cos = jnp.maximum(dot(normals, light_dir), 1.0 / MAX_SLOPE)
    slope = jnp.minimum(safe_div(safe_norm(jnp.cross(normals, light_dir)), cos), MAX_SLOPE)
    reach = depth - settings.shadow_bias * texel * (1.0 + slope)
    if settings.raster == "hard":
        col, row = jnp.round(x).astype(jnp.int32), jnp.round(y).astype(jnp.int32)
        lit = (reach <= _map_depth(shadow_map, index, col, row)).astype(points.dtype)
    else:
        col0, row0 = jnp.floor(x), jnp.floor(y)
        fx, fy = x - col0, y - row0
        col0, row0 = col0.astype(jnp.int32), row0.astype(jnp.int32)
        width = settings.shadow_softness * texel
        lit = sum(jax.nn.sigmoid((_map_depth(shadow_map, index, col0 + dc, row0 + dr) - reach)
                                 / width) * wx * wy
                  for dc, wx in ((0, 1.0 - fx), (1, fx)) for dr, wy in ((0, 1.0 - fy), (1, fy)))
    return jnp.where(inside, lit, 1.0)[..., None]


def sampled_visibility(kind, light, maps: ShadowMap, points, normals, settings):
    """How much of an area or sphere light (a single light) reaches each point: [..., 1],
    V = sum_j c_j vis_j / sum_j c_j over its sample points j, c_j = max(N.L_j, 0)
    max(-n_j.L_j, 0) / r_j^2 (the sample's unshadowed diffuse contribution), vis_j the
    `visibility` in its map (maps: `area_maps`); 1 where no sample contributes. A scan
    over the samples, each step rematerialized in the backward pass."""
    sample_at, emit_normals = sample_points(kind, light)
    zeros = jnp.zeros(points.shape[:-1] + (1,), points.dtype)

    def step(sums, sample):
        q, emit_normal, shadow_map = sample
        light_dir, facing = from_point(points, q, emit_normal)
        weight = facing * jnp.maximum(dot(normals, light_dir, keepdims=True), 0.0)
        seen = visibility(shadow_map, points, normals, light_dir, settings)
        return (sums[0] + weight * seen, sums[1] + weight), None

    (lit, total), _ = jax.lax.scan(jax.checkpoint(step), (zeros, zeros),
                                   (sample_at, emit_normals, maps))
    return safe_div(lit, total, fallback=1.0)

"""Ground truth that is not our mesh renderer: an exact sphere, ray traced per pixel.

For each sample position in a pixel, the camera ray is intersected with the exact sphere
and the hit point is shaded with its exact normal by the same lighting core (`shade`),
so the difference between a mesh render and this image is the error of tessellation,
interpolation, resolution and rasterization alone. `supersample=s` shoots s x s rays per
pixel on a regular grid and averages the composited colour and the coverage.

`SphereOverPlane` is the reference for shadows: its mesh, its exact hard shadow from
a point or directional light (ray/sphere tests in NumPy float64, per pixel centre), and
the irradiance of its floor from a disk or a spherical light with the sphere's shadow
(penumbrae: a midpoint quadrature over the light, each node tested against the sphere).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.numerics import clamp01, dot, safe_normalize, safe_sqrt
from diffshade.scene.camera import Camera, lens, view_dir_infinite
from diffshade.scene.mesh import icosphere, mesh_from_arrays
from diffshade.shading.lighting import shade


def _sample_ndc(width, height, supersample, dtype):
    """NDC (x, y) of s x s sub-pixel samples: [H, W, s*s, 2], row 0 at the top."""
    offsets = (jnp.arange(supersample, dtype=dtype) + 0.5) / supersample
    cols = jnp.arange(width, dtype=dtype)[:, None] + offsets[None, :]
    rows = jnp.arange(height, dtype=dtype)[:, None] + offsets[None, :]
    x = 2.0 * cols / width - 1.0
    y = 1.0 - 2.0 * rows / height
    xs = jnp.broadcast_to(x[None, :, None, :], (height, width, supersample, supersample))
    ys = jnp.broadcast_to(y[:, None, :, None], (height, width, supersample, supersample))
    return jnp.stack([xs, ys], -1).reshape(height, width, supersample * supersample, 2)


def camera_rays(camera: Camera, ndc):
    """World-space ray origins and unit directions through NDC points ndc: [..., 2]."""
    forward = safe_normalize(camera.target - camera.eye)
    side = safe_normalize(jnp.cross(forward, camera.up))
    up = jnp.cross(side, forward)
    scale, offset = lens(camera)
    eye_xy = (ndc - offset) / scale
    across = eye_xy[..., :1] * side + eye_xy[..., 1:] * up
    if camera.projection == "perspective":
        dirs = across + forward
        return jnp.broadcast_to(camera.eye, dirs.shape), safe_normalize(dirs)
    origins = camera.eye + across
    return origins, jnp.broadcast_to(forward, origins.shape)


def intersect_sphere(origins, dirs, center, radius):
    """Nearest hit distance along unit rays [..., 3] (inf where missed) and the hit mask."""
    rel = origins - center
    b = dot(rel, dirs)
    disc = b * b - (dot(rel, rel) - radius * radius)
    hit = disc > 0.0
    root = safe_sqrt(jnp.where(hit, disc, 0.0))
    near_t, far_t = -b - root, -b + root
    t = jnp.where(near_t > 0.0, near_t, far_t)
    hit = hit & (t > 0.0)
    return jnp.where(hit, t, jnp.inf), hit


def render_analytic_sphere(scene, settings, center=(0.0, 0.0, 0.0), radius=1.0, supersample=1):
    """The exact sphere lit like `scene` (its lights, material, viewer model, background):
    [H, W, 4] RGBA, alpha = fraction of samples that hit. The scene's mesh is ignored."""
    cam = scene.camera
    ndc = _sample_ndc(cam.width, cam.height, supersample, cam.eye.dtype)
    return sphere_at_ndc(scene, settings, ndc, center, radius)


def sphere_at_ndc(scene, settings, ndc, center=(0.0, 0.0, 0.0), radius=1.0):
    """The exact sphere lit like `scene`, seen through NDC points ndc [..., S, 2] of its
    camera (S samples per pixel, averaged): [..., 4] RGBA."""
    cam = scene.camera
    dtype = cam.eye.dtype
    center = jnp.asarray(center, dtype)
    origins, dirs = camera_rays(cam, ndc)
    t, hit = intersect_sphere(origins, dirs, center, radius)
    points = origins + jnp.where(hit, t, 0.0)[..., None] * dirs
    normals = safe_normalize(points - center)
    view = (safe_normalize(cam.eye - points) if scene.local_viewer
            else jnp.broadcast_to(view_dir_infinite(cam), points.shape))
    parts = shade(scene.material, scene.lights, scene.global_ambient, points, normals, view,
                  settings)
    colour = clamp01(parts.total) if settings.clamp else parts.total
    cover = hit[..., None].astype(dtype)
    rgb = jnp.mean(cover * colour + (1.0 - cover) * scene.background, axis=-2)
    return jnp.concatenate([rgb, jnp.mean(cover, axis=-2)], -1)


render_analytic_sphere = jax.jit(render_analytic_sphere,
                                 static_argnames=("radius", "supersample"))
sphere_at_ndc = jax.jit(sphere_at_ndc, static_argnames=("radius",))



@dataclasses.dataclass(frozen=True)
class SphereOverPlane:
    """A sphere over a square floor, the reference scene for shadows: the sphere at
    `center` with `radius`; the floor y = plane_y, |x|, |z| <= half_size."""

    center: tuple = (0.0, 0.0, 0.0)
    radius: float = 0.5
    plane_y: float = -1.0
    half_size: float = 2.0

    def mesh(self, subdivisions=2, cells=4):
        """One Mesh: an icosphere (vertices on the exact sphere) and a floor of
        cells x cells squares facing +y."""
        sphere = icosphere(subdivisions, self.radius)
        grid = np.linspace(-self.half_size, self.half_size, cells + 1)
        xs, zs = np.meshgrid(grid, grid)
        floor = np.stack([xs.ravel(), np.full(xs.size, self.plane_y), zs.ravel()], 1)
        a = (np.arange(cells)[:, None] * (cells + 1) + np.arange(cells)[None, :]).ravel()
        quads = np.concatenate([np.stack([a, a + cells + 1, a + 1], 1),
                                np.stack([a + 1, a + cells + 1, a + cells + 2], 1)])
        vertices = np.asarray(sphere.vertices, np.float64) + np.asarray(self.center)
        n_sphere = len(vertices)
        normals = np.concatenate([np.asarray(sphere.normals, np.float64),
                                  np.tile([0.0, 1.0, 0.0], (len(floor), 1))])
        return mesh_from_arrays(np.concatenate([vertices, floor]),
                                np.concatenate([np.asarray(sphere.faces), quads + n_sphere]),
                                normals)

    def shadow(self, camera: Camera, light):
        """The exact hard shadow at each pixel centre, in NumPy float64 (a reference for
        shadow maps); light: ("point", position) or ("directional", travel direction).
        Returns (on_plane [H, W] bool: the pixel's camera ray meets the floor before the
        sphere; shadow [H, W] bool: that floor point cannot see the light: its segment to
        the light (a ray against the direction, for a directional light) meets the
        sphere)."""
        origins, dirs = pixel_rays(camera)
        center = np.asarray(self.center, np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_plane = (self.plane_y - origins[..., 1]) / dirs[..., 1]
        points = origins + t_plane[..., None] * dirs
        inside = np.all(np.abs(points[..., [0, 2]]) <= self.half_size, -1) & (t_plane > 0)
        t_sphere = _segment_sphere(origins, dirs, center, self.radius, np.inf)
        on_plane = inside & ~(t_sphere < t_plane)
        kind, value = light
        value = np.asarray(value, np.float64)
        to_light = value - points if kind == "point" else -np.broadcast_to(value, points.shape)
        limit = 1.0 if kind == "point" else np.inf
        hit = np.isfinite(_segment_sphere(points, to_light, center, self.radius, limit))
        return on_plane, on_plane & hit


    def floor_points(self, camera: Camera):
        """Where each pixel centre's camera ray meets the floor's plane: [H, W, 3]."""
        origins, dirs = pixel_rays(camera)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (self.plane_y - origins[..., 1]) / dirs[..., 1]
        return origins + t[..., None] * dirs

    def floor_irradiance(self, points, light, nodes=64, chunk=256):
        """Irradiance per unit colour of floor points [..., 3] (normal +y) from a disk or a
        spherical light (the radiometry of docs/area-lights.md), NumPy float64: (E with
        the sphere's shadow, E without it), [...] each. light: ("disk", centre, emitting
        normal, radius) or ("sphere", centre, radius). A midpoint rule of nodes^2 points
        (`chunk` at a time): over the disk's area (uniform in r^2 and azimuth), or over
        the sphere's cone of directions (uniform in solid angle)."""
        u = (np.arange(nodes) + 0.5) / nodes
        a, b = (x.ravel() for x in np.meshgrid(u, u, indexing="ij"))
        points = np.asarray(points, np.float64)[..., None, :]  # [..., 1, 3]: nodes next
        shadowed = unshadowed = 0.0
        for i in range(0, a.size, chunk):
            to_light, share, limit = _quadrature_nodes(light, points, a[i:i + chunk],
                                                       2.0 * np.pi * b[i:i + chunk])
            hit = np.isfinite(_segment_sphere(points, to_light, np.asarray(self.center),
                                              self.radius, limit))
            shadowed = shadowed + np.sum(np.where(hit, 0.0, share), -1) / a.size
            unshadowed = unshadowed + np.sum(share, -1) / a.size
        return shadowed, unshadowed


def _quadrature_nodes(light, points, a, phi):
    """(vectors from points [..., 1, 3] towards each node [..., N, 3], each node's share of
    E times the node count [..., N], how far along the vector the light is) for nodes at
    unit-square coordinates (a, phi / 2 pi) [N]."""
    if light[0] == "disk":
        _, centre, normal, radius = light
        normal = np.asarray(normal, np.float64) / np.linalg.norm(normal)
        t1, t2 = _tangents(normal)
        r = radius * np.sqrt(a)
        at = np.asarray(centre) + (r * np.cos(phi))[:, None] * t1 + (r * np.sin(phi))[:, None] * t2
        to_light = at - points
        dist2 = np.sum(to_light * to_light, -1)
        unit = to_light / np.sqrt(dist2)[..., None]
        facing = np.maximum(-unit @ normal, 0.0)
        return to_light, np.maximum(unit[..., 1], 0.0) * facing / dist2, 1.0
    _, centre, radius = light
    axis = np.asarray(centre, np.float64) - points
    dist2 = np.sum(axis * axis, -1)
    axis = axis / np.sqrt(dist2)[..., None]
    one_minus = 1.0 - np.sqrt(1.0 - radius * radius / dist2)  # 1 - cos(the cone's half-angle)
    cos_t = 1.0 - a * one_minus
    sin_t = np.sqrt(np.maximum(1.0 - cos_t * cos_t, 0.0))
    t1, t2 = _tangents(axis)
    to_light = ((sin_t * np.cos(phi))[..., None] * t1 + (sin_t * np.sin(phi))[..., None] * t2
                + cos_t[..., None] * axis)
    # radiance 1 / (pi R^2) times the cone's solid angle 2 pi (1 - cos a); seen from the
    # floor, the occluder is never beyond the light
    return to_light, np.maximum(to_light[..., 1], 0.0) * 2.0 * one_minus / radius**2, np.inf


def _tangents(normal):
    """Two unit vectors [..., 3] completing unit normal [..., 3] to an orthonormal frame."""
    helper = np.where(np.abs(normal[..., :1]) < 0.9, [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    t1 = np.cross(normal, helper)
    t1 = t1 / np.linalg.norm(t1, axis=-1, keepdims=True)
    return t1, np.cross(normal, t1)


def _segment_sphere(origins, dirs, center, radius, limit):
    """Nearest t in (0, limit) with |origin + t dir - center| = radius: [...] (inf if none)."""
    rel = origins - center
    a = np.sum(dirs * dirs, -1)
    b = np.sum(rel * dirs, -1)
    disc = b * b - a * (np.sum(rel * rel, -1) - radius * radius)
    root = np.sqrt(np.maximum(disc, 0.0))
    t = np.stack([(-b - root) / a, (-b + root) / a])
    ok = (disc > 0) & (t > 1e-9) & (t < limit)
    return np.where(ok, t, np.inf).min(0)


def pixel_rays(camera: Camera):
    """NumPy float64 origins and directions [H, W, 3] of a perspective camera's pixel
    centres (OpenGL conventions, as camera_rays)."""
    eye, target, up = (np.asarray(getattr(camera, k), np.float64) for k in ("eye", "target", "up"))
    forward = (target - eye) / np.linalg.norm(target - eye)
    side = np.cross(forward, up)
    side /= np.linalg.norm(side)
    true_up = np.cross(side, forward)
    scale_y = 1.0 / np.tan(np.deg2rad(float(camera.fov_y)) / 2.0)
    aspect = camera.width / camera.height
    scale = (scale_y * float(camera.focal_ratio) / aspect, scale_y)
    offset = 2.0 * np.asarray(camera.shift, np.float64) / (camera.width, -camera.height)
    x = (2.0 * (np.arange(camera.width) + 0.5) / camera.width - 1.0 - offset[0]) / scale[0]
    y = (1.0 - 2.0 * (np.arange(camera.height) + 0.5) / camera.height - offset[1]) / scale[1]
    dirs = forward + x[None, :, None] * side + y[:, None, None] * true_up
    return np.broadcast_to(eye, dirs.shape), dirs

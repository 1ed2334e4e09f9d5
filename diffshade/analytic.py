"""Ground truth that is not our mesh renderer: an exact sphere, ray traced per pixel.

For each sample position in a pixel, the camera ray is intersected with the exact sphere
and the hit point is shaded with its exact normal by the same lighting core (`shade`),
so the difference between a mesh render and this image is the error of tessellation,
interpolation, resolution and rasterization alone. `supersample=s` shoots s x s rays per
pixel on a regular grid and averages the composited colour and the coverage.
"""

import jax
import jax.numpy as jnp

from diffshade.camera import Camera, view_dir_infinite
from diffshade.numerics import clamp01, dot, safe_normalize, safe_sqrt
from diffshade.shading import shade


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
    aspect = camera.width / camera.height
    if camera.projection == "perspective":
        half_h = jnp.tan(jnp.deg2rad(camera.fov_y) / 2.0)
        dirs = (ndc[..., :1] * half_h * aspect * side + ndc[..., 1:] * half_h * up + forward)
        return jnp.broadcast_to(camera.eye, dirs.shape), safe_normalize(dirs)
    half_h = camera.ortho_height / 2.0
    origins = camera.eye + ndc[..., :1] * half_h * aspect * side + ndc[..., 1:] * half_h * up
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
    dtype = cam.eye.dtype
    center = jnp.asarray(center, dtype)
    ndc = _sample_ndc(cam.width, cam.height, supersample, dtype)
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

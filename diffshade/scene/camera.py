"""Camera: look-at view, perspective or orthographic projection, and image size.

`Camera` is a frozen pytree. The eye, target, up, field of view and clip planes are array
leaves (differentiable); the image size and projection kind are static (they choose shapes
and code paths). Conventions (OpenGL): right-handed, the camera looks down -z in eye space,
NDC in [-1, 1]^3, image rows from the top, pixel centres at half-integers.
"""

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.numerics import float_dtype, representable, safe_normalize

PROJECTIONS = ("perspective", "orthographic")
#: The largest image side accepted, in pixels (OpenGL's usual GL_MAX_VIEWPORT_DIMS): a
#: typo such as 10**30 is refused here rather than failing deep inside XLA.
MAX_IMAGE_SIZE = 16384


@partial(jax.tree_util.register_dataclass,
         data_fields=["eye", "target", "up", "fov_y", "near", "far", "ortho_height"],
         meta_fields=["width", "height", "projection"])
@dataclasses.dataclass(frozen=True)
class Camera:
    """eye, target, up: [3] float; fov_y: [] degrees; near, far: [] > 0;
    ortho_height: [] world units spanned vertically by an orthographic view;
    width, height: static ints (pixels); projection: 'perspective' | 'orthographic'."""

    eye: jax.Array
    target: jax.Array
    up: jax.Array
    fov_y: jax.Array
    near: jax.Array
    far: jax.Array
    ortho_height: jax.Array
    width: int
    height: int
    projection: str = "perspective"


def _floats(name, value, expected):
    """value as a float64 array, or ValueError "name: got value; expected ..." (a string,
    None or a ragged sequence is not a number)."""
    try:
        if isinstance(value, (str, bytes)) or value is None:
            raise TypeError(type(value).__name__)
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: got {value!r}; expected {expected}") from None


def _vec3(name, value):
    arr = _floats(name, value, "3 finite numbers")
    if arr.shape != (3,) or not np.all(representable(arr)):
        raise ValueError(f"{name}: got {value!r}; expected 3 finite numbers")
    return arr


def _scalar(name, value, expected):
    """value as a finite float, or ValueError naming `name`."""
    arr = _floats(name, value, expected)
    if arr.shape != () or not representable(arr):
        raise ValueError(f"{name}: got {value!r}; expected {expected}")
    return float(arr)


def check_image_size(name, value):
    """value as an int image side in [1, MAX_IMAGE_SIZE], or ValueError naming `name`."""
    if (isinstance(value, bool) or not isinstance(value, (int, np.integer))
            or not 0 < value <= MAX_IMAGE_SIZE):
        raise ValueError(f"{name}: got {value!r}; expected a positive integer of pixels, at "
                         f"most {MAX_IMAGE_SIZE}")
    return int(value)


def _check_look_at(eye, target, up):
    forward = target - eye
    if np.linalg.norm(forward) < 1e-12:
        raise ValueError(f"eye, target: both are {eye.tolist()}; expected distinct points")
    if np.linalg.norm(up) < 1e-12:
        raise ValueError(f"up: got {up.tolist()}; expected a non-zero vector")
    scale = np.linalg.norm(forward) * np.linalg.norm(up) + 1e-300
    sin = np.linalg.norm(np.cross(forward, up)) / scale
    if sin < 1e-6:
        raise ValueError(f"up: {up.tolist()} is parallel to the view direction "
                         f"{forward.tolist()}; expected a vector not parallel to it")


def look_at(eye, target, up=(0.0, 1.0, 0.0), *, width=256, height=256, fov_y=45.0,
            near=0.1, far=100.0, projection="perspective", ortho_height=2.0) -> Camera:
    """Build a validated Camera. fov_y in degrees, in (0, 180); 0 < near < far."""
    eye, target, up = _vec3("eye", eye), _vec3("target", target), _vec3("up", up)
    _check_look_at(eye, target, up)
    width, height = check_image_size("width", width), check_image_size("height", height)
    if projection not in PROJECTIONS:
        raise ValueError(f"projection: got {projection!r}; expected one of {PROJECTIONS}")
    if not 0.0 < _scalar("fov_y", fov_y, "degrees in (0, 180)") < 180.0:
        raise ValueError(f"fov_y: got {fov_y!r}; expected degrees in (0, 180)")
    expected = "a finite number with 0 < near < far"
    if not 0.0 < _scalar("near", near, expected) < _scalar("far", far, expected):
        raise ValueError(f"near, far: got near={near!r}, far={far!r}; expected 0 < near < far")
    if not _scalar("ortho_height", ortho_height, "a positive number") > 0:
        raise ValueError(f"ortho_height: got {ortho_height!r}; expected a positive number")
    arr = partial(jnp.asarray, dtype=float_dtype())
    return Camera(arr(eye), arr(target), arr(up), arr(fov_y), arr(near), arr(far),
                  arr(ortho_height), width, height, projection)


def view_matrix(camera: Camera):
    """World -> eye rigid transform: [4, 4] float (gluLookAt)."""
    forward = safe_normalize(camera.target - camera.eye)
    side = safe_normalize(jnp.cross(forward, camera.up))
    true_up = jnp.cross(side, forward)
    rot = jnp.stack([side, true_up, -forward])
    trans = -rot @ camera.eye
    top = jnp.concatenate([rot, trans[:, None]], axis=1)
    return jnp.concatenate([top, jnp.array([[0.0, 0.0, 0.0, 1.0]], top.dtype)], axis=0)


def projection_matrix(camera: Camera):
    """Eye -> clip: [4, 4] float (gluPerspective or glOrtho, aspect = width / height)."""
    aspect = camera.width / camera.height
    n, f = camera.near, camera.far
    depth = jnp.stack([-(f + n) / (f - n), -2.0 * f * n / (f - n)])
    if camera.projection == "perspective":
        cot = 1.0 / jnp.tan(jnp.deg2rad(camera.fov_y) / 2.0)
        rows = [[cot / aspect, 0, 0, 0], [0, cot, 0, 0], [0, 0, depth[0], depth[1]], [0, 0, -1, 0]]
    else:
        half_h = camera.ortho_height / 2.0
        rows = [[1.0 / (half_h * aspect), 0, 0, 0], [0, 1.0 / half_h, 0, 0],
                [0, 0, -2.0 / (f - n), -(f + n) / (f - n)], [0, 0, 0, 1]]
    dtype = camera.near.dtype
    return jnp.stack([jnp.stack([jnp.asarray(x, dtype=dtype) for x in r]) for r in rows])


def view_dir_infinite(camera: Camera):
    """World-space direction of eye-space +z (OpenGL's infinite viewer): [3] float."""
    return -safe_normalize(camera.target - camera.eye)


def pixel_centers_ndc(width: int, height: int, dtype=jnp.float32):
    """NDC (x, y) of each pixel centre: [H, W, 2]; row 0 is the top (y = +1 side)."""
    xs = (2.0 * (jnp.arange(width, dtype=dtype) + 0.5) / width) - 1.0
    ys = 1.0 - (2.0 * (jnp.arange(height, dtype=dtype) + 0.5) / height)
    return jnp.stack(jnp.meshgrid(xs, ys, indexing="xy"), axis=-1)

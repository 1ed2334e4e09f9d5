"""Camera: look-at view, perspective or orthographic projection, and image size.

`Camera` is a frozen pytree. The eye, target, up, field of view, clip planes, principal
point shift, focal ratio and lens distortion are array leaves (differentiable); the image
size and projection kind are static (they choose shapes and code paths). Conventions
(OpenGL): right-handed, the camera looks down -z in eye space, NDC in [-1, 1]^3, image rows
from the top, pixel centres at half-integers. A calibrated camera (fx != fy, an off-centre
principal point) is the same Camera with a non-zero `shift` and `focal_ratio` != 1
(scene.calibration converts to and from OpenCV's K, R, t). `dist` only describes the
photos: the renderer draws the undistorted (pinhole) image.
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
#: The largest factor by which a camera's projection scales eye space into NDC
#: (1 / tan(fov_y / 2), 2 / ortho_height, an OpenCV camera's 2 fx / width and 2 fy /
#: height): the rasterizer multiplies clip coordinates in pairs and triples, and beyond
#: ~1e17 those overflow float32 for a scene a few units across (a fov_y of 1e-20 degrees
#: scales by 1e22: its images were empty or wrong). 1e8 is a lens of a 10^-6 degree view
#: (or an ortho_height of 2e-8), far past any real one.
MAX_LENS_SCALE = 1e8
#: fov_y's lower bound in degrees: 1 / tan(fov_y / 2) = MAX_LENS_SCALE
MIN_FOV_Y = float(np.rad2deg(2.0 * np.arctan(1.0 / MAX_LENS_SCALE)))


@partial(jax.tree_util.register_dataclass,
         data_fields=["eye", "target", "up", "fov_y", "near", "far", "ortho_height", "shift",
                      "focal_ratio", "dist"],
         meta_fields=["width", "height", "projection"])
@dataclasses.dataclass(frozen=True)
class Camera:
    """eye, target, up: [3] float; fov_y: [] degrees; near, far: [] > 0;
    ortho_height: [] world units spanned vertically by an orthographic view;
    shift: [2] pixels, the principal point minus the image centre (x right, y down);
    focal_ratio: [] horizontal over vertical focal length (fx / fy); dist: [5] OpenCV's
    (k1, k2, p1, p2, k3) of the photos (the renderer ignores it);
    width, height: static ints (pixels); projection: 'perspective' | 'orthographic'."""

    eye: jax.Array
    target: jax.Array
    up: jax.Array
    fov_y: jax.Array
    near: jax.Array
    far: jax.Array
    ortho_height: jax.Array
    shift: jax.Array
    focal_ratio: jax.Array
    dist: jax.Array
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
    """Build a validated Camera. fov_y in degrees, in [MIN_FOV_Y, 180) (about 1.1e-6);
    ortho_height >= 2e-8 (MAX_LENS_SCALE); 0 < near < far."""
    eye, target, up = _vec3("eye", eye), _vec3("target", target), _vec3("up", up)
    _check_look_at(eye, target, up)
    width, height = check_image_size("width", width), check_image_size("height", height)
    if projection not in PROJECTIONS:
        raise ValueError(f"projection: got {projection!r}; expected one of {PROJECTIONS}")
    if not MIN_FOV_Y <= _scalar("fov_y", fov_y, f"degrees in [{MIN_FOV_Y:.4g}, 180)") < 180.0:
        raise ValueError(f"fov_y: got {fov_y!r}; expected degrees in [{MIN_FOV_Y:.4g}, 180) "
                         f"(a narrower view scales eye space by more than {MAX_LENS_SCALE:g}, "
                         "past what float32 clip coordinates hold)")
    expected = "a finite number with 0 < near < far"
    if not 0.0 < _scalar("near", near, expected) < _scalar("far", far, expected):
        raise ValueError(f"near, far: got near={near!r}, far={far!r}; expected 0 < near < far")
    if not _scalar("ortho_height", ortho_height, "a positive number") >= 2.0 / MAX_LENS_SCALE:
        raise ValueError(f"ortho_height: got {ortho_height!r}; expected a number >= "
                         f"{2.0 / MAX_LENS_SCALE:g} (a smaller one scales eye space by more "
                         f"than {MAX_LENS_SCALE:g}, past what float32 clip coordinates hold)")
    arr = partial(jnp.asarray, dtype=float_dtype())
    return Camera(arr(eye), arr(target), arr(up), arr(fov_y), arr(near), arr(far),
                  arr(ortho_height), arr((0.0, 0.0)), arr(1.0), arr(np.zeros(5)), width,
                  height, projection)


def view_matrix(camera: Camera):
    """World -> eye rigid transform: [4, 4] float (gluLookAt)."""
    forward = safe_normalize(camera.target - camera.eye)
    side = safe_normalize(jnp.cross(forward, camera.up))
    true_up = jnp.cross(side, forward)
    rot = jnp.stack([side, true_up, -forward])
    trans = -rot @ camera.eye
    top = jnp.concatenate([rot, trans[:, None]], axis=1)
    return jnp.concatenate([top, jnp.array([[0.0, 0.0, 0.0, 1.0]], top.dtype)], axis=0)


def lens(camera: Camera):
    """(scale [2], offset [2]) mapping eye space to NDC: x_ndc = scale * x + offset, where x
    is (x_eye, y_eye) / -z_eye (perspective) or (x_eye, y_eye) (orthographic)."""
    aspect = camera.width / camera.height
    if camera.projection == "perspective":
        scale_y = 1.0 / jnp.tan(jnp.deg2rad(camera.fov_y) / 2.0)
    else:
        scale_y = 2.0 / camera.ortho_height
    scale = jnp.stack([scale_y * camera.focal_ratio / aspect, scale_y])
    # pixels -> NDC: x doubles over the width; y doubles over the height and flips
    offset = 2.0 * camera.shift * jnp.array([1.0 / camera.width, -1.0 / camera.height],
                                            camera.shift.dtype)
    return scale, offset


def projection_matrix(camera: Camera):
    """Eye -> clip: [4, 4] float (gluPerspective or glOrtho, aspect = width / height, with
    the principal point shifted off the image centre and fx != fy where the camera says)."""
    (sx, sy), (ox, oy) = lens(camera)
    n, f = camera.near, camera.far
    depth = jnp.stack([-(f + n) / (f - n), -2.0 * f * n / (f - n)])
    if camera.projection == "perspective":
        rows = [[sx, 0, -ox, 0], [0, sy, -oy, 0], [0, 0, depth[0], depth[1]], [0, 0, -1, 0]]
    else:
        rows = [[sx, 0, 0, ox], [0, sy, 0, oy],
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

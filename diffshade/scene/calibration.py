"""Cameras as calibrations give them: OpenCV's K, R, t, image size and lens distortion.

OpenCV's conventions, exactly: x_cam = R x_world + t; the camera looks along +z with x
right and y down; a point projects to u = fx x'' + cx, v = fy y'' + cy, where (x'', y'')
are the normalized coordinates (x_cam / z_cam, y_cam / z_cam) distorted by the
radial-tangential model dist = (k1, k2, p1, p2[, k3]); the centre of the top-left pixel is
(0, 0) (diffshade's pixel centres sit at half-integers: cx = W / 2 - 0.5 is the image
centre). Skew is 0.

`camera_from_opencv` validates at the boundary and builds a `Camera` (the pose as
eye/target/up, the intrinsics as fov_y, focal_ratio and shift); `camera_to_opencv` is the
inverse. `opencv_pose` and `with_pose` are the differentiable maps between a Camera and
(R, t) (pose refinement goes through them). `distort` is the lens model; `check_unfolded`
refuses a distortion whose radial term stops increasing inside the image (it would fold
the image over). A camera renders its pinhole image; io.undistort resamples photos into it.
"""

import dataclasses
from functools import partial

import jax.numpy as jnp
import numpy as np

from diffshade.numerics import float_dtype
from diffshade.scene.camera import (
    MAX_LENS_SCALE,
    Camera,
    check_image_size,
    lens,
    look_at,
    view_matrix,
)

#: how far R^T R may be from the identity (a calibration's R, written with ~7 digits)
ROTATION_TOLERANCE = 1e-6
_GL_FROM_CV = np.diag([1.0, -1.0, -1.0])  # eye axes: y down, z forward -> y up, z back


def _matrix(name, value, shapes, expected):
    """value as a finite float64 array of one of `shapes`, or ValueError naming `name`."""
    try:
        if isinstance(value, (str, bytes)) or value is None:
            raise TypeError(type(value).__name__)
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: got {_show(value)}; expected {expected}") from None
    if arr.shape not in shapes or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: got {_show(value)}; expected {expected}")
    return arr


def _show(value):
    text = repr(np.asarray(value).tolist() if not isinstance(value, (list, tuple)) else value)
    return text if len(text) <= 80 else text[:77] + "..."


def check_intrinsics(K):
    """K as [3, 3] float64: [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0 (finite),
    or ValueError naming K, its value and what was expected."""
    expected = "[[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with finite fx > 0, fy > 0 (no skew)"
    K = _matrix("K", K, [(3, 3)], expected)
    pattern = np.array([[1, 0, 1], [0, 1, 1], [0, 0, 0]], bool)
    if np.any(K[~pattern] != [0, 0, 0, 0, 1]) or not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f"K: got {_show(K)}; expected {expected}")
    return K


def check_rotation(R):
    """R as [3, 3] float64 with R^T R = I and det R = +1 (to ROTATION_TOLERANCE)."""
    expected = f"a rotation matrix (R^T R = I to {ROTATION_TOLERANCE:g}, det R = +1)"
    R = _matrix("R", R, [(3, 3)], expected)
    error = np.max(np.abs(R.T @ R - np.eye(3)))
    if error > ROTATION_TOLERANCE or np.linalg.det(R) < 0:
        detail = f"det R = {np.linalg.det(R):.6g}" if error <= ROTATION_TOLERANCE else \
            f"R^T R differs from I by {error:.3g}"
        raise ValueError(f"R: got {_show(R)} ({detail}); expected {expected}")
    return R


def _check_dist(dist):
    """dist as [5] float64 (k1, k2, p1, p2, k3); 4 values mean k3 = 0."""
    expected = "[k1, k2, p1, p2] or [k1, k2, p1, p2, k3] (finite numbers)"
    if dist is None:
        return np.zeros(5)
    arr = _matrix("dist", dist, [(4,), (5,)], expected)
    return np.concatenate([arr, np.zeros(5 - arr.size)])


def _corner_radius(K, width, height):
    """The largest normalized radius of the image (its outer corners, pixel edges)."""
    us = np.array([-0.5, width - 0.5]) - K[0, 2]
    vs = np.array([-0.5, height - 0.5]) - K[1, 2]
    return float(np.hypot(us[:, None] / K[0, 0], vs[None, :] / K[1, 1]).max())


def check_unfolded(dist, K, width, height):
    """ValueError unless r (1 + k1 r^2 + k2 r^4 + k3 r^6) increases for every radius r of
    the image (up to its corners): else undistorting folds part of the image over."""
    k1, k2, _, _, k3 = dist
    r_max = _corner_radius(K, width, height)
    # d/dr of the radial model, a cubic in s = r^2; its real roots in (0, r_max^2]
    slope = np.polynomial.Polynomial([1.0, 3.0 * k1, 5.0 * k2, 7.0 * k3])
    roots = [s.real for s in slope.roots() if abs(s.imag) < 1e-12 and 0 < s.real <= r_max**2]
    if roots or slope(r_max**2) <= 0:
        where = np.sqrt(min(roots)) if roots else r_max
        raise ValueError(f"dist: got {dist.tolist()}; expected a radial model r (1 + k1 r^2 "
                         f"+ k2 r^4 + k3 r^6) increasing over the image (r up to "
                         f"{r_max:.4g}), but it stops increasing at r = {where:.4g} (the "
                         "image would fold over)")


def distort(dist, xy):
    """OpenCV's radial-tangential model in NumPy float64: dist [5] (k1, k2, p1, p2, k3);
    normalized coordinates [..., 2] -> distorted [..., 2]."""
    k1, k2, p1, p2, k3 = np.asarray(dist, np.float64)
    xy = np.asarray(xy, np.float64)
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([x * radial + dx, y * radial + dy], axis=-1)


def with_pose(camera: Camera, R, t) -> Camera:
    """camera moved to the OpenCV pose (R [3, 3], t [3]): eye = -R^T t, looking along R's
    third row, up = -(its second row). Differentiable in R and t (no validation)."""
    R, t = jnp.asarray(R, camera.eye.dtype), jnp.asarray(t, camera.eye.dtype)
    eye = -R.T @ t
    return dataclasses.replace(camera, eye=eye, target=eye + R[2], up=-R[1])


def opencv_pose(camera: Camera):
    """(R [3, 3], t [3]) of the camera in OpenCV's convention (x_cam = R x + t, +z
    forward, y down). Differentiable."""
    view = view_matrix(camera)
    flip = jnp.asarray(_GL_FROM_CV, view.dtype)
    return flip @ view[:3, :3], flip @ view[:3, 3]


def camera_from_opencv(K, R, t, width, height, dist=None, *, near=0.1, far=100.0) -> Camera:
    """A validated perspective Camera from an OpenCV calibration: K [3, 3] intrinsics,
    R [3, 3] rotation and t [3] translation (world -> camera), image size in pixels,
    dist (k1, k2, p1, p2[, k3]) or None; near, far: clip distances along the view axis.

    Raises ValueError naming the argument (K, R, t, dist, ...), its value and what was
    expected: K not [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, R not a
    rotation to 1e-6, t not finite, a distortion that folds the image over.
    """
    K, R = check_intrinsics(K), check_rotation(R)
    t = _matrix("t", t, [(3,)], "3 finite numbers")
    width, height = check_image_size("width", width), check_image_size("height", height)
    dist = _check_dist(dist)
    check_unfolded(dist, K, width, height)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    for focal, size, which in ((fx, width, "fx"), (fy, height, "fy")):
        if 2.0 * focal / size > MAX_LENS_SCALE:
            raise ValueError(f"K: {which} = {float(focal)!r} pixels for an image {size} pixels "
                             f"across; expected at most {MAX_LENS_SCALE * size / 2.0:g} (a "
                             f"longer focal length scales eye space by more than "
                             f"{MAX_LENS_SCALE:g}, past what float32 clip coordinates hold)")
    fov_y = np.rad2deg(2.0 * np.arctan(height / (2.0 * fy)))
    eye = -R.T @ t
    camera = look_at(eye, eye + R[2], -R[1], width=width, height=height, fov_y=fov_y,
                     near=near, far=far)
    arr = partial(jnp.asarray, dtype=float_dtype())
    # pixel centres: OpenCV's at integers, diffshade's at half-integers
    shift = (cx + 0.5 - width / 2.0, cy + 0.5 - height / 2.0)
    return dataclasses.replace(camera, shift=arr(shift), focal_ratio=arr(fx / fy),
                               dist=arr(dist))


def opencv_intrinsics(camera: Camera):
    """K [3, 3] of a perspective camera (OpenCV's pixel convention). Differentiable."""
    if camera.projection != "perspective":
        raise ValueError(f"camera.projection: got {camera.projection!r}; expected "
                         "'perspective' (OpenCV's K describes a pinhole camera)")
    scale, _ = lens(camera)
    fy = scale[1] * camera.height / 2.0
    cx = camera.width / 2.0 + camera.shift[0] - 0.5
    cy = camera.height / 2.0 + camera.shift[1] - 0.5
    zero, one = jnp.zeros_like(fy), jnp.ones_like(fy)
    return jnp.stack([jnp.stack([fy * camera.focal_ratio, zero, cx]),
                      jnp.stack([zero, fy, cy]), jnp.stack([zero, zero, one])])


def camera_to_opencv(camera: Camera) -> dict:
    """{"K", "R", "t", "width", "height", "dist"} of a perspective camera, as float64
    NumPy arrays and ints: the inverse of camera_from_opencv."""
    R, t = opencv_pose(camera)
    as64 = partial(np.asarray, dtype=np.float64)
    return {"K": as64(opencv_intrinsics(camera)), "R": as64(R), "t": as64(t),
            "width": camera.width, "height": camera.height, "dist": as64(camera.dist)}

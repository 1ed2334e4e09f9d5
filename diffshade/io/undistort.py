"""Lens distortion on images: a photo resampled into its camera's pinhole image, and back.

diffshade renders the pinhole image of a camera (its K, no distortion). A photo taken
through a lens with OpenCV distortion `camera.dist` is brought to that image by
`undistort_image`: pinhole pixel (u, v) takes the photo's colour at the distorted position
(fx x'' + cx, fy y'' + cy), (x'', y'') = distort((u - cx) / fx, (v - cy) / fy), sampled
bilinearly in linear colour. `undistort_mask` says which pinhole pixels that sample fully
covers (all four neighbours inside the photo and counted), so a resampled edge pixel never
enters a fit. `distort_image` is the inverse (synthetic photos, tests), with
`undistort_points` inverting the lens model by fixed-point iteration, as OpenCV's
undistortPoints does. Coordinates here are OpenCV's (pixel centres at integers);
docs/calibrated-cameras.md measures what the resampling costs.
"""

import dataclasses

import jax.numpy as jnp
import numpy as np

from diffshade.scene.calibration import distort, opencv_intrinsics
from diffshade.scene.camera import Camera


def pinhole(camera: Camera) -> Camera:
    """camera without lens distortion: the image the renderer draws."""
    return dataclasses.replace(camera, dist=jnp.zeros_like(camera.dist))


def _normalized_grid(K, width, height):
    """Normalized coordinates of every pixel centre: [H, W, 2] float64."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]], axis=-1)


def _to_pixels(K, xy):
    return xy[..., 0] * K[0, 0] + K[0, 2], xy[..., 1] * K[1, 1] + K[1, 2]


def _calibration(camera):
    """(K [3, 3], dist [5]) as float64 NumPy arrays."""
    return (np.asarray(opencv_intrinsics(camera), np.float64),
            np.asarray(camera.dist, np.float64))


def _neighbours(u, v, width, height):
    """The four pixels around (u, v) [H', W'] (pixel centres at integers): column and row
    indices (u0, u1, v0, v1), weights (wu, wv) and [H', W'] bool, True where (u, v) lies
    inside the image (all four neighbours exist)."""
    inside = (u >= 0) & (u <= width - 1) & (v >= 0) & (v <= height - 1)
    u0 = np.clip(np.floor(u), 0, max(width - 2, 0)).astype(int)
    v0 = np.clip(np.floor(v), 0, max(height - 2, 0)).astype(int)
    u1, v1 = np.minimum(u0 + 1, width - 1), np.minimum(v0 + 1, height - 1)
    return (u0, u1, v0, v1), (np.clip(u - u0, 0, 1), np.clip(v - v0, 0, 1)), inside


def _bilinear(image, u, v):
    """image [H, W, C] sampled at (u, v): [H', W', C], and where it is inside."""
    (u0, u1, v0, v1), (wu, wv), inside = _neighbours(u, v, *image.shape[1::-1])
    wu, wv = wu[..., None], wv[..., None]
    top = image[v0, u0] * (1 - wu) + image[v0, u1] * wu
    bottom = image[v1, u0] * (1 - wu) + image[v1, u1] * wu
    return top * (1 - wv) + bottom * wv, inside


def _photo_positions(camera):
    """Where each pinhole pixel lies in the photo: (u, v), each [H, W] float64."""
    K, dist = _calibration(camera)
    grid = _normalized_grid(K, camera.width, camera.height)
    return _to_pixels(K, distort(dist, grid))


def undistort_image(image, camera: Camera) -> np.ndarray:
    """The pinhole image [H, W, C] float of a photo [H, W, C] (linear colours) taken by
    camera (with its dist); pixels whose sample leaves the photo are 0."""
    u, v = _photo_positions(camera)
    colours, inside = _bilinear(np.asarray(image, np.float64), u, v)
    return np.where(inside[..., None], colours, 0.0).astype(np.asarray(image).dtype)


def undistort_mask(mask, camera: Camera) -> np.ndarray:
    """[H, W] bool: the pinhole pixels whose photo sample lies inside the photo with all
    four neighbours counted in mask [H, W] bool (None: every photo pixel counts)."""
    counted = np.ones((camera.height, camera.width), bool) if mask is None else \
        np.asarray(mask, bool)
    (u0, u1, v0, v1), _, inside = _neighbours(*_photo_positions(camera), camera.width,
                                              camera.height)
    return (inside & counted[v0, u0] & counted[v0, u1] & counted[v1, u0]
            & counted[v1, u1])


def undistort_points(dist, distorted, iterations=30):
    """Normalized coordinates [..., 2] whose distortion is `distorted` [..., 2] (fixed-point
    iteration; exact to float precision for mild, unfolded distortion)."""
    dist, distorted = np.asarray(dist, np.float64), np.asarray(distorted, np.float64)
    xy = distorted.copy()
    for _ in range(iterations):
        xy = xy + (distorted - distort(dist, xy))
    return xy


def distort_image(image, camera: Camera) -> np.ndarray:
    """The photo [H, W, C] that camera (with its dist) takes of the pinhole image
    [H, W, C]: bilinear; photo pixels that see outside the pinhole image are 0."""
    K, dist = _calibration(camera)
    grid = undistort_points(dist, _normalized_grid(K, camera.width, camera.height))
    colours, inside = _bilinear(np.asarray(image, np.float64), *_to_pixels(K, grid))
    return np.where(inside[..., None], colours, 0.0).astype(np.asarray(image).dtype)

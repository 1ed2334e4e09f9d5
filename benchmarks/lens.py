"""The lens of benchmarks/capture.py, in NumPy: OpenCV's radial-tangential model inverted,
and a photo made from a finer square-pixel pinhole image through it.

Conventions are OpenCV's (docs/calibrated-cameras.md): the centre of pixel (0, 0) at
(0, 0); normalized coordinates (x, y) = ((u - cx) / fx, (v - cy) / fy) before distortion.
"""

import math

import numpy as np


def undistort_normalized(dist, xd, yd, iterations=60):
    """OpenCV's radial-tangential model inverted by fixed-point iteration (as
    cv::undistortPoints does): the normalized pinhole coordinates (x, y) whose distortion is
    (xd, yd). Converges for mild distortion (the model close to the identity)."""
    k1, k2, p1, p2, *rest = list(dist) + [0.0] * (5 - len(dist))
    k3 = rest[0]
    x, y = np.array(xd, np.float64), np.array(yd, np.float64)
    for _ in range(iterations):
        r2 = x * x + y * y
        radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
        dy = p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
        x, y = (xd - dx) / radial, (yd - dy) / radial
    return x, y


def bilinear_corners(shape, u, v):
    """The four (rows, columns, weights) that bilinear interpolation at pixel positions
    (u, v) (the centre of pixel (0, 0) at (0, 0)) of an image of `shape` [H, W, ...] takes;
    every position must lie inside the image's pixel centres."""
    height, width = shape[:2]
    if u.min() < 0 or v.min() < 0 or u.max() > width - 1 or v.max() > height - 1:
        raise ValueError("a sample falls outside the image it is taken from")
    u0 = np.minimum(np.floor(u).astype(int), width - 2)
    v0 = np.minimum(np.floor(v).astype(int), height - 2)
    fu, fv = u - u0, v - v0
    return [(v0, u0, (1 - fu) * (1 - fv)), (v0, u0 + 1, fu * (1 - fv)),
            (v0 + 1, u0, (1 - fu) * fv), (v0 + 1, u0 + 1, fu * fv)]


def bilinear(image, u, v):
    """image [H, W, C] sampled bilinearly at (u, v)."""
    return sum(w[..., None] * image[rows, cols]
               for rows, cols, w in bilinear_corners(image.shape, u, v))


def sub_pixel_grid(width, height, samples):
    """Photo positions (u, v), each [H, W, S] for S = samples^2 points spread evenly over
    each pixel."""
    offsets = (np.arange(samples) + 0.5) / samples - 0.5
    du, dv = (a.ravel() for a in np.meshgrid(offsets, offsets))
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    return u[..., None] + du, v[..., None] + dv


def pinhole_positions(K, dist, width, height, samples):
    """Where each photo sub-pixel's ray is, in normalized pinhole coordinates (x, y), each
    [H, W, S]: the photo position's normalized distorted coordinates, undistorted."""
    K = np.asarray(K, np.float64)
    u, v = sub_pixel_grid(width, height, samples)
    return undistort_normalized(dist, (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1])


def pinhole_frame(K, dist, width, height, samples, oversample):
    """(focal, width, height) of a square-pixel pinhole image centred on the optical axis
    (centre of pixel (0, 0) at (0, 0), so the axis at (W/2 - 0.5, H/2 - 0.5)) that is
    `oversample` times finer than the photo and holds every photo sub-pixel's ray with two
    pixels to spare."""
    x, y = pinhole_positions(K, dist, width, height, samples)
    focal = oversample * max(K[0][0], K[1][1])
    half_w = math.ceil(focal * np.abs(x).max() + 2.5)
    half_h = math.ceil(focal * np.abs(y).max() + 2.5)
    return focal, 2 * half_w, 2 * half_h


def lens_photo(pinhole_image, focal, K, dist, width, height, samples):
    """The photo [H, W, C] that a camera of intrinsics K and distortion `dist` takes of the
    scene whose square-pixel pinhole image (axis at its centre, focal length `focal` in its
    pixels) is `pinhole_image`: each photo pixel the mean of samples^2 sub-pixel values,
    each sampled bilinearly where its ray falls in the pinhole image."""
    x, y = pinhole_positions(K, dist, width, height, samples)
    big_h, big_w = pinhole_image.shape[:2]
    u, v = focal * x + (big_w / 2 - 0.5), focal * y + (big_h / 2 - 0.5)
    image = np.asarray(pinhole_image, np.float64)
    return np.stack([bilinear(image, u[..., i], v[..., i]) for i in range(u.shape[-1])],
                    0).mean(axis=0)

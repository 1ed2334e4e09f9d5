"""The texture lookup's host kernels (diffshade.host.texture_kernels) called directly on
many samples: blocks (_BLOCK) and parts (`chunks`) cut anywhere, a batch of textures in
one call, samples with no texture, textures of one texel, one row, one column and not
square, UVs on texel centres, on texel borders and outside [0, 1].

References, independent of the kernels: a naive per-sample loop over the four nearest
texel centres with its own wrap (values, and the texels' gradient as the sum of each
sample's cotangent times its weights), and float64 central differences of that loop (the
UVs' gradient).
"""

import math

import numpy as np
import pytest

from diffshade.host import texture_kernels

# ------------------------------------------------------------------- naive reference


def naive_corners(height, width, u, v, wrap):
    """[(flat texel index, weight)] of the four texels a sample at (u, v) blends: texel
    centres at ((i + 0.5) / width, 1 - (j + 0.5) / height), indices wrapped or clamped."""
    x, y = u * width - 0.5, (1.0 - v) * height - 0.5
    if wrap == "clamp":
        x, y = min(max(x, 0.0), width - 1.0), min(max(y, 0.0), height - 1.0)
    x0, y0 = math.floor(x), math.floor(y)
    fx, fy = x - x0, y - y0
    corners = []
    for dy, wy in ((0, 1 - fy), (1, fy)):
        for dx, wx in ((0, 1 - fx), (1, fx)):
            if wrap == "repeat":
                row, col = (y0 + dy) % height, (x0 + dx) % width
            else:
                row, col = min(y0 + dy, height - 1), min(x0 + dx, width - 1)
            corners.append((row * width + col, wy * wx))
    return corners


def naive_lookup(ids, uv, texels, height, width, wrap, g_out):
    """(values [M, C], texels' gradient [T, C] for the cotangent g_out [M, C]) by the
    naive loop; a sample with no texture (offset -1, or a texture past the texels) reads
    zeros and gives nothing."""
    values, g_texels = np.zeros(g_out.shape), np.zeros(texels.shape)
    for m, (base, (u, v)) in enumerate(zip(ids, uv, strict=True)):
        if base < 0 or base + height * width > len(texels):
            continue
        for index, weight in naive_corners(height, width, u, v, wrap):
            values[m] += weight * texels[base + index]
            g_texels[base + index] += weight * g_out[m]
    return values, g_texels


def naive_uv_gradient(ids, uv, texels, height, width, wrap, g_out, eps=1e-7):
    """d sum(g_out * values) / d uv [M, 2] by float64 central differences of the loop."""
    grad = np.zeros(uv.shape)
    for axis in range(2):
        step = np.zeros(2)
        step[axis] = eps
        plus = naive_lookup(ids, uv + step, texels, height, width, wrap, g_out)[0]
        minus = naive_lookup(ids, uv - step, texels, height, width, wrap, g_out)[0]
        grad[:, axis] = np.sum(g_out * (plus - minus), axis=1) / (2 * eps)
    return grad


# ------------------------------------------------------------------------- samples


def samples(height, width, batch, n_random, rng):
    """(ids [M], uv [M, 2], random [M] bool): for a batch of textures of height x width,
    the texel centres and borders of every texel (u = i / width and (i + 0.5) / width,
    likewise v), u and v exactly 0 and 1, and n_random random UVs in [-1.5, 2.5] (only
    these are `random`: the others sit on the lookup's kinks); offsets of the batch's
    textures, with some samples without one (-1) or one that would end past the texels."""
    us = np.concatenate([np.arange(2 * width + 1) / (2 * width), [0.0, 1.0]])
    vs = np.concatenate([np.arange(2 * height + 1) / (2 * height), [1.0, 0.0]])
    grid = np.stack(np.meshgrid(us, vs), -1).reshape(-1, 2)
    uv = np.concatenate([grid, rng.uniform(-1.5, 2.5, (n_random, 2))])
    random = np.arange(len(uv)) >= len(grid)
    ids = rng.integers(0, batch, len(uv)) * height * width
    ids[rng.random(len(uv)) < 0.1] = -1
    ids[rng.random(len(uv)) < 0.03] = batch * height * width  # past the texels
    return ids.astype(np.int32), uv, random


# square, non-square, one texel, one row, one column; the samples span several blocks
SIZES = [(8, 8), (3, 7), (1, 1), (1, 5), (4, 1)]


@pytest.mark.parametrize("wrap", ["repeat", "clamp"])
@pytest.mark.parametrize("height,width", SIZES)
def test_kernels_match_the_naive_loop_across_blocks_parts_and_a_batch(height, width, wrap):
    rng = np.random.default_rng(height * 10 + width)
    block = texture_kernels._BLOCK
    ids, uv, random = samples(height, width, 3, 2 * block + 77, rng)
    for channels in (3, 1):
        texels = rng.random((3 * height * width, channels))
        g_out = rng.normal(size=(len(uv), channels))
        want, want_g = naive_lookup(ids, uv, texels, height, width, wrap, g_out)
        want_uv = naive_uv_gradient(ids, uv, texels, height, width, wrap, g_out)
        args = (height, width, wrap == "clamp")
        valid = (ids >= 0) & (ids + height * width <= len(texels))
        for chunks in (1, 2, 3):
            got = texture_kernels.sample_forward(ids, uv, texels, *args, chunks)
            np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)
            g_uv, g_texels = texture_kernels.sample_backward(ids, uv, texels, g_out, *args,
                                                             True, chunks)
            np.testing.assert_allclose(g_texels, want_g, rtol=1e-12, atol=1e-12)
            # the UVs' gradient where the lookup is smooth, central differences' error
            np.testing.assert_allclose(g_uv[random], want_uv[random], rtol=1e-6, atol=1e-6)
            assert not np.any(g_uv[~valid])
            zeros, same = texture_kernels.sample_backward(ids, uv, texels, g_out, *args,
                                                          False, chunks)
            assert not np.any(zeros)
            np.testing.assert_array_equal(same, g_texels)


@pytest.mark.parametrize("wrap", ["repeat", "clamp"])
def test_float32_kernels_match_the_float64_loop(wrap):
    """The float32 path (the renders'), RGB: values and texels' gradient within float32
    rounding of the float64 loop."""
    rng = np.random.default_rng(7)
    height, width = 16, 24
    ids, uv, _ = samples(height, width, 2, 3 * texture_kernels._BLOCK, rng)
    texels = rng.random((2 * height * width, 3))
    g_out = rng.normal(size=(len(uv), 3))
    want, want_g = naive_lookup(ids, uv, texels, height, width, wrap, g_out)
    args = (height, width, wrap == "clamp")
    f32 = lambda x: x.astype(np.float32)
    got = texture_kernels.sample_forward(ids, f32(uv), f32(texels), *args, 2)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
    _, g_texels = texture_kernels.sample_backward(ids, f32(uv), f32(texels), f32(g_out),
                                                  *args, False, 2)
    np.testing.assert_allclose(g_texels, want_g, rtol=1e-4, atol=1e-4)

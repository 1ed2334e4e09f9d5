"""Texture lookup: bilinear sampling at UVs, and a material's textures read at its samples.

`sample_texture(texture, uv)` reads texels [H, W, C] at uv [..., 2] (v = 0 at the image's
bottom row, OBJ / OpenGL): the texel centres sit at ((i + 0.5) / W, 1 - (j + 0.5) / H) and
a UV between four of them blends them bilinearly (GL_LINEAR). Outside [0, 1] the
texture's wrap decides: 'repeat' takes u and v modulo 1 (blending across the edges),
'clamp' reads the edge texels. Every read index is in range whatever the UV (no
out-of-bounds gather), and the value is differentiable with respect to every texel (a
sample's four texels get its bilinear weights) and to the UV (piecewise linear).

Minification: there is no mip-mapping. A texel smaller than a pixel is read at the
pixel's sample points only, so a far or grazing textured surface aliases; render
supersampled (diffshade.pipeline.rendering.render_supersampled) to average more
samples per pixel (docs/textures.md says how many).

`textured_material(material, uv)` replaces each Texture field of a Material by its values
at the samples' UVs: kd and ks [..., 3], shininess [...]. A material without textures is
returned as it is: no texture code is traced.
"""

import dataclasses

import jax
import jax.numpy as jnp

from diffshade.raster.interpolation import interpolate_corners
from diffshade.scene.materials import TEXTURED_FIELDS, has_textures
from diffshade.scene.textures import Texture, is_texture

__all__ = ["sample_texture", "textured_material"]


def _axis(coord, size, wrap):
    """(index [...] int32 of the texel at or before coord, weight of the next one [...])
    for texel coordinate coord [...] (texel centres at integers) along an axis of `size`
    texels; which texel is next (wrapped or the edge) is _next's."""
    if wrap == "repeat":
        coord = jnp.mod(coord, size)
        # mod of a tiny negative number rounds to size itself: that is texel 0
        coord = jnp.where(coord >= size, coord - size, coord)
    else:
        coord = jnp.clip(coord, 0.0, size - 1.0)
    low = jnp.floor(coord)
    return low.astype(jnp.int32), coord - low


def _next(texels, axis, wrap):
    """Each texel's neighbour one step along axis (+1): wrapped ('repeat') or the edge
    texel itself ('clamp'). Shifts, not gathers: their transposes are shifts too."""
    if wrap == "repeat":
        return jnp.roll(texels, -1, axis)
    last = jax.lax.slice_in_dim(texels, texels.shape[axis] - 1, None, axis=axis)
    rest = jax.lax.slice_in_dim(texels, 1, None, axis=axis)
    return jnp.concatenate([rest, last], axis)


def _cell_columns(texture):
    """Each cell's two columns as the interpolation op's corners, [H * W, 3, 2C]: corner 0
    is the cell's left column (row, col) | (row + 1, col), corner 1 its right column
    (row, col + 1) | (row + 1, col + 1), neighbours by wrap; corner 2 is unused (zeros)."""
    texels, wrap = texture.texels, texture.wrap
    left = jnp.concatenate([texels, _next(texels, 0, wrap)], -1)
    right = _next(left, 1, wrap)
    corners = jnp.stack([left, right, jnp.zeros_like(left)], 2)
    return corners.reshape((-1, 3, corners.shape[-1]))


def sample_texture(texture: Texture, uv, host=None):
    """Bilinear value [..., C] of texture at uv [..., 2] (module docstring).

    The cells' columns are arranged once (shifts of the texture), and each sample reads
    its cell's two columns blended across (1 - fx, fx) in one pass of the fragment
    interpolation op (diffshade.raster.interpolation; host: its compiled kernels, default
    on the CPU backend), then blends the top and bottom rows (1 - fy, fy): the texels'
    gradient is that op's compiled scatter-add plus shifts, not an XLA scatter over the
    samples."""
    host = jax.default_backend() == "cpu" if host is None else host
    height, width, channels = texture.texels.shape
    x0, fx = _axis(uv[..., 0] * width - 0.5, width, texture.wrap)
    y0, fy = _axis((1.0 - uv[..., 1]) * height - 0.5, height, texture.wrap)
    corners = _cell_columns(texture)
    fx, fy = fx.astype(corners.dtype)[..., None], fy.astype(corners.dtype)[..., None]
    # as the op's [1, M, 1] fragments
    cells = (y0 * width + x0).reshape(1, -1, 1)
    weights = jnp.concatenate([1 - fx, fx, jnp.zeros_like(fx)], -1).reshape(1, -1, 1, 3)
    rows = interpolate_corners(cells, weights, corners, host=host)[0].reshape(
        uv.shape[:-1] + (2 * channels,))
    return (1 - fy) * rows[..., :channels] + fy * rows[..., channels:]


def textured_material(material, uv):
    """material with each Texture field read at uv [..., 2]: kd, ks [..., 3], shininess
    [...]; material itself (None included) when it has no texture."""
    if not has_textures(material):
        return material
    changes = {}
    for name in TEXTURED_FIELDS:
        value = getattr(material, name)
        if is_texture(value):
            sampled = sample_texture(value, uv)
            changes[name] = sampled[..., 0] if name == "shininess" else sampled
    return dataclasses.replace(material, **changes)

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

import jax.numpy as jnp

from diffshade.scene.materials import TEXTURED_FIELDS, has_textures
from diffshade.scene.textures import Texture, is_texture

__all__ = ["sample_texture", "textured_material"]


def _axis(coord, size, wrap):
    """(index0, index1 [...] int32, weight of index1 [...]) of texel coordinate coord
    [...] (texel centres at integers) along an axis of `size` texels."""
    if wrap == "repeat":
        coord = jnp.mod(coord, size)
        # mod of a tiny negative number rounds to size itself: that is texel 0
        coord = jnp.where(coord >= size, coord - size, coord)
        low = jnp.floor(coord)
        frac = coord - low
        low = low.astype(jnp.int32)
        return low, jnp.where(low + 1 >= size, 0, low + 1), frac
    coord = jnp.clip(coord, 0.0, size - 1.0)
    low = jnp.floor(coord)
    frac = coord - low
    low = low.astype(jnp.int32)
    return low, jnp.minimum(low + 1, size - 1), frac


def sample_texture(texture: Texture, uv):
    """Bilinear value [..., C] of texture at uv [..., 2] (module docstring)."""
    height, width, channels = texture.texels.shape
    x = uv[..., 0] * width - 0.5
    y = (1.0 - uv[..., 1]) * height - 0.5
    x0, x1, fx = _axis(x, width, texture.wrap)
    y0, y1, fy = _axis(y, height, texture.wrap)
    flat = texture.texels.reshape(-1, channels)
    # the four texels in one gather (and so one scatter-add in the backward pass)
    index = jnp.stack([y0 * width + x0, y0 * width + x1, y1 * width + x0, y1 * width + x1], -1)
    texels = jnp.take(flat, index, axis=0, mode="clip")
    fx, fy = fx[..., None].astype(flat.dtype), fy[..., None].astype(flat.dtype)
    top = texels[..., 0, :] * (1.0 - fx) + texels[..., 1, :] * fx
    bottom = texels[..., 2, :] * (1.0 - fx) + texels[..., 3, :] * fx
    return top * (1.0 - fy) + bottom * fy


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

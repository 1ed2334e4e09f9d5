"""Texture lookup: bilinear sampling at UVs, and a material's textures read at its samples.

`sample_texture(texture, uv)` reads texels [H, W, C] at uv [..., 2] (v = 0 at the image's
bottom row, OBJ / OpenGL): the texel centres sit at ((i + 0.5) / W, 1 - (j + 0.5) / H) and
a UV between four of them blends them bilinearly (GL_LINEAR). Outside [0, 1] the
texture's wrap decides: 'repeat' takes u and v modulo 1 (blending across the edges),
'clamp' reads the edge texels. Every read index is in range whatever the UV (no
out-of-bounds gather), and the value is differentiable with respect to every texel (a
sample's four texels get its bilinear weights) and to the UV (piecewise linear).

The lookup is a FragmentOp (diffshade.host.hostop: every JAX transform kept) whose host
kernels (diffshade.host.texture_kernels) make one pass over the samples forward, and one
backward that scatters each cotangent straight into the texels [H, W, C] and computes the
UVs' gradient only where reverse mode needs it; in jax.numpy (another backend, or
kernels='jax') it is four gathers, and XLA's scatter-add as their transpose.

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
from jax.interpreters import ad

from diffshade.host import fragment_kernels, texture_kernels
from diffshade.host.hostop import FragmentOp
from diffshade.scene.materials import TEXTURED_FIELDS, has_textures
from diffshade.scene.textures import Texture, is_texture

__all__ = ["sample_texture", "textured_material"]


def _axis(coord, size, clamp):
    """(index [...] int32 of the texel at or before coord, index of the next one (wrapped
    or the edge), weight of the next one [...]) for texel coordinate coord [...] (texel
    centres at integers) along an axis of `size` texels. Indices are in range whatever
    coord (a NaN coord gives a NaN weight)."""
    if clamp:
        coord = jnp.clip(coord, 0.0, size - 1.0)
    else:
        coord = jnp.mod(coord, size)
        # mod of a tiny negative number rounds to size itself: that is texel 0
        coord = jnp.where(coord >= size, coord - size, coord)
    low = jnp.floor(coord)
    index = jnp.clip(low.astype(jnp.int32), 0, size - 1)
    if clamp:
        return index, jnp.minimum(index + 1, size - 1), coord - low
    return index, jnp.where(index + 1 == size, 0, index + 1), coord - low


def _sample_native(ids, uv, texels, *, height, width, clamp, uv_grad=1):
    """The lookup of texture_kernels (its conventions) in jax.numpy: ids [M] int32, uv [M,
    2], texels [T, C] -> ([M, C],)."""
    x0, x1, fx = _axis(uv[..., 0] * width - 0.5, width, clamp)
    y0, y1, fy = _axis((1.0 - uv[..., 1]) * height - 0.5, height, clamp)
    base = jnp.maximum(ids, 0)
    fx, fy = fx.astype(texels.dtype)[..., None], fy.astype(texels.dtype)[..., None]

    def row(y):
        at = lambda x: jnp.take(texels, base + y * width + x, axis=0, mode="clip")
        return (1 - fx) * at(x0) + fx * at(x1)
    value = (1 - fy) * row(y0) + fy * row(y1)
    return (jnp.where((ids >= 0)[..., None], value, 0.0),)


def _sample_avals(ids, uv, texels, **params):
    return (jax.ShapeDtypeStruct(ids.shape + texels.shape[-1:], texels.dtype),)


def _sample_forward(ids, uv, texels, *, height, width, clamp, uv_grad=1):
    return (texture_kernels.sample_forward(ids.reshape(-1), uv.reshape(-1, 2), texels, height,
                                           width, bool(clamp), fragment_kernels.chunks()),)


def _sample_backward(ids, uv, texels, g_out, *, height, width, clamp, uv_grad=1):
    g_uv, g_texels = texture_kernels.sample_backward(
        ids.reshape(-1), uv.reshape(-1, 2), texels, g_out.reshape(-1, texels.shape[-1]),
        height, width, bool(clamp), bool(uv_grad), fragment_kernels.chunks())
    return g_uv.reshape(uv.shape), g_texels


class _TextureOp(FragmentOp):
    """The lookup's FragmentOp, whose backward kernel skips the UVs' gradient (and the
    texel reads it takes) where reverse mode needs none: where the UVs' tangent is a
    known value (zeros: the UVs do not depend on what is differentiated), the transpose
    binds the backward with uv_grad=0, and its zeros for the UVs are not used."""

    def _transpose(self, other, n, cotangents, ids, *args, **params):
        if other is self.prims["vjp"] and not ad.is_undefined_primal(args[n]):
            params = {**params, "uv_grad": 0}
        return super()._transpose(other, n, cotangents, ids, *args, **params)


#: the bilinear lookup: ids [M] int32 (the offset of each sample's texture in texels, -1:
#: no sample, zeros), uv [M, 2], texels [T, C] (a texture's height * width rows, row-major
#: from the top) -> ([M, C],); static: height, width, clamp (0: 'repeat', 1: 'clamp'),
#: uv_grad (1; _TextureOp sets 0 in the backward where the UVs need no gradient)
sample_texels = _TextureOp("sample_texture", ("pixel", "face"), _sample_native, _sample_forward,
                           _sample_backward, _sample_avals,
                           ffi=("texture", ("height", "width", "clamp", "uv_grad")))


def sample_texture(texture: Texture, uv, host=None, valid=None):
    """Bilinear value [..., C] of texture at uv [..., 2] (module docstring); valid: [...]
    bool, the samples to read (the others get zeros and give no gradient), default all.

    host: by the compiled kernels of diffshade.host.texture_kernels (default: on the CPU
    backend), which read each sample's four texels and, backward, scatter its cotangent
    into them and give its UV a gradient, one pass each; else in jax.numpy (gathers, and
    a scatter-add as their transpose)."""
    host = jax.default_backend() == "cpu" if host is None else host
    height, width, channels = texture.texels.shape
    texels = texture.texels.reshape(height * width, channels)
    flat = uv.astype(texels.dtype).reshape(-1, 2)
    ids = jnp.zeros(flat.shape[:1], jnp.int32)
    if valid is not None:
        ids = jnp.where(valid.reshape(-1), ids, -1)
    values = sample_texels(ids, flat, texels, host=host, height=height, width=width,
                           clamp=int(texture.wrap == "clamp"), uv_grad=1)[0]
    return values.reshape(uv.shape[:-1] + (channels,))


def textured_material(material, uv, host=None, valid=None):
    """material with each Texture field read at uv [..., 2]: kd, ks [..., 3], shininess
    [...]; material itself (None included) when it has no texture. host and valid ([...]
    bool, the samples that hold a fragment): as in sample_texture."""
    if not has_textures(material):
        return material
    changes = {}
    for name in TEXTURED_FIELDS:
        value = getattr(material, name)
        if is_texture(value):
            sampled = sample_texture(value, uv, host, valid)
            changes[name] = sampled[..., 0] if name == "shininess" else sampled
    return dataclasses.replace(material, **changes)

"""Texture: an image that gives a material coefficient a value at every point of a surface.

`Texture` holds texels [H, W, C] float (linear values, row 0 = the top of the image) as a
pytree leaf, so gradients reach every texel, and `wrap` (static: it chooses code) says
what a UV outside [0, 1] reads: 'repeat' (the default, u and v taken modulo 1, as
OpenGL's GL_REPEAT) or 'clamp' (the nearest edge texel, GL_CLAMP_TO_EDGE). UVs follow
the OBJ / OpenGL convention: (0, 0) is the bottom-left corner of the image, v = 1 its
top row. Sampling (bilinear) is diffshade.shading.texturing.

`make_texture(texels)` validates: [H, W] or [H, W, C], finite, non-negative, at most
MAX_TEXELS texels; its ValueError names the argument, the value and what was expected.
Reading a texture from an image file is diffshade.io.textures (the image loader's floor).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.numerics import float_dtype_of

__all__ = ["MAX_TEXELS", "WRAPS", "Texture", "is_texture", "make_texture"]

WRAPS = ("repeat", "clamp")
#: the most texels a texture may have (a 8192 x 8192 map): 768 MiB as float32 RGB, before
#: the gradient's copy; larger is refused at construction, not met as an allocation failure
MAX_TEXELS = 8192 * 8192


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Texture:
    """texels: [H, W, C] float, linear, row 0 = top (v = 1); wrap: 'repeat' or 'clamp'
    (static)."""

    texels: jax.Array
    wrap: str = dataclasses.field(default="repeat", metadata={"static": True})


def is_texture(value) -> bool:
    return isinstance(value, Texture)


def _check_size(shape, name):
    """ValueError for more than MAX_TEXELS texels, checked before any copy is made."""
    if len(shape) in (2, 3) and shape[0] * shape[1] > MAX_TEXELS:
        raise ValueError(f"{name}: {shape[0]} x {shape[1]} texels; expected at most "
                         f"{MAX_TEXELS} (8192 x 8192)")


def _texel_array(texels, name):
    """texels as a float64 [H, W, C] numpy array, or ValueError naming `name`."""
    if isinstance(texels, (str, bytes)):
        raise ValueError(f"{name}: got {texels!r}; expected an array of texels "
                         "(diffshade.texture reads image files)")
    if hasattr(texels, "shape"):
        _check_size(tuple(texels.shape), name)
    try:
        arr = np.asarray(texels, np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: got {type(texels).__name__}; expected an [H, W] or "
                         "[H, W, C] array of numbers") from None
    arr = arr[..., None] if arr.ndim == 2 else arr
    if arr.ndim != 3 or min(arr.shape) < 1:
        raise ValueError(f"{name}: shape {arr.shape}; expected [H, W] or [H, W, C] with "
                         "H, W, C >= 1")
    return arr


def _check_values(arr, name):
    _check_size(arr.shape, name)
    bad = np.argwhere(~np.isfinite(arr) | (arr < 0))
    if bad.size:
        row, col, channel = bad[0]
        raise ValueError(f"{name}: texel [{row}, {col}, {channel}] is {arr[row, col, channel]}"
                         f" ({len(bad)} such values); expected finite values >= 0")


def make_texture(texels, wrap="repeat", name="texels") -> Texture:
    """Validated Texture of texels [H, W] or [H, W, C] (real numbers, linear). Float32
    input stays float32, anything else is stored in the default float dtype (float64
    under x64). name: what errors call the texels."""
    if wrap not in WRAPS:
        raise ValueError(f"wrap: got {wrap!r}; expected one of {WRAPS}")
    if isinstance(texels, Texture):
        return texels if texels.wrap == wrap else Texture(texels.texels, wrap)
    arr = _texel_array(texels, name)
    _check_values(arr, name)
    return Texture(jnp.asarray(arr, float_dtype_of(texels)), wrap)

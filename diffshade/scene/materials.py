"""Material: the Blinn-Phong reflection coefficients of a surface (OpenGL `glMaterial`).

`Material` holds coefficients only. ka, kd, ks and emission are RGB ([3]; a scalar
broadcasts), shininess is a scalar exponent. `ks=None` means no specular term is traced or
compiled, `emission=None` no emission. Defaults are OpenGL's: ka 0.2, kd 0.8, no specular,
no emission. kt (RGB in [0, 1]) is the transparency coefficient of the lecture notes,
I = (1 - kt) I_refl + kt I_trans (docs/transparency.md); `kt=None` (the default, opaque)
compiles no layer compositing at all.

kd, ks and shininess may also be a Texture (diffshade.scene.textures): the coefficient
then varies over the surface, read at each shading sample's UV (diffshade.shading.texturing);
kd and ks textures have 1 channel (grey) or 3 (RGB), shininess's 1. A material without
textures compiles no texture code.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.numerics import float_dtype, representable
from diffshade.scene.textures import Texture, is_texture

#: the fields that may be a Texture
TEXTURED_FIELDS = ("kd", "ks", "shininess")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Material:
    """ka, kd: [..., 3]; ks: [..., 3] or None; shininess: [...]; emission: [..., 3] or None;
    kt: [..., 3] transparency in [0, 1], or None (opaque). kd, ks and shininess may be a
    Texture instead (texels [H, W, 3] for kd and ks, [H, W, 1] for shininess)."""

    ka: jax.Array
    kd: jax.Array
    ks: jax.Array | None = None
    shininess: jax.Array | None = None
    emission: jax.Array | None = None
    kt: jax.Array | None = None


def _floats(value):
    """value as a float64 array, or None when it is not numbers (a string, None, ragged)."""
    if isinstance(value, (str, bytes)) or value is None:
        return None
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        return None


def _coefficient(name, value):
    if is_texture(value):
        raise ValueError(f"{name}: got a texture of {value.texels.shape[1]}x"
                         f"{value.texels.shape[0]} texels; expected a non-negative finite "
                         f"number or 3 of them (RGB): only {', '.join(TEXTURED_FIELDS)} take "
                         "textures")
    arr = _floats(value)
    if arr is not None and arr.shape == ():
        arr = np.full(3, float(arr))
    if arr is None or arr.shape != (3,) or not np.all(representable(arr)) or np.any(arr < 0):
        raise ValueError(f"{name}: got {value!r}; expected a non-negative finite number "
                         "or 3 of them (RGB)")
    return jnp.asarray(arr, dtype=float_dtype())


def _texture(name, value, channels):
    """A texture for field `name`, with `channels` channels (a grey one is repeated)."""
    count = value.texels.shape[-1]
    if count not in (1, channels):
        raise ValueError(f"{name}: a texture of {count} channels; expected "
                         f"{'1 (grey) or 3 (RGB)' if channels == 3 else '1'}")
    texels = jnp.broadcast_to(value.texels, value.texels.shape[:2] + (channels,))
    return Texture(texels, value.wrap)


def has_textures(material) -> bool:
    """Whether any field of the material is a Texture."""
    return material is not None and any(is_texture(getattr(material, name))
                                        for name in TEXTURED_FIELDS)


def _transparency(value):
    """kt as [3] in [0, 1] (a scalar broadcasts)."""
    arr = _floats(value)
    if arr is not None and arr.shape == ():
        arr = np.full(3, float(arr))
    if arr is None or arr.shape != (3,) or not np.all((arr >= 0) & (arr <= 1)):
        raise ValueError(f"kt: got {value!r}; expected a number in [0, 1] or 3 of them (RGB)")
    return jnp.asarray(arr, dtype=float_dtype())


def material(ka=0.2, kd=0.8, ks=None, shininess=0.0, emission=None, kt=None) -> Material:
    """Build a validated Material. shininess must be finite and >= 0 (OpenGL caps it at 128;
    diffshade does not, so that sharp highlights can be fitted). kt: transparency in [0, 1]
    (None: opaque, and no compositing is compiled; 0 composites layers that are opaque).
    kd, ks and shininess may be a Texture (diffshade.texture): 1 or 3 channels for kd and
    ks (grey repeated to RGB), 1 for shininess; the scene's mesh then needs UVs."""
    if is_texture(shininess):
        return _material(ka, kd, ks, _texture("shininess", shininess, 1), emission, kt)
    exponent = _floats(shininess)
    if exponent is None or exponent.shape != () or not (representable(exponent) and exponent >= 0):
        raise ValueError(f"shininess: got {shininess!r}; expected a finite number >= 0")
    return _material(ka, kd, ks, jnp.asarray(shininess, dtype=float_dtype()), emission, kt)


def _colour(name, value):
    return _texture(name, value, 3) if is_texture(value) else _coefficient(name, value)


def _material(ka, kd, ks, shininess, emission, kt):
    if is_texture(kt):
        raise ValueError("kt: got a texture; expected a number in [0, 1] or 3 of them (RGB): "
                         "transparency is uniform over a material")
    return Material(
        ka=_coefficient("ka", ka),
        kd=_colour("kd", kd),
        ks=None if ks is None else _colour("ks", ks),
        shininess=shininess,
        emission=None if emission is None else _coefficient("emission", emission),
        kt=None if kt is None else _transparency(kt),
    )

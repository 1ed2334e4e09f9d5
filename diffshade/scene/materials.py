"""Material: the Blinn-Phong reflection coefficients of a surface (OpenGL `glMaterial`).

`Material` holds coefficients only. ka, kd, ks and emission are RGB ([3]; a scalar
broadcasts), shininess is a scalar exponent. `ks=None` means no specular term is traced or
compiled, `emission=None` no emission. Defaults are OpenGL's: ka 0.2, kd 0.8, no specular,
no emission. kt (RGB in [0, 1]) is the transparency coefficient of the lecture notes,
I = (1 - kt) I_refl + kt I_trans (docs/transparency.md); `kt=None` (the default, opaque)
compiles no layer compositing at all.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.numerics import float_dtype, representable


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Material:
    """ka, kd: [..., 3]; ks: [..., 3] or None; shininess: [...]; emission: [..., 3] or None;
    kt: [..., 3] transparency in [0, 1], or None (opaque)."""

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
    arr = _floats(value)
    if arr is not None and arr.shape == ():
        arr = np.full(3, float(arr))
    if arr is None or arr.shape != (3,) or not np.all(representable(arr)) or np.any(arr < 0):
        raise ValueError(f"{name}: got {value!r}; expected a non-negative finite number "
                         "or 3 of them (RGB)")
    return jnp.asarray(arr, dtype=float_dtype())


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
    (None: opaque, and no compositing is compiled; 0 composites layers that are opaque)."""
    exponent = _floats(shininess)
    if exponent is None or exponent.shape != () or not (representable(exponent) and exponent >= 0):
        raise ValueError(f"shininess: got {shininess!r}; expected a finite number >= 0")
    return Material(
        ka=_coefficient("ka", ka),
        kd=_coefficient("kd", kd),
        ks=None if ks is None else _coefficient("ks", ks),
        shininess=jnp.asarray(shininess, dtype=float_dtype()),
        emission=None if emission is None else _coefficient("emission", emission),
        kt=None if kt is None else _transparency(kt),
    )

"""What photos add to the model: a per-view exposure and white-balance gain.

A camera scales the light it records: view v's image is gain_v * (the rendered colour),
per channel, before the sensor clips it. gain_v = exposure_v * (wb_r, 1, wb_b)_v: one
exposure factor and, for white balance, a red and a blue factor against green (the
convention of camera white-balance multipliers). Since the lit colour is linear in ka,
kd, ks and the emission, a gain is applied by scaling the material (`scaled_material`),
and the clamp of the render then stands for the sensor's clipping.

The gains are relative to view 0, the reference (gain 1): scaling every coefficient by c
and every gain by 1 / c gives the same images, so only ratios are determined. The fitted
material is the one seen at view 0's exposure and white balance.

Values (fitting.spec.params): 'exposure' [V - 1] (views 1 .. V-1), 'white_balance' [V - 1, 2]
(red, blue); both positive, optimized as logarithms.
"""

import dataclasses

import jax.numpy as jnp

from diffshade.numerics import float_dtype

GAIN_NAMES = ("exposure", "white_balance")
_SHAPES = {"exposure": (), "white_balance": (2,)}


def fitted_gains(spec) -> tuple:
    """The gain names the spec fits, in GAIN_NAMES order."""
    return tuple(name for name in GAIN_NAMES if getattr(spec, name))


def gain_values(spec, n_views) -> dict:
    """Initial values (all gains 1) of the gains `spec` fits for n_views views."""
    names = fitted_gains(spec)
    if names and n_views < 2:
        raise ValueError(f"{names[0]}: got a dataset of {n_views} view; expected at least 2 "
                         "views (gains are fitted relative to view 0)")
    return {name: jnp.ones((n_views - 1, *_SHAPES[name]), float_dtype()) for name in names}


def view_gains(values: dict, n_views: int):
    """[V, 3] RGB gain of every view (row 0 is 1), or None when no gain is fitted."""
    if not any(name in values for name in GAIN_NAMES):
        return None
    dtype = next(jnp.asarray(values[n]).dtype for n in GAIN_NAMES if n in values)
    gains = jnp.ones((n_views - 1, 3), dtype)
    if "exposure" in values:
        gains = gains * values["exposure"][:, None]
    if "white_balance" in values:
        balance = values["white_balance"]
        gains = gains * jnp.stack([balance[:, 0], jnp.ones_like(balance[:, 0]), balance[:, 1]],
                                  axis=-1)
    return jnp.concatenate([jnp.ones((1, 3), dtype), gains])


def scaled_material(material, gain):
    """The material whose lit colour is `gain` [3] times `material`'s."""
    def scale(value):
        return None if value is None else value * gain
    return dataclasses.replace(material, ka=scale(material.ka), kd=scale(material.kd),
                               ks=scale(material.ks), emission=scale(material.emission))


def view_materials(material, values: dict, n_views: int) -> list:
    """One material per view: `material` scaled by the view's gain (itself when none)."""
    gains = view_gains(values, n_views)
    if gains is None:
        return [material] * n_views
    return [scaled_material(material, gains[v]) for v in range(n_views)]

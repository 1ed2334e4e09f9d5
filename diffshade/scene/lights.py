"""Light sources with OpenGL 1.x semantics, and their grouping by type.

Each light has ambient, diffuse and specular colours as in `glLightfv`. The factory
functions (`ambient_light`, `directional_light`, `point_light`, `spot_light`) validate
their input; `color=` sets diffuse = specular = color and leaves ambient at 0.
`group_lights` stacks the lights of one type into one pytree with a leading light axis,
and leaves a type absent (`None`) when the scene has none, so that no code for it is
traced or compiled. Area and extended lights (rectangle, disk, sphere) are declared here
too; their factories and shading are diffshade.shading.area (docs/area-lights.md).
Whether a light casts shadows (`shadows=True`; every type but the ambient light) is
static structure: a stacked group holds a tuple of one flag per light, and only the
flagged lights get a shadow pass (diffshade.shading.shadows).

Conventions: positions are world-space points; a `direction` is the direction the light
*travels* (from the light into the scene), as for `GL_SPOT_DIRECTION`; attenuation is
(constant, linear, quadratic) >= 0, not all 0, giving 1 / (a + b d + c d^2) ((0, 0, 1)
is a physical point light's inverse square; docs/light-units.md); spot cutoff and exponent as
`GL_SPOT_CUTOFF` (degrees, in [0, 90], or 180 for no cone) and `GL_SPOT_EXPONENT`.
"""

import dataclasses
from collections.abc import Iterable

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.numerics import float_dtype, representable


def _pytree(cls):
    cls = dataclasses.dataclass(frozen=True)(cls)
    fields = [f.name for f in dataclasses.fields(cls)]
    meta = [name for name in fields if name == "shadows"]
    return jax.tree_util.register_dataclass(
        cls, data_fields=[name for name in fields if name not in meta], meta_fields=meta)


@_pytree
class AmbientLight:
    """ambient: [..., 3] colour added as ka * ambient (no attenuation)."""

    ambient: jax.Array


@_pytree
class DirectionalLight:
    """direction: [..., 3] travel direction; ambient, diffuse, specular: [..., 3];
    shadows: static, see `shadow_flags`."""

    direction: jax.Array
    ambient: jax.Array
    diffuse: jax.Array
    specular: jax.Array
    shadows: bool | tuple = False


@_pytree
class PointLight:
    """position: [..., 3]; colours [..., 3]; attenuation: [..., 3] (constant, linear,
    quadratic); shadows: static, see `shadow_flags`."""

    position: jax.Array
    ambient: jax.Array
    diffuse: jax.Array
    specular: jax.Array
    attenuation: jax.Array
    shadows: bool | tuple = False


@_pytree
class SpotLight:
    """A point light restricted to a cone: direction [..., 3], cutoff [...] degrees,
    exponent [...]; shadows: static, see `shadow_flags`."""

    position: jax.Array
    direction: jax.Array
    ambient: jax.Array
    diffuse: jax.Array
    specular: jax.Array
    attenuation: jax.Array
    cutoff: jax.Array
    exponent: jax.Array
    shadows: bool | tuple = False


def _sampled(cls):
    """A light pytree whose `samples` (the static sample count) and `shadows` are
    metadata."""
    cls = dataclasses.dataclass(frozen=True)(cls)
    meta = ["samples", "shadows"]
    fields = [f.name for f in dataclasses.fields(cls) if f.name not in meta]
    return jax.tree_util.register_dataclass(cls, data_fields=fields, meta_fields=meta)


@_sampled
class RectLight:
    """A one-sided rectangular (parallelogram) emitter: center [..., 3], edge vectors
    edge_u, edge_v [..., 3] (it emits towards edge_u x edge_v); colours [..., 3];
    samples: the static sample count of its sampled terms (area_lights.py); shadows:
    static, see `shadow_flags` (a shadow map per sample, diffshade.shading.shadows)."""

    center: jax.Array
    edge_u: jax.Array
    edge_v: jax.Array
    ambient: jax.Array
    diffuse: jax.Array
    specular: jax.Array
    samples: int = 16
    shadows: bool | tuple = False


@_sampled
class DiskLight:
    """A one-sided disk emitter: center [..., 3], normal [..., 3] (it emits towards the
    normal), radius [...]; colours [..., 3]; samples and shadows as RectLight."""

    center: jax.Array
    normal: jax.Array
    radius: jax.Array
    ambient: jax.Array
    diffuse: jax.Array
    specular: jax.Array
    samples: int = 16
    shadows: bool | tuple = False


@_sampled
class SphereLight:
    """A spherical emitter: position [..., 3], radius [...]; colours [..., 3]; samples and
    shadows as RectLight."""

    position: jax.Array
    radius: jax.Array
    ambient: jax.Array
    diffuse: jax.Array
    specular: jax.Array
    samples: int = 16
    shadows: bool | tuple = False


@_pytree
class LightGroups:
    """Lights stacked by type (leading axis = light index); a type with no light is None."""

    ambient: AmbientLight | None = None
    directional: DirectionalLight | None = None
    point: PointLight | None = None
    spot: SpotLight | None = None
    rect: RectLight | None = None
    disk: DiskLight | None = None
    sphere: SphereLight | None = None


def _array(name, value, shape, *, nonneg=False):
    kind = "non-negative " if nonneg else ""
    error = ValueError(f"{name}: got {value!r}; expected {kind}finite numbers of shape {shape}")
    try:  # a string, None or a ragged sequence is not a number
        if isinstance(value, (str, bytes)) or value is None:
            raise error
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise error from None
    if shape == (3,) and arr.shape == ():
        arr = np.full(3, float(arr))
    if arr.shape != shape or not np.all(representable(arr)) or (nonneg and np.any(arr < 0)):
        raise error
    return jnp.asarray(arr, dtype=float_dtype())


def _scalar(name, value, expected):
    """value as a finite float, or ValueError "name: got value; expected ..."."""
    try:
        return float(_array(name, value, ()))
    except ValueError:
        raise ValueError(f"{name}: got {value!r}; expected {expected}") from None


def _direction(name, value):
    arr = _array(name, value, (3,))
    if float(jnp.linalg.norm(arr)) < 1e-12:
        raise ValueError(f"{name}: got {value!r}; expected a non-zero vector")
    return arr


def _colours(color, ambient, diffuse, specular):
    """OpenGL colours: `color` sets diffuse = specular; explicit keywords win."""
    base = 1.0 if color is None else _array("color", color, (3,), nonneg=True)
    diffuse = base if diffuse is None else diffuse
    specular = base if specular is None else specular
    return (_array("ambient", ambient, (3,), nonneg=True),
            _array("diffuse", diffuse, (3,), nonneg=True),
            _array("specular", specular, (3,), nonneg=True))


def _attenuation(value):
    att = _array("attenuation", value, (3,), nonneg=True)
    if not float(jnp.max(att)) > 0.0:
        raise ValueError(f"attenuation: got {value!r}; expected (constant, linear, quadratic) "
                         ">= 0, not all 0, so that 1/(a + b d + c d^2) is finite for d > 0 "
                         "((0, 0, 1): pure inverse square)")
    return att


def ambient_light(color=1.0) -> AmbientLight:
    """A light with only an ambient colour: [3] or scalar grey."""
    return AmbientLight(_array("color", color, (3,), nonneg=True))


def _shadows(value):
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"shadows: got {value!r}; expected True or False")
    return bool(value)


def directional_light(direction, color=None, *, ambient=0.0, diffuse=None,
                      specular=None, shadows=False) -> DirectionalLight:
    """A light at infinity shining along `direction` (white when no colour is given);
    shadows=True: points it cannot see keep only its ambient term (diffshade.shading.shadows)."""
    return DirectionalLight(_direction("direction", direction),
                            *_colours(color, ambient, diffuse, specular), _shadows(shadows))


def point_light(position, color=None, *, ambient=0.0, diffuse=None, specular=None,
                attenuation=(1.0, 0.0, 0.0), shadows=False) -> PointLight:
    """A positional light with attenuation 1/(a + b d + c d^2); shadows as
    `directional_light`'s (a cube shadow map)."""
    return PointLight(_array("position", position, (3,)),
                      *_colours(color, ambient, diffuse, specular), _attenuation(attenuation),
                      _shadows(shadows))


#: the widest spot cone (half-angle, degrees) a spot's perspective shadow map covers
SHADOW_SPOT_CUTOFF = 80.0


def spot_light(position, direction, color=None, *, cutoff=30.0, exponent=0.0, ambient=0.0,
               diffuse=None, specular=None, attenuation=(1.0, 0.0, 0.0),
               shadows=False) -> SpotLight:
    """A positional light limited to the cone of half-angle `cutoff` degrees around
    `direction`; shadows as `directional_light`'s (one perspective map over the cone,
    so at most SHADOW_SPOT_CUTOFF degrees)."""
    cone, power = "degrees in [0, 90], or 180 (no cone)", "a number in [0, 128]"
    angle = _scalar("cutoff", cutoff, cone)
    if not (0.0 <= angle <= 90.0 or angle == 180.0):
        raise ValueError(f"cutoff: got {cutoff!r}; expected {cone}")
    if _shadows(shadows) and angle > SHADOW_SPOT_CUTOFF:
        raise ValueError(f"cutoff: got {cutoff!r}; expected at most {SHADOW_SPOT_CUTOFF:g} "
                         "degrees for a spot with shadows (its perspective shadow map covers "
                         "the cone; use a point light with shadows for a wider one)")
    if not 0.0 <= _scalar("exponent", exponent, power) <= 128.0:
        raise ValueError(f"exponent: got {exponent!r}; expected {power}")
    dt = float_dtype()
    return SpotLight(_array("position", position, (3,)), _direction("direction", direction),
                     *_colours(color, ambient, diffuse, specular), _attenuation(attenuation),
                     jnp.asarray(cutoff, dt), jnp.asarray(exponent, dt), bool(shadows))


_GROUP_OF = {AmbientLight: "ambient", DirectionalLight: "directional", PointLight: "point",
             SpotLight: "spot", RectLight: "rect", DiskLight: "disk", SphereLight: "sphere"}


def _check_sample_counts(items, indices):
    """Lights of one type stack only with one (static) sample count."""
    counts = [getattr(light, "samples", None) for light in items]
    for light, i in zip(items, indices, strict=True):
        if getattr(light, "samples", None) != counts[0]:
            raise ValueError(f"lights[{i}].samples: got {light.samples}; expected "
                             f"{counts[0]}, the sample count of lights[{indices[0]}] (lights "
                             "of one type share one sample count)")


def group_lights(lights) -> LightGroups:
    """Stack a list of single lights by type into `LightGroups` (absent types are None)."""
    if isinstance(lights, LightGroups):
        return lights
    if type(lights) in _GROUP_OF or isinstance(lights, str) or not isinstance(lights, Iterable):
        raise TypeError(f"lights: got {type(lights).__name__}; expected a list of lights "
                        "or a LightGroups")
    groups = {name: [] for name in _GROUP_OF.values()}
    indices = {name: [] for name in _GROUP_OF.values()}
    for i, light in enumerate(lights):
        if type(light) not in _GROUP_OF:
            raise TypeError(f"lights[{i}]: got {type(light).__name__}; expected one of "
                            f"{[c.__name__ for c in _GROUP_OF]}")
        groups[_GROUP_OF[type(light)]].append(light)
        indices[_GROUP_OF[type(light)]].append(i)
    for name, items in groups.items():
        _check_sample_counts(items, indices[name])
    return LightGroups(**{name: _stack(items) for name, items in groups.items()})


def _stack(lights):
    """One pytree of a type's lights (leading light axis), None for none; the static
    shadow flags become one tuple, a flag per light."""
    if not lights:
        return None
    if not hasattr(lights[0], "shadows"):
        return jax.tree.map(lambda *xs: jnp.stack(xs), *lights)
    flags = tuple(flag for light in lights for flag in shadow_flags(light, 1))
    plain = [dataclasses.replace(light, shadows=False) for light in lights]
    return dataclasses.replace(jax.tree.map(lambda *xs: jnp.stack(xs), *plain), shadows=flags)


def shadow_flags(group, count) -> tuple:
    """Whether each of the `count` lights of a group casts shadows: a single light's
    `shadows` is a bool, a stacked group's a tuple of one bool per light."""
    flags = getattr(group, "shadows", False)
    flags = tuple(flags) if isinstance(flags, tuple) else (bool(flags),) * count
    if len(flags) != count:
        raise ValueError(f"shadows: got {flags!r} for {count} lights; expected one flag "
                         "per light")
    return flags

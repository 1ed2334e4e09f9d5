"""What is fitted, and the map between optimizer variables and physical values.

A `FitSpec` (frozen, hashable, static under `jit`) names the fitted quantities: each of
ka, kd, ks as 'rgb' (3 values), 'grey' (1 value for all channels) or None (held fixed),
shininess (bool), and optionally every light's colour and position. Held-fixed values come
from a base `Material` (and the dataset's lights).

Three representations of the same quantities, each a dict pytree with the same keys:
- params (unconstrained, what the optimizer moves): coefficient = upper * sigmoid(u);
  shininess = exp(u); light colour = exp(u) (diffuse = specular); light position = u.
- values (physical): the coefficients, shininess, colours and positions themselves.
- Material / LightGroups: what `diffshade.shade` consumes.
Keys: 'ka', 'kd', 'ks' ([3] or []), 'shininess' ([]), 'lights' (a tuple over views of
{group: {'color': [L, 3], 'position': [L, 3]}} for the 'directional', 'point', 'spot'
groups present). Optimizer groups for per-group learning rates: `param_labels`.

Several objects (a base Material stacked along a leading object axis, see
diffshade.objects): the material keys move into 'objects', a tuple with one such dict
per object ({'objects': ({'ka': ..., 'shininess': ...}, ...), 'lights': ...}); every
object's material is fitted at once, and the Material built back is stacked again.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.material import Material, material
from diffshade.numerics import float_dtype
from diffshade.objects import stack_materials, unstack_material

COEFFICIENTS = ("ka", "kd", "ks")
MODES = ("rgb", "grey")
LIGHT_GROUPS = ("directional", "point", "spot")
POSITIONED_GROUPS = ("point", "spot")
# Logits are kept finite: a coefficient exactly at a bound maps to +-13.8.
_EDGE = 1e-6

DEFAULT_INIT = material(ka=0.3, kd=0.5, ks=0.3, shininess=20.0)


@dataclasses.dataclass(frozen=True)
class FitSpec:
    """ka, kd, ks: 'rgb' | 'grey' | None; shininess: fitted or not; light_colors,
    light_positions: fit every light's colour (diffuse = specular) / position (point and spot
    lights); upper: the coefficients' upper bound (they live in [0, upper])."""

    ka: str | None = "rgb"
    kd: str | None = "rgb"
    ks: str | None = "rgb"
    shininess: bool = True
    light_colors: bool = False
    light_positions: bool = False
    upper: float = 1.0

    def __post_init__(self):
        for name in COEFFICIENTS:
            mode = getattr(self, name)
            if mode is not None and mode not in MODES:
                raise ValueError(f"{name}: got {mode!r}; expected one of {MODES} or None")
        if not (isinstance(self.upper, (int, float)) and 0 < self.upper < float("inf")):
            raise ValueError(f"upper: got {self.upper!r}; expected a positive finite number")

    @property
    def coefficients(self):
        """The fitted coefficient names, in the order ka, kd, ks."""
        return tuple(name for name in COEFFICIENTS if getattr(self, name) is not None)

    @property
    def fits_lights(self):
        return self.light_colors or self.light_positions

    @property
    def fits_material(self):
        return bool(self.coefficients) or self.shininess


def _logit(x):
    x = jnp.clip(x, _EDGE, 1.0 - _EDGE)
    return jnp.log(x) - jnp.log1p(-x)


def _coefficient_value(name, material_, spec):
    value = getattr(material_, name)
    value = jnp.zeros(3, float_dtype()) if value is None else jnp.asarray(value, float_dtype())
    return jnp.mean(value) if getattr(spec, name) == "grey" else value


def _light_values(lights, spec):
    """Physical light values of the fitted fields, per view (see module docstring)."""
    per_view = []
    for groups in lights:
        entry = {}
        for group in LIGHT_GROUPS:
            light = getattr(groups, group)
            if light is None:
                continue
            fields = {}
            if spec.light_colors:
                fields["color"] = jnp.asarray(light.diffuse, float_dtype())
            if spec.light_positions and group in POSITIONED_GROUPS:
                fields["position"] = jnp.asarray(light.position, float_dtype())
            if fields:
                entry[group] = fields
        per_view.append(entry)
    return tuple(per_view)


def object_count(material_: Material):
    """The number of objects of a stacked Material ([O, 3] leaves), or None for one."""
    return None if jnp.ndim(material_.kd) < 2 else int(jnp.shape(material_.kd)[0])


def _one_material_values(material_, spec):
    values = {name: _coefficient_value(name, material_, spec) for name in spec.coefficients}
    if spec.shininess:
        values["shininess"] = jnp.asarray(material_.shininess, float_dtype())
    return values


def material_values(material_: Material, spec: FitSpec, lights=None) -> dict:
    """Physical values of the fitted quantities of `material_` (stacked: per object, under
    'objects') and `lights`, a sequence of LightGroups, one per view; needed when the spec
    fits lights)."""
    count = object_count(material_)
    if count is None:
        values = _one_material_values(material_, spec)
    else:
        values = {"objects": tuple(_one_material_values(unstack_material(material_, i), spec)
                                   for i in range(count))}
    if spec.fits_lights:
        if lights is None:
            raise ValueError("lights: got None; expected one LightGroups per view, because "
                             "the spec fits light colours or positions")
        values["lights"] = _light_values(lights, spec)
    return values


def _light_map(tree, color_fn, position_fn):
    return tuple({group: {key: (color_fn if key == "color" else position_fn)(x)
                          for key, x in fields.items()}
                  for group, fields in view.items()} for view in tree)


def _per_object(fn, tree, spec):
    """fn applied to the material part of tree: the top level, or each of tree['objects']."""
    if "objects" in tree:
        return {"objects": tuple(fn(one, spec) for one in tree["objects"])}
    return fn(tree, spec)


def _material_params(values, spec):
    params = {name: _logit(values[name] / spec.upper) for name in spec.coefficients}
    if spec.shininess:
        params["shininess"] = jnp.log(jnp.maximum(values["shininess"], 1e-6))
    return params


def _material_values(params, spec):
    values = {name: spec.upper * jax.nn.sigmoid(params[name]) for name in spec.coefficients}
    if spec.shininess:
        values["shininess"] = jnp.exp(params["shininess"])
    return values


def from_values(values: dict, spec: FitSpec) -> dict:
    """Physical values -> unconstrained params (inverse of `to_values`)."""
    params = _per_object(_material_params, values, spec)
    if "lights" in values:
        params["lights"] = _light_map(values["lights"], lambda c: jnp.log(jnp.maximum(c, 1e-6)),
                                      lambda p: p)
    return params


def to_values(params: dict, spec: FitSpec) -> dict:
    """Unconstrained params -> physical values: coefficients in (0, upper), shininess > 0."""
    values = _per_object(_material_values, params, spec)
    if "lights" in params:
        values["lights"] = _light_map(params["lights"], jnp.exp, lambda p: p)
    return values


def to_unconstrained(material_: Material, spec: FitSpec, lights=None) -> dict:
    """Material (and lights, one LightGroups per view, when fitted) -> params dict pytree."""
    return from_values(material_values(material_, spec, lights), spec)


def _one_material(values, spec, base):
    changes = {name: jnp.broadcast_to(values[name], (3,)) for name in spec.coefficients}
    if spec.shininess:
        changes["shininess"] = values["shininess"]
    return dataclasses.replace(base, **changes)


def values_to_material(values: dict, spec: FitSpec, base: Material) -> Material:
    """Physical values -> Material; quantities the spec does not fit come from `base`
    (stacked, with values per object under 'objects')."""
    if "objects" not in values:
        return _one_material(values, spec, base)
    return stack_materials([_one_material(one, spec, unstack_material(base, i))
                            for i, one in enumerate(values["objects"])])


def to_material(params: dict, spec: FitSpec, base_material: Material) -> Material:
    """Unconstrained params -> Material; held-fixed quantities come from base_material."""
    return values_to_material(to_values(params, spec), spec, base_material)


def values_to_lights(values: dict, spec: FitSpec, base_lights):
    """Physical values -> tuple of LightGroups (one per view); unchanged when not fitted."""
    if "lights" not in values:
        return tuple(base_lights)
    out = []
    for groups, entry in zip(base_lights, values["lights"], strict=True):
        changes = {}
        for group, fields in entry.items():
            light = getattr(groups, group)
            light_changes = {}
            if "color" in fields:
                light_changes.update(diffuse=fields["color"], specular=fields["color"])
            if "position" in fields:
                light_changes["position"] = fields["position"]
            changes[group] = dataclasses.replace(light, **light_changes)
        out.append(dataclasses.replace(groups, **changes))
    return tuple(out)


def to_lights(params: dict, spec: FitSpec, base_lights):
    """Unconstrained params -> tuple of LightGroups (one per view)."""
    return values_to_lights(to_values(params, spec), spec, base_lights)


def _label(path, _):
    keys = [getattr(k, "key", None) for k in path]
    if "shininess" in keys:
        return "shininess"
    return "position" if "position" in keys else "colour"


def param_labels(params: dict):
    """Optimizer group of every leaf: 'shininess' (log scale), 'position', or 'colour'
    (coefficient logits and log light colours). Use with `optax.partition`."""
    return jax.tree_util.tree_map_with_path(_label, params)


def _leaf_names(path, leaf):
    keys = [getattr(k, "key", getattr(k, "idx", None)) for k in path]
    if keys[0] == "objects":
        return [f"objects[{keys[1]}].{name}" for name in _leaf_names(path[2:], leaf)]
    if keys[0] != "lights":
        return [keys[0]] if np.ndim(leaf) == 0 else [f"{keys[0]}[{c}]" for c in "rgb"]
    _, view, group, field = keys
    axis = "rgb" if field == "color" else "xyz"
    return [f"lights[{view}].{group}[{i}].{field}[{axis[c]}]"
            for i in range(np.shape(leaf)[0]) for c in range(3)]


def value_names(values: dict) -> list:
    """Readable name of every scalar of `values`, in the order of
    `jax.flatten_util.ravel_pytree(values)`: 'ka[r]', 'kd' (grey), 'shininess',
    'objects[1].kd[g]', 'lights[0].point[1].color[g]', 'lights[2].point[0].position[x]',
    ..."""
    leaves = jax.tree_util.tree_flatten_with_path(values)[0]
    return [name for path, leaf in leaves for name in _leaf_names(path, leaf)]

"""What is fitted, and the map between optimizer variables and physical values.

A `FitSpec` (frozen, hashable, static under `jit`) names the fitted quantities: each of
ka, kd, ks and the transparency kt as 'rgb' (3 values), 'grey' (1 value for all channels)
or None (held fixed), shininess (bool), optionally every light's colour and position, and
each view's exposure and white-balance gain relative to view 0 (fitting.spec.gains).
Held-fixed values come from a base `Material` (and the dataset's lights).

Three representations of the same quantities, each a dict pytree with the same keys:
- params (unconstrained, what the optimizer moves): coefficient = upper * sigmoid(u);
  kt = sigmoid(u) (in [0, 1] whatever `upper`); shininess = exp(u); light colour =
  exp(u) (diffuse = specular); light position = u; exposure, white balance = exp(u).
- values (physical): the coefficients, kt, shininess, colours and positions themselves.
- Material / LightGroups: what `diffshade.shade` consumes.
Keys: 'ka', 'kd', 'ks', 'kt' ([3] or []), 'shininess' ([]), 'lights' (a tuple over views of
{group: {'color': [L, 3], 'position': [L, 3]}} for the 'directional', 'point', 'spot'
groups present), 'exposure' ([V - 1]), 'white_balance' ([V - 1, 2]: red, blue).

`KINDS` is the one table of parameter kinds, keyed by a leaf's last dict key: its map to
physical values (`TRANSFORMS`), its optimizer group for per-group learning rates
(`param_labels`) and its bounds (`at_bound`). A new kind of fitted quantity is one entry
there, plus where its value comes from and goes to (`material_values`,
`values_to_material`, `values_to_lights`). `FIT_NAMES` are the names `--fit` accepts.

Several objects (a base Material stacked along a leading object axis, see
diffshade.scene.objects): the material keys move into 'objects', a tuple with one such dict
per object ({'objects': ({'ka': ..., 'shininess': ...}, ...), 'lights': ...}); every
object's material is fitted at once, and the Material built back is stacked again. The
gains and lights stay at the top level (they are the views', not the objects').
"""

import dataclasses
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from diffshade.numerics import float_dtype
from diffshade.scene import Material, Texture, material, stack_materials, unstack_material
from fitting.spec.gains import GAIN_NAMES, fitted_gains, gain_values

COEFFICIENTS = ("ka", "kd", "ks")
MODES = ("rgb", "grey")
# the quantities fitted per channel or grey
MODED = (*COEFFICIENTS, "kt")
LIGHT_GROUPS = ("directional", "point", "spot")
POSITIONED_GROUPS = ("point", "spot")
# Logits are kept finite: a coefficient exactly at a bound maps to +-13.8.
_EDGE = 1e-6

DEFAULT_INIT = material(ka=0.3, kd=0.5, ks=0.3, shininess=20.0)
FIT_NAMES = (*COEFFICIENTS, "shininess", "kt", "light_colors", "light_positions", *GAIN_NAMES)
# kt's start when the initial material has none: mid-range (a logit of 0 would start it
# at its bound, where its gradient vanishes)
KT_START = 0.5
# A value within this fraction of its bound (of 1 for a bound at 0 with no upper one) is
# at the bound: its standard error is not defined (the Gaussian approximation fails).
BOUND_TOL = 1e-3


def _logit(x):
    x = jnp.clip(x, _EDGE, 1.0 - _EDGE)
    return jnp.log(x) - jnp.log1p(-x)


@dataclasses.dataclass(frozen=True)
class Transform:
    """to_value(u, upper), from_value(x, upper) between an unconstrained variable u and a
    physical value x; bounds(upper) -> (low, high) of x."""

    to_value: object
    from_value: object
    bounds: object


TRANSFORMS = {
    "bounded": Transform(lambda u, upper: upper * jax.nn.sigmoid(u),
                         lambda x, upper: _logit(x / upper), lambda upper: (0.0, upper)),
    "unit": Transform(lambda u, _: jax.nn.sigmoid(u), lambda x, _: _logit(x),
                      lambda _: (0.0, 1.0)),
    "log": Transform(lambda u, _: jnp.exp(u), lambda x, _: jnp.log(jnp.maximum(x, 1e-6)),
                     lambda _: (0.0, np.inf)),
    "identity": Transform(lambda u, _: u, lambda x, _: x, lambda _: (-np.inf, np.inf)),
}


@dataclasses.dataclass(frozen=True)
class Kind:
    """transform: a key of TRANSFORMS; group: the optimizer group ('colour', 'shininess',
    'position'; fitting.solve.step gives each its learning rate)."""

    transform: str
    group: str


KINDS = {
    "ka": Kind("bounded", "colour"),
    "kd": Kind("bounded", "colour"),
    "ks": Kind("bounded", "colour"),
    "shininess": Kind("log", "shininess"),
    "kt": Kind("unit", "colour"),  # transparency, in [0, 1]
    "color": Kind("log", "colour"),  # a light's colour (diffuse = specular)
    "position": Kind("identity", "position"),
    "exposure": Kind("log", "colour"),  # per-view gains (fitting.spec.gains)
    "white_balance": Kind("log", "colour"),
}


@dataclasses.dataclass(frozen=True)
class FitSpec:
    """ka, kd, ks, kt: 'rgb' | 'grey' | None (kt: transparency, held fixed by default);
    shininess: fitted or not; light_colors,
    light_positions: fit every light's colour (diffuse = specular) / position (point and spot
    lights); exposure, white_balance: fit a gain per view relative to view 0
    (fitting.spec.gains); upper: the coefficients' upper bound (they live in [0, upper])."""

    ka: str | None = "rgb"
    kd: str | None = "rgb"
    ks: str | None = "rgb"
    shininess: bool = True
    light_colors: bool = False
    light_positions: bool = False
    upper: float = 1.0
    exposure: bool = False
    white_balance: bool = False
    kt: str | None = None

    def __post_init__(self):
        for name in MODED:
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
        return bool(self.coefficients) or self.shininess or self.kt is not None

    @property
    def fitted(self) -> dict:
        """{name: this spec's setting} for every name of FIT_NAMES (JSON-ready)."""
        return {name: getattr(self, name) for name in FIT_NAMES}

    @classmethod
    def from_names(cls, fitted, grey=(), upper=1.0):
        """The spec that fits the FIT_NAMES in `fitted`, the coefficients in `grey` with
        one value for all channels."""
        unknown = [n for n in (*fitted, *grey) if n not in FIT_NAMES]
        if unknown:
            raise ValueError(f"fitted: got {unknown}; expected names among {FIT_NAMES}")
        return cls(**{n: None if n not in fitted else "grey" if n in grey else "rgb"
                      for n in MODED},
                   **{n: n in fitted for n in FIT_NAMES if n not in MODED}, upper=upper)


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
    """The number of objects of a stacked Material ([O, 3] leaves), or None for one (a
    textured material is one: textures are for scenes of one object)."""
    if isinstance(material_.kd, Texture):
        return None
    return None if jnp.ndim(material_.kd) < 2 else int(jnp.shape(material_.kd)[0])


def _one_material_values(material_, spec):
    values = {name: _coefficient_value(name, material_, spec) for name in spec.coefficients}
    if spec.shininess:
        values["shininess"] = jnp.asarray(material_.shininess, float_dtype())
    if spec.kt is not None:
        values["kt"] = _coefficient_value("kt", material_, spec)
    return values


def start_material(init: Material, spec: FitSpec) -> Material:
    """`init`, with kt = KT_START where the spec fits kt and `init` has none: a material
    with a kt also makes the fitting cache keep every fragment layer (fitting.model.cache)."""
    if spec.kt is None or init.kt is not None:
        return init
    return dataclasses.replace(init, kt=jnp.full(jnp.shape(init.kd), KT_START, float_dtype()))


def material_values(material_: Material, spec: FitSpec, lights=None, n_views=None) -> dict:
    """Physical values of the fitted quantities of `material_` (stacked: per object, under
    'objects') and `lights`, a sequence of LightGroups, one per view; needed when the spec
    fits lights. Fitted gains start at 1; they need the number of views: n_views, or
    len(lights)."""
    count = object_count(material_)
    if count is None:
        values = _one_material_values(material_, spec)
    else:
        values = {"objects": tuple(_one_material_values(unstack_material(material_, i), spec)
                                   for i in range(count))}
    if fitted_gains(spec):
        if n_views is None and lights is None:
            raise ValueError("n_views: got None; expected the number of views, because the "
                             "spec fits per-view gains")
        values |= gain_values(spec, len(lights) if n_views is None else n_views)
    if spec.fits_lights:
        if lights is None:
            raise ValueError("lights: got None; expected one LightGroups per view, because "
                             "the spec fits light colours or positions")
        values["lights"] = _light_values(lights, spec)
    return values


def _key(path):
    return [k.key for k in path if hasattr(k, "key")][-1]


def _kind(path):
    """The KINDS entry of a leaf: its last dict key."""
    return KINDS[_key(path)]


def _map_leaves(tree, spec, direction):
    def one(path, leaf):
        return getattr(TRANSFORMS[_kind(path).transform], direction)(leaf, spec.upper)
    return jax.tree_util.tree_map_with_path(one, tree)


# jitted: called outside a trace they are then one program each, not one per operation
# (each of which JAX would trace, lower and look up in the compilation cache)
@partial(jax.jit, static_argnames=("spec",))
def from_values(values: dict, spec: FitSpec) -> dict:
    """Physical values -> unconstrained params (inverse of `to_values`)."""
    return _map_leaves(values, spec, "from_value")


@partial(jax.jit, static_argnames=("spec",))
def to_values(params: dict, spec: FitSpec) -> dict:
    """Unconstrained params -> physical values: coefficients in (0, upper), shininess > 0."""
    return _map_leaves(params, spec, "to_value")


def at_bound(values: dict, spec: FitSpec) -> np.ndarray:
    """[p] bool, in `value_names` order: the scalars within BOUND_TOL of a bound of their
    kind (times the bounded range, or times 1 when it is unbounded)."""
    flags = []
    for path, leaf in jax.tree_util.tree_flatten_with_path(values)[0]:
        low, high = TRANSFORMS[_kind(path).transform].bounds(spec.upper)
        tol = BOUND_TOL * ((high - low) if np.isfinite(high - low) else 1.0)
        x = np.ravel(np.asarray(leaf, np.float64))
        flags.append((x - low <= tol) | (high - x <= tol))
    return np.concatenate(flags) if flags else np.zeros(0, bool)


def to_unconstrained(material_: Material, spec: FitSpec, lights=None) -> dict:
    """Material (and lights, one LightGroups per view, when fitted) -> params dict pytree."""
    return from_values(material_values(material_, spec, lights), spec)


def _one_material(values, spec, base):
    changes = {name: jnp.broadcast_to(values[name], (3,)) for name in spec.coefficients
               + (("kt",) if spec.kt is not None else ())}
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


def param_labels(params: dict):
    """Optimizer group of every leaf (KINDS): 'shininess' (log scale), 'position', or
    'colour' (coefficient logits, log light colours, and leaves of no kind). Use with
    `optax.partition`."""
    def group(path, _):
        return KINDS[_key(path)].group if _key(path) in KINDS else "colour"
    return jax.tree_util.tree_map_with_path(group, params)


def _leaf_names(path, leaf):
    keys = [getattr(k, "key", getattr(k, "idx", None)) for k in path]
    if keys[0] == "exposure":
        return [f"exposure[{v + 1}]" for v in range(np.shape(leaf)[0])]
    if keys[0] == "white_balance":
        return [f"white_balance[{v + 1}][{c}]" for v in range(np.shape(leaf)[0]) for c in "rb"]
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
    'objects[1].kd[g]', 'exposure[1]' (view 1's), 'white_balance[2][b]',
    'lights[0].point[1].color[g]', 'lights[2].point[0].position[x]', ..."""
    leaves = jax.tree_util.tree_flatten_with_path(values)[0]
    return [name for path, leaf in leaves for name in _leaf_names(path, leaf)]

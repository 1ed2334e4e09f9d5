"""spec: what is fitted: FitSpec, the map between optimizer variables and physical values.

The floor's public face, listed in `__all__`; the rest stays in its modules. fitting's
own modules import each other by full module path.
"""

from fitting.spec.params import (
    DEFAULT_INIT,
    FIT_NAMES,
    KINDS,
    FitSpec,
    at_bound,
    from_values,
    material_values,
    param_labels,
    to_lights,
    to_material,
    to_unconstrained,
    to_values,
    value_names,
    values_to_lights,
    values_to_material,
)

__all__ = [
    "DEFAULT_INIT", "FIT_NAMES", "KINDS", "FitSpec", "at_bound", "from_values",
    "material_values", "param_labels", "to_lights", "to_material", "to_unconstrained",
    "to_values", "value_names", "values_to_lights", "values_to_material",
]

"""composite: fragment colours -> RGBA: hard and soft blending, transparent layers.

The floor's public face, listed in `__all__` (diffshade's own modules import each other
by full module path).
"""

from diffshade.composite.blend import hard_blend, soft_alpha, soft_blend, soft_weights
from diffshade.composite.transparency import is_transparent, layer_weights, layers_needed

__all__ = [
    "hard_blend", "soft_alpha", "soft_blend", "soft_weights",
    "is_transparent", "layer_weights", "layers_needed",
]

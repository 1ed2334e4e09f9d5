"""shade: where and how light falls: shading samples, the lighting core, shadows.

The floor's public face, listed in `__all__` (diffshade's own modules import each other
by full module path).
"""

from diffshade.shading.lighting import ShadingParts, light_visibility, shade
from diffshade.shading.samples import Reader, Samples, read, shading_samples
from diffshade.shading.shadows import ShadowMap, shadow_maps
from diffshade.shading.texturing import sample_texture, textured_material

__all__ = [
    "ShadingParts", "light_visibility", "shade",
    "Reader", "Samples", "read", "shading_samples",
    "ShadowMap", "shadow_maps",
    "sample_texture", "textured_material",
]

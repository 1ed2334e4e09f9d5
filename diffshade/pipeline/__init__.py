"""pipeline: the composition: render, its batched and cached variants.

The floor's public face, listed in `__all__` (diffshade's own modules import each other
by full module path). `render` here is the function (the module is
diffshade.pipeline.rendering).
"""

from diffshade.pipeline.cost import check_render
from diffshade.pipeline.rendering import (
    blend,
    rasterize_scene,
    render,
    render_fragments,
    render_parts,
    render_supersampled,
    render_views,
    stack_cameras,
    view_dirs,
)
from diffshade.pipeline.shading_cache import (
    ShadingCache,
    cache_shading,
    render_cached,
    slot_samples,
)

__all__ = [
    "check_render",
    "blend", "rasterize_scene", "render", "render_fragments", "render_parts",
    "render_supersampled", "render_views", "stack_cameras", "view_dirs",
    "ShadingCache", "cache_shading", "render_cached", "slot_samples",
]

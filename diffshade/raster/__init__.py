"""raster: project -> search -> fragments -> interpolate.

The floor's public face, listed in `__all__` (diffshade's own modules import each other
by full module path). `project` and `interpolate` here are the functions (the modules are
diffshade.raster.projection and diffshade.raster.interpolation).
"""

from diffshade.raster.fragments import Fragments, fragments_from_ids, rasterize
from diffshade.raster.interpolation import interpolate, interpolate_rows
from diffshade.raster.projection import Projected, project
from diffshade.raster.search import search_depth, search_faces

__all__ = [
    "Fragments", "fragments_from_ids", "rasterize",
    "interpolate", "interpolate_rows",
    "Projected", "project",
    "search_depth", "search_faces",
]

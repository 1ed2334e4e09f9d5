"""raster: project -> search -> fragments -> interpolate.

The floor's public face, listed in `__all__` (diffshade's own modules import each other
by full module path). `project` and `interpolate` here are the functions (the modules are
diffshade.raster.project and diffshade.raster.interpolate).
"""

from diffshade.raster.fragments import Fragments, fragments_from_ids, rasterize
from diffshade.raster.interpolate import interpolate, interpolate_rows
from diffshade.raster.project import Projected, project
from diffshade.raster.search import search_depth, search_faces

__all__ = [
    "Fragments", "fragments_from_ids", "rasterize",
    "interpolate", "interpolate_rows",
    "Projected", "project",
    "search_depth", "search_faces",
]

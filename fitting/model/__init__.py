"""model: the forward model on cached pixels (build_cache, predict) and the losses.

The floor's public face, listed in `__all__`; the rest stays in its modules. fitting's
own modules import each other by full module path.
"""

from fitting.model.cache import FitData, ViewSamples, build_cache, pixel_parts, predict
from fitting.model.loss import (
    LOSSES,
    RenderData,
    make_loss,
    make_render_loss,
    render_data,
    residuals,
)

__all__ = [
    "FitData", "ViewSamples", "build_cache", "pixel_parts", "predict", "LOSSES", "RenderData",
    "make_loss", "make_render_loss", "render_data", "residuals",
]

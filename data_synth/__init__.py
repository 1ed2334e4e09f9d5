"""data_synth: synthetic fitting datasets with known materials.

`make_dataset` renders a built-in shape (or any mesh file) with a given or random
material from several cameras and lights through `diffshade.render`. The dataset folder
format (`save_dataset`, `load_dataset`) lives in fitting.data.folder; both are re-exported
here. See data_synth/scenes.py for the layout of cameras and lights.
"""

from data_synth.materials import COEFFICIENT_RANGES, SHININESS_RANGE, random_material
from data_synth.scenes import (
    GLOBAL_AMBIENT,
    LIGHT_INTENSITY,
    SHAPES,
    camera_eyes,
    degrade,
    make_dataset,
    shape_mesh,
    view_lights,
)
from fitting.data.folder import load_dataset, save_dataset

__all__ = [
    "COEFFICIENT_RANGES", "GLOBAL_AMBIENT", "LIGHT_INTENSITY", "SHAPES", "SHININESS_RANGE",
    "camera_eyes", "degrade", "load_dataset", "make_dataset", "random_material",
    "save_dataset", "shape_mesh", "view_lights",
]

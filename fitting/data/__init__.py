"""data: the dataset: views of one scene with their targets, and its folder format.

The floor's public face, listed in `__all__`; the rest stays in its modules. fitting's
own modules import each other by full module path.
"""

from fitting.data.capture import capture_cameras, import_capture
from fitting.data.folder import load_dataset, save_dataset
from fitting.data.views import Dataset, View, dataset_of_scene, material_for, view_scene

__all__ = [
    "capture_cameras", "import_capture",
    "load_dataset", "save_dataset", "Dataset", "View", "dataset_of_scene", "material_for",
    "view_scene",
]

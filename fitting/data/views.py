"""The fitting data: views (camera, lights, target image, optional mask) of one object.

A `Dataset` is what a fit consumes: one mesh placed by one model matrix, one global
ambient light and one `RenderSettings`, seen in several `View`s, each with its own camera,
lights and target image. `truth` (the material that rendered the targets, when known) lets
a fit report its error. Inputs are validated here, at the boundary: a target whose size
does not match its camera raises a ValueError naming the view.

`view_scene` builds the diffshade `Scene` of one view for a given material: the same
forward model renders the targets (data_synth) and the fit's full-image path.

Several objects: `objects` (diffshade.scene.objects.ObjectIds) says which object each face and
vertex of the (joined) mesh belongs to; materials (truth, the fit's) then have a leading
object axis. `dataset_of_scene` takes mesh, model and ids from a Scene; `object_total`
counts a dataset's objects and `material_for` gives a material the shape a dataset needs
(one material for every object, or one per object, in order or by name).
"""

import dataclasses

import numpy as np

from diffshade.scene import (
    Camera,
    LightGroups,
    Material,
    Mesh,
    ObjectIds,
    Scene,
    check_mesh,
    group_lights,
    make_scene,
    replace,
    stack_materials,
)
from diffshade.settings import RenderSettings
from fitting.data.rounding import Rounding


@dataclasses.dataclass(frozen=True)
class View:
    """camera: Camera; lights: LightGroups (a list of lights is grouped); target: [H, W, 3]
    float linear colours; mask: [H, W] bool, True where the pixel counts (None: all);
    rounding: fitting.data.rounding.Rounding of a target resampled from 8-bit codes (an
    undistorted photo), or None (the rounding, if any, is read from the target's codes)."""

    camera: Camera
    lights: LightGroups
    target: np.ndarray
    mask: np.ndarray | None = None
    rounding: Rounding | None = None

    def __post_init__(self):
        object.__setattr__(self, "lights", group_lights(self.lights))
        object.__setattr__(self, "target", _float_array("target", self.target))
        if self.mask is not None:
            object.__setattr__(self, "mask", np.asarray(self.mask, bool))


@dataclasses.dataclass(frozen=True)
class Dataset:
    """mesh: Mesh; views: tuple of View; model: [4, 4] model-to-world matrix (None:
    identity); global_ambient: [3] or scalar; settings: RenderSettings the targets were
    rendered with (the fit renders with the same ones, clamping included); truth: the
    Material that made the targets, or None; local_viewer, two_sided: as in make_scene;
    info: free-form description (how the data were made); objects: ObjectIds of a mesh
    joined from several objects (materials then stacked, [O, 3]), or None."""

    mesh: Mesh
    views: tuple
    model: np.ndarray | None = None
    global_ambient: object = 0.2
    settings: RenderSettings = RenderSettings()
    truth: Material | None = None
    local_viewer: bool = False
    two_sided: bool = False
    info: dict = dataclasses.field(default_factory=dict, compare=False)
    objects: ObjectIds | None = None

    def __post_init__(self):
        if not isinstance(self.mesh, Mesh):
            raise TypeError(f"mesh: got {type(self.mesh).__name__}; expected Mesh")
        # A Mesh built directly is unchecked: a bad face index would reach the rasterizer.
        object.__setattr__(self, "mesh", check_mesh(self.mesh))
        views = tuple(self.views)
        if not views:
            raise ValueError("views: got an empty sequence; expected at least one View")
        for i, view in enumerate(views):
            _check_view(i, view)
        object.__setattr__(self, "views", views)
        model = np.eye(4) if self.model is None else _float_array("model", self.model)
        if model.shape != (4, 4) or not np.all(np.isfinite(model)):
            raise ValueError(f"model: got an array of shape {model.shape}; expected a finite "
                             "4x4 model-to-world matrix")
        object.__setattr__(self, "model", model.astype(np.float64))
        ambient = _float_array("global_ambient", self.global_ambient)
        if ambient.shape not in ((), (3,)) or not np.all(np.isfinite(ambient)) or np.any(
                ambient < 0):
            raise ValueError(f"global_ambient: got {self.global_ambient!r}; expected a "
                             "non-negative number or 3 of them")
        if self.truth is not None and not isinstance(self.truth, Material):
            raise TypeError(f"truth: got {type(self.truth).__name__}; expected a Material "
                            "(diffshade.scene.materials(...)) or None")
        if not isinstance(self.settings, RenderSettings):
            raise TypeError(f"settings: got {type(self.settings).__name__}; "
                            "expected RenderSettings")


def _float_array(name, value):
    """np.asarray(value, float) with a clear error for text or ragged input."""
    try:
        return np.asarray(value, np.float32 if name == "target" else np.float64)
    except (TypeError, ValueError) as err:
        kind = "ragged nested lists" if "inhomogeneous" in str(err) else repr(value)
        raise ValueError(f"{name}: got {kind}; expected an array of numbers") from None


def _check_view(i, view):
    if not isinstance(view, View):
        raise TypeError(f"views[{i}]: got {type(view).__name__}; expected View")
    if not isinstance(view.camera, Camera):
        raise TypeError(f"views[{i}].camera: got {type(view.camera).__name__}; expected Camera")
    height, width = view.camera.height, view.camera.width
    if view.target.shape != (height, width, 3):
        raise ValueError(f"views[{i}].target: got shape {view.target.shape}; expected "
                         f"({height}, {width}, 3), the size of views[{i}].camera "
                         f"(width {width}, height {height}) with RGB channels")
    if view.mask is not None and view.mask.shape != (height, width):
        raise ValueError(f"views[{i}].mask: got shape {view.mask.shape}; expected "
                         f"({height}, {width}), the size of views[{i}].camera")
    if not np.all(np.isfinite(view.target)):
        raise ValueError(f"views[{i}].target: contains NaN or inf; expected finite colours")


def view_scene(dataset: Dataset, index: int, material: Material, lights=None) -> Scene:
    """The diffshade Scene of view `index` with `material` (and `lights`, default the
    view's own)."""
    view = dataset.views[index]
    scene = make_scene(dataset.mesh, view.camera, view.lights if lights is None else lights,
                       material, model=dataset.model, global_ambient=dataset.global_ambient,
                       local_viewer=dataset.local_viewer, two_sided=dataset.two_sided)
    return scene if dataset.objects is None else replace(scene, objects=dataset.objects)


def dataset_of_scene(scene: Scene, views, **kwargs) -> Dataset:
    """A Dataset of `scene`'s mesh, model, objects, global ambient and lighting switches,
    seen in `views` (kwargs: the other Dataset fields, e.g. truth, settings)."""
    return Dataset(scene.mesh, views, model=scene.model, global_ambient=scene.global_ambient,
                   local_viewer=scene.local_viewer, two_sided=scene.two_sided,
                   objects=scene.objects, **kwargs)


def object_total(dataset: Dataset) -> int | None:
    """The number of objects of a dataset of several objects, or None (one object)."""
    return None if dataset.objects is None else int(np.max(dataset.objects.faces)) + 1


def object_names(dataset: Dataset) -> tuple | None:
    """The names of a dataset's objects (the scene files' "name"s, an unnamed object i
    'object_<i>'), or None for a dataset of one object."""
    count = object_total(dataset)
    if count is None:
        return None
    return dataset.objects.names or tuple(f"object_{i}" for i in range(count))


def _in_order(named, names, where):
    """{name: Material} -> the materials in the objects' order (every object named)."""
    unknown = [n for n in named if n not in names]
    if unknown:
        raise ValueError(f"{where}: objects: {unknown[0]!r}: unknown object name; expected "
                         f"names among {', '.join(map(repr, names))}")
    missing = [n for n in names if n not in named]
    if missing:
        raise ValueError(f"{where}: objects: no material for {missing[0]!r}; expected one "
                         f"for every object ({', '.join(map(repr, names))})")
    return stack_materials([named[n] for n in names])


def material_for(dataset: Dataset, material, name="material") -> Material:
    """`material` as the dataset's materials are: with several objects, a single material
    is repeated for every object, a stacked one ([O, 3] leaves) must have one row per
    object, and a dict {object name: Material} must name every object (`object_names`);
    with one object it must be a single material. ValueError naming `name` otherwise."""
    count, names = object_total(dataset), object_names(dataset)
    if isinstance(material, dict):
        if names is None:
            raise ValueError(f"{name}: got materials for the objects {sorted(material)}; "
                             "expected one material, as the dataset has one object")
        return _in_order(material, names, name)
    given = None if np.ndim(material.kd) < 2 else int(np.shape(material.kd)[0])
    if given == count:
        return material
    if given is None:
        return stack_materials([material] * count)
    expected = "one material" if count is None else f"one material, or {count} (one per object)"
    raise ValueError(f"{name}: got materials for {given} objects; expected {expected}, as the "
                     f"dataset has {count or 1} object{'s' if count else ''}")

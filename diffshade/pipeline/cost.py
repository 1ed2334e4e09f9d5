"""What a render of a scene costs in memory, checked before anything is compiled or allocated.

`check_render(scene, settings, views, factor)` gathers the sizes a render of `scene`
implies (its image, fragment slots, mesh, textures, shadow maps and light samples), adds
up their bytes by diffshade.budget's formulas and raises budget.SizeError naming the
setting that costs the most when the total is beyond the memory available, or when one
array would hold more than budget.MAX_ELEMENTS values. The render entry points call it (through
rendering.check_arguments), so no size reaches an allocation inside XLA.
"""

from typing import NamedTuple

import jax

from diffshade import budget
from diffshade.composite.transparency import layers_needed
from diffshade.scene.lights import shadow_flags
from diffshade.scene.materials import TEXTURED_FIELDS
from diffshade.scene.textures import is_texture
from diffshade.shading.area import KINDS as AREA_KINDS

__all__ = ["RenderCost", "check_render", "render_cost"]


def _shadow_counts(lights):
    """(cube maps, single maps, sample cube maps of area lights, most samples of one
    area light) of the lights with shadows."""
    cubes = flat = sample_cubes = most = 0
    for kind in ("directional", "point", "spot", *AREA_KINDS):
        group = getattr(lights, kind)
        if group is None:
            continue
        flags = shadow_flags(group, jax.tree.leaves(group)[0].shape[0])
        casting = sum(flags)
        if not casting:
            continue
        if kind in AREA_KINDS:
            sample_cubes += casting * group.samples
            most = max(most, group.samples)
        elif kind == "point":
            cubes += casting
        else:
            flat += casting
    return cubes, flat, sample_cubes, most


def _texture_terms(scene):
    """{('material.kd', 'HxW texels'): bytes} of each texture of the scene's materials:
    one copy whatever the views (a batch of views shares it)."""
    terms = {}
    for owner in ("material", "back_material"):
        material = getattr(scene, owner)
        for name in TEXTURED_FIELDS if material is not None else ():
            value = getattr(material, name)
            if is_texture(value):
                height, width, channels = value.texels.shape
                terms[(f"{owner}.{name}", f"{height}x{width} texels")] = budget.texture_bytes(
                    height * width, channels)
    return terms


def _terms(scene, settings, views, pixels, slots, shadows):
    """{(key, value shown): bytes} of each setting's share of the render (its fixed
    budget.BASE_BYTES aside); shadows: the scene's _shadow_counts."""
    cam, side = scene.camera, settings.shadow_map_size
    cubes, flat, sample_cubes, most = shadows
    per_pixel = budget.render_bytes(pixels, 1 if slots == 1 else 0)
    terms = {("camera width x height", f"{cam.width}x{cam.height}"): views * per_pixel,
             ("mesh faces", scene.mesh.faces.shape[0]):
                 views * budget.mesh_bytes(scene.mesh.faces.shape[0])}
    if slots > 1:
        terms[("faces_per_pixel", slots)] = views * pixels * slots * budget.SLOT_BYTES
    if cubes or flat or sample_cubes:
        maps = budget.shadow_bytes(side, cubes + sample_cubes, flat)
        samples = budget.CUBE * sample_cubes * side * side * budget.DEPTH_BYTES
        terms[("shadow_map_size", side)] = views * (maps - samples)
        if sample_cubes:  # the area lights' sample maps, kept all at once
            terms[("samples", most)] = views * samples
    return terms | _texture_terms(scene)


def _largest_array(views, pixels, slots, side, shadows):
    """Values in the largest array: the fragments' barycentrics [views, H, W, slots, 3],
    a cube's map fragments [6, M, M, 1, 3] or the area lights' sample maps [S, 6, M, M]."""
    cubes, flat, sample_cubes, _ = shadows
    texels = side * side if cubes or flat or sample_cubes else 0
    maps = budget.CUBE * texels * max(3, sample_cubes)
    return views * max(pixels * slots * 3, maps)


def _described(cam, factor, views, slots, faces, map_side):
    """The request in words: 'a 64x64 render with 8 fragment slots a pixel, 80 faces and
    shadow maps of 256x256 texels'."""
    items = ["1 fragment slot a pixel" if slots == 1 else f"{slots} fragment slots a pixel",
             f"{faces} faces"]
    if map_side:
        items.append(f"shadow maps of {map_side}x{map_side} texels")
    return (f"a {cam.width * factor}x{cam.height * factor} render"
            f"{f' of {views} views' if views > 1 else ''} with {', '.join(items[:-1])} and "
            f"{items[-1]}")


class RenderCost(NamedTuple):
    """A render's memory: bytes in all, values in its largest array, the setting that
    costs the most (key, value as shown) and the request in words."""

    bytes: int
    elements: int
    key: str
    value: object
    what: str


def render_cost(scene, settings, views=1, factor=1) -> RenderCost:
    """The memory a render of `scene` needs, from `views` cameras at once, at `factor` x
    its camera's resolution (module docstring)."""
    cam = scene.camera
    pixels = cam.width * cam.height * factor * factor
    slots = settings.faces_per_pixel if settings.raster == "soft" else layers_needed(
        scene, settings)
    shadows = _shadow_counts(scene.lights)
    terms = _terms(scene, settings, views, pixels, slots, shadows)
    (key, value), _ = max(terms.items(), key=lambda item: item[1])
    what = _described(cam, factor, views, slots, scene.mesh.faces.shape[0],
                      settings.shadow_map_size if any(shadows) else None)
    elements = _largest_array(views, pixels, slots, settings.shadow_map_size, shadows)
    return RenderCost(budget.BASE_BYTES + sum(terms.values()), elements, key, value, what)


def check_render(scene, settings, views=1, factor=1):
    """Raise budget.SizeError when rendering `scene` (from `views` cameras at once, at
    `factor` x its camera's resolution) would need more memory than is available, or an
    array beyond budget.MAX_ELEMENTS values (module docstring)."""
    cost = render_cost(scene, settings, views, factor)
    budget.check(cost.key, cost.value, cost.bytes, cost.what, cost.elements)

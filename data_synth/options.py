"""synth's command-line options (data_synth.cli) as make_dataset's arguments, and the
dataset's layout before rendering, for synth and its background compilation of the fit
(data_synth.background)."""

import dataclasses

from data_synth.scenes import dataset_layout
from diffshade.io import load_scenes
from fitting.inputs import parse_material


def what(args):
    """(shape, material or None, RenderSettings or None) for make_dataset: --shape and
    --material, or the Scene of --scene with its settings (--shading overriding)."""
    if args.scene is None:
        material = (None if args.material in (None, "random")
                    else parse_material(args.material, "--material"))
        return args.shape or "icosphere", material, None
    for option, value in (("--shape", args.shape), ("--material", args.material)):
        if value is not None:
            raise ValueError(f"{option}: got {value!r} with --scene; expected the shape and "
                             "materials inside the scene file")
    scenes, settings = load_scenes(args.scene)  # any camera: the layout replaces them
    scene = scenes[0]
    if args.shading:
        settings = dataclasses.replace(settings, shading=args.shading)
    return scene, None, settings


def layout_of(args):
    """The Dataset synth's `args` make, before its targets are rendered
    (data_synth.scenes.dataset_layout)."""
    shape, material, settings = what(args)
    return dataset_layout(shape, material, n_views=args.views, n_lights=args.lights,
                          size=args.size, seed=args.seed, shading=args.shading or "phong",
                          settings=settings, texture=args.texture)

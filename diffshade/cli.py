"""The `diffshade` command line: `main(argv) -> exit status`.

    diffshade render SCENE.json -o OUT.png [--shading MODE] [--size WxH] [--parts]
        [--camera N] [--material RESULT.json]
    diffshade render --builtin sphere -o OUT.png

    diffshade synth ... (data_synth.cli),  diffshade fit ... (fitting.cli)

`COMMANDS` is the table of commands: name -> register(subparsers), a callable which adds
the command's parser with `subparsers.add_parser(name, help=...)` and sets
`parser.set_defaults(run=fn)`, fn(args) -> int exit status. `render` is registered here;
the applications built on the renderer (synth, fit) come in as entry points of the group
`diffshade.commands` (pyproject.toml), so that the library never imports its applications.

A user error (ValueError, including SceneFileError, or OSError such as a missing or
unwritable file) prints one line `diffshade: error: <message>` on stderr and returns 2,
never a traceback; so do command-line usage errors. Success prints each written path and
returns 0. Output files are written atomically (diffshade.io.images).
"""

import argparse
import dataclasses
import importlib.metadata
import os
import sys

import numpy as np

from diffshade.host import warmup
from diffshade.io import compile_cache
from diffshade.io.images import check_writable, write_npy, write_png
from diffshade.io.scenefile import load_material, load_scenes
from diffshade.pipeline.rendering import render, render_parts
from diffshade.scene.builtin import BUILTIN_SCENES, builtin_scene
from diffshade.scene.camera import MAX_IMAGE_SIZE
from diffshade.scene.materials import has_textures
from diffshade.scene.scene import replace
from diffshade.settings import SHADING_MODES, RenderSettings

__all__ = ["COMMANDS", "build_parser", "main", "program"]

_USER_ERRORS = (ValueError, OSError)
_OUTPUT_KINDS = (".png", ".npy")
_PARTS = ("ambient", "diffuse", "specular", "emission")


class _UsageError(ValueError):
    """A command-line usage error (argparse would print usage and exit instead)."""


class _Parser(argparse.ArgumentParser):
    def error(self, message):
        raise _UsageError(f"{message} (see '{self.prog} --help')")


def _size(text):
    """'WxH' -> (width, height), both positive integers."""
    width, sep, height = text.lower().partition("x")
    if not (sep and width.isdigit() and height.isdigit()
            and 0 < int(width) <= MAX_IMAGE_SIZE and 0 < int(height) <= MAX_IMAGE_SIZE):
        raise argparse.ArgumentTypeError(f"got {text!r}; expected WxH in pixels, e.g. 256x256, "
                                         f"each at most {MAX_IMAGE_SIZE}")
    return int(width), int(height)


def _index(text):
    """'N' -> N, an integer >= 0."""
    if not text.isdigit():
        raise argparse.ArgumentTypeError(f"got {text!r}; expected an index >= 0")
    return int(text)


def _register_render(subparsers):
    parser = subparsers.add_parser(
        "render", help="render a scene file or a built-in scene to an image",
        description="Render a JSON scene file (see docs/scene-format.md) or a built-in "
                    "scene. OUT.png gets 8-bit sRGB-encoded RGB over the scene's background "
                    "(for viewing); OUT.npy gets linear float32 RGBA [H, W, 4] (alpha = "
                    "coverage), for data (docs/color.md).")
    parser.add_argument("scene", nargs="?", metavar="SCENE.json", help="scene file")
    parser.add_argument("--builtin", choices=BUILTIN_SCENES, help="render a built-in scene")
    parser.add_argument("-o", "--output", required=True, metavar="OUT",
                        help="output image, .png or .npy")
    parser.add_argument("--shading", choices=SHADING_MODES,
                        help="override the scene's settings.shading")
    parser.add_argument("--size", type=_size, metavar="WxH",
                        help="override the image size (built-in default: 256x256)")
    parser.add_argument("--camera", type=_index, metavar="N",
                        help="the camera to render of a scene file with several "
                             "(\"cameras\"), counted from 0")
    parser.add_argument("--material", metavar="FILE.json",
                        help="render with this material instead of the scene file's: a "
                             "'diffshade fit' result.json, or a JSON material object")
    parser.add_argument("--parts", action="store_true",
                        help="also write OUT_ambient, OUT_diffuse, OUT_specular, "
                             "OUT_emission (unclamped, zero off the object)")
    parser.set_defaults(run=_run_render)


def _scene_and_settings(args):
    """(Scene, RenderSettings) from args.scene or args.builtin, with --size applied."""
    if (args.scene is None) == (args.builtin is None):
        raise _UsageError("render: expected a scene file or --builtin NAME, not "
                          f"{'both' if args.scene else 'neither'}")
    if args.builtin:
        for flag, value in (("--camera", args.camera), ("--material", args.material)):
            if value is not None:
                raise _UsageError(f"{flag}: got {value!r} with --builtin; expected a scene "
                                  "file")
        return builtin_scene(args.builtin, *(args.size or (256, 256))), RenderSettings()
    scene, settings = _one_camera(args.scene, args.camera)
    if args.material:
        scene = replace(scene, material=load_material(args.material, scene))
    if args.size:
        width, height = args.size
        scene = replace(scene, camera=replace(scene.camera, width=width, height=height))
    return scene, settings


def _one_camera(path, camera):
    """(Scene, RenderSettings) of camera `camera` of the scene file (None: its only one)."""
    scenes, settings = load_scenes(path)
    if camera is None and len(scenes) > 1:
        raise _UsageError(f"{path}: has {len(scenes)} cameras; expected --camera N to pick "
                          f"one (0 to {len(scenes) - 1})")
    if camera is not None and camera >= len(scenes):
        raise _UsageError(f"--camera: got {camera}; expected an index below {len(scenes)}, "
                          f"the cameras of {path}")
    return scenes[camera or 0], settings


def _write(path, image, kind):
    """PNG: the RGB channels (already composited over the background), sRGB-encoded;
    .npy: all of them, linear."""
    if kind == ".png":
        return write_png(path, image[..., :3])
    return write_npy(path, image.astype(np.float32))


def _run_render(args):
    root, kind = os.path.splitext(args.output)
    if kind.lower() not in _OUTPUT_KINDS:
        raise _UsageError(f"--output: got {args.output!r}; expected a path ending in "
                          f"{' or '.join(_OUTPUT_KINDS)}")
    check_writable(args.output, "--output")
    scene, settings = _scene_and_settings(args)
    if has_textures(scene.material):
        warmup.cold_start(warmup.TEXTURE_TARGETS)
    if args.shading:
        settings = dataclasses.replace(settings, shading=args.shading)
    # Render everything before writing anything, so that a failure leaves no output.
    images = {args.output: np.asarray(render(scene, settings))}
    if args.parts:
        parts = render_parts(scene, settings)
        images |= {f"{root}_{name}{kind}": np.asarray(getattr(parts, name)) for name in _PARTS}
    for path, image in images.items():
        print(_write(path, image, kind.lower()))
    return 0


#: the entry-point group through which applications add commands
COMMAND_GROUP = "diffshade.commands"


def _deferred(entry_point):
    """register(subparsers) that imports the entry point's module only when called."""
    def register(subparsers):
        return entry_point.load()(subparsers)
    register.entry_point = entry_point
    return register


def _installed_commands():
    points = importlib.metadata.entry_points(group=COMMAND_GROUP)
    return {point.name: _deferred(point) for point in sorted(points, key=lambda p: p.name)}


COMMANDS = {"render": _register_render, **_installed_commands()}


def build_parser(command=None):
    """The argument parser with every command of `COMMANDS` registered, or only `command`
    when it names one: registering a command imports its module, and the applications'
    (fit, synth) import fitting, optax and SciPy, which `diffshade render` does not need."""
    parser = _Parser(prog="diffshade",
                     description="diffshade: a differentiable Blinn-Phong renderer.")
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, register in COMMANDS.items():
        if command not in COMMANDS or name == command:
            register(subparsers)
    return parser


def _one_line(err):
    if isinstance(err, OSError) and err.strerror and err.filename:
        # A failed rename (filename -> filename2) is about its target, not the temporary.
        text = f"{err.filename2 or err.filename}: {err.strerror}"
    else:
        text = str(err) or type(err).__name__
    return " ".join(text.split())


def program() -> int:
    """The `diffshade` program (its console script, `python -m diffshade`): main on the
    process's arguments, after the cold start of a fresh install (diffshade.host.warmup:
    where numba has not compiled the host kernels yet, this run uses the JAX kernels while
    they compile in the background)."""
    warmup.cold_start(warmup.command_targets(sys.argv[1:]))
    return main()


def main(argv=None) -> int:
    """Run the command line on argv (default sys.argv[1:]); returns the exit status."""
    compile_cache.enable()
    argv = sys.argv[1:] if argv is None else list(argv)
    # the command is the first argument (the program itself has no options but --help)
    parser = build_parser(argv[0] if argv else None)
    try:
        try:
            args = parser.parse_args(argv)
        except SystemExit as done:  # --help: argparse printed it and wants to exit
            return 0 if done.code is None else done.code
        return args.run(args)
    except _USER_ERRORS as err:
        print(f"diffshade: error: {_one_line(err)}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(program())

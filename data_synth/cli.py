"""`diffshade synth -o DATASET`: write a synthetic fitting dataset folder (docs/cli.md).

    diffshade synth [--shape icosphere|torus|box|MESH_FILE] [--material random|KA,KD,KS,N|
        FILE.json] [--views 3] [--lights 2] [--size 128] [--seed 0] [--quantize-8bit]
        [--noise STD] [--shading phong] [--texture RES] -o DATASET
    diffshade synth --scene SCENE.json [--views ...] -o DATASET

--scene takes the objects (or the mesh), their materials (the truth), the model
transform, global ambient, lighting switches and settings from a scene file; the cameras
and lights are synth's layout, as for --shape (the file's own are not used).

The dataset (data_synth.make_dataset: views x lights images, the true material) is built
in memory, saved by `save_dataset` into a new hidden folder beside DATASET, and renamed to
DATASET: a reader never sees a half-written dataset, and a failure leaves nothing behind.
An existing DATASET is replaced when it is a dataset folder (it has a dataset.json) or
empty; any other existing path is an error, checked before rendering.
"""

import os
import shutil
import uuid

from data_synth import background
from data_synth.options import what
from data_synth.scenes import make_dataset
from diffshade.io import check_writable
from diffshade.settings import SHADING_MODES
from fitting.data.folder import save_dataset
from fitting.inputs import non_negative_float, positive_int


def register(subparsers):
    parser = subparsers.add_parser(
        "synth", help="make a synthetic dataset folder for 'diffshade fit'",
        description="Render a built-in shape or a mesh file with a known (given or random) "
                    "material from several cameras, each with several lights (one image per "
                    "camera and light), and write the dataset folder: targets as float .npy "
                    "and 8-bit PNG, scene files (with the mesh) and truth.json.")
    parser.add_argument("--shape", metavar="icosphere|torus|box|PATH",
                        help="built-in shape or mesh file (default icosphere)")
    parser.add_argument("--scene", metavar="SCENE.json",
                        help="a scene file whose objects (or mesh) and materials are "
                             "rendered instead of --shape (its cameras and lights are not "
                             "used; see docs/objects.md)")
    parser.add_argument("--material", metavar="random|KA,KD,KS,N|FILE",
                        help="'random' (from --seed), 4 numbers (grey ka, kd, ks and "
                             "shininess) or a JSON file with ka, kd, ks, shininess")
    parser.add_argument("--views", type=positive_int, default=3, help="cameras (default 3)")
    parser.add_argument("--lights", type=positive_int, default=2,
                        help="lights per camera, one image each (default 2)")
    parser.add_argument("--size", type=positive_int, default=128,
                        help="image width and height in pixels (default 128)")
    parser.add_argument("--seed", type=int, default=0,
                        help="random material and noise seed, >= 0 (default 0)")
    parser.add_argument("--quantize-8bit", action="store_true",
                        help="round the targets to 8 bits")
    parser.add_argument("--noise", type=non_negative_float, default=0.0, metavar="STD",
                        help="Gaussian noise standard deviation (default 0)")
    parser.add_argument("--shading", choices=SHADING_MODES,
                        help="shading mode of the targets (default phong; with --scene, the "
                             "file's settings.shading)")
    parser.add_argument("--texture", type=positive_int, metavar="RES",
                        help="the true kd is a known procedural texture of RES x RES "
                             "texels over the shape's UVs (docs/textures.md); written as "
                             "truth.kd.npy and truth.kd.png")
    parser.add_argument("-o", "--output", required=True, metavar="DATASET",
                        help="dataset folder to write")
    parser.set_defaults(run=run_synth)


def _check_output(path):
    """DATASET may be new, an empty folder or a dataset folder (replaced), in a writable
    folder."""
    if not os.path.exists(path):
        check_writable(path, "--output", "replaced")
        return
    if not os.path.isdir(path):
        raise ValueError(f"--output: {path!r} is a file; expected a dataset folder to write")
    if os.listdir(path) and not os.path.isfile(os.path.join(path, "dataset.json")):
        raise ValueError(f"--output: {path!r} is a folder with other files in it; expected a "
                         "new path, an empty folder or a dataset folder to replace")
    check_writable(path, "--output", "replaced")


def _replace_folder(new, target):
    """Rename the folder `new` to `target`, replacing an existing `target` folder."""
    if not os.path.exists(target):
        os.rename(new, target)
        return
    old = os.path.join(os.path.dirname(target),
                       f".{os.path.basename(target)}.{uuid.uuid4().hex[:12]}.old")
    os.rename(target, old)
    try:
        os.rename(new, target)
    except BaseException:
        os.rename(old, target)
        raise
    shutil.rmtree(old)


def save_dataset_atomically(dataset, out_dir) -> str:
    """save_dataset into a hidden folder beside out_dir, then rename it to out_dir."""
    out_dir = os.path.abspath(os.fspath(out_dir))
    parent, name = os.path.split(out_dir)
    os.makedirs(parent, exist_ok=True)
    tmp = os.path.join(parent, f".{name}.{uuid.uuid4().hex[:12]}.tmp")
    try:
        os.mkdir(tmp)  # not tempfile.mkdtemp: its 0o700 would outlive the rename
    except OSError as err:  # the user's path, not the hidden temporary, is what failed
        raise type(err)(err.errno, err.strerror, out_dir) from None
    try:
        save_dataset(dataset, tmp)
        _replace_folder(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out_dir


def run_synth(args) -> int:
    """The `synth` command: prints the dataset folder's path. While it renders, the fit of
    the dataset compiles in the background (data_synth.background)."""
    _check_output(args.output)
    if args.seed < 0:
        raise ValueError(f"--seed: got {args.seed}; expected an integer >= 0")
    shape, material, settings = what(args)
    process, failed = background.start(args), True
    try:
        dataset = make_dataset(shape, material, n_views=args.views, n_lights=args.lights,
                               size=args.size, seed=args.seed,
                               quantize_8bit=args.quantize_8bit, noise_std=args.noise,
                               shading=args.shading or "phong", settings=settings,
                               texture=args.texture)
        save_dataset_atomically(dataset, args.output)
        failed = False
    finally:
        background.finish(process, failed)
    print(args.output)
    return 0

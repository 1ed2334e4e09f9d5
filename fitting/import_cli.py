"""`diffshade import SOURCE --scene SCENE.json -o DATASET`: a dataset folder from a
calibrated capture (fitting.data.capture; docs/calibrated-cameras.md).

SOURCE is a COLMAP sparse model in text form (a folder with cameras.txt and images.txt;
--images names the folder of its photos) or a Blender/NeRF transforms.json. Everything is
checked before anything is written; a problem is a ValueError or OSError, which
diffshade.cli prints as one line (exit 2).
"""

from fitting.data.capture import import_capture


def register(subparsers):
    parser = subparsers.add_parser(
        "import", help="make a dataset folder from a COLMAP model or a transforms.json",
        description="Write a dataset folder for 'diffshade fit' from a calibrated capture: "
                    "a COLMAP sparse model in text form (cameras.txt, images.txt) or a "
                    "Blender/NeRF transforms.json, with the mesh, lights and settings of "
                    "SCENE.json (its cameras are replaced by the capture's). The photos "
                    "are referenced, not copied.")
    parser.add_argument("source", metavar="SOURCE",
                        help="COLMAP model folder (cameras.txt, images.txt) or transforms.json")
    parser.add_argument("--scene", required=True, metavar="SCENE.json",
                        help="scene file with the mesh, lights, material and settings")
    parser.add_argument("--images", metavar="DIR",
                        help="COLMAP only: the folder images.txt's names are relative to")
    parser.add_argument("-o", "--output", required=True, metavar="DATASET",
                        help="dataset folder to write (created if missing)")
    parser.set_defaults(run=_run)


def _run(args):
    print(import_capture(args.source, args.scene, args.output, args.images))
    return 0

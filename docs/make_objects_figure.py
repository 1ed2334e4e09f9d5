"""docs/img/objects.png: a scene of three objects, each with its own mesh, transform and
material: a glossy red sphere and a blue torus on a grey table top.

    PYTHONPATH=. python docs/make_objects_figure.py [--out docs/img/objects.png]
"""

import argparse
import os

import diffshade as ds


def table_scene(width=320, height=200):
    """The figure's scene (also what docs/objects.md describes)."""
    objects = [
        ds.scene_object(ds.box((3.0, 0.2, 2.0)), ds.material(ka=0.2, kd=0.55),
                        transform=ds.model_matrix((0.0, -0.1, 0.0))),
        ds.scene_object(ds.icosphere(4, 0.5),
                        ds.material(ka=0.2, kd=(0.7, 0.1, 0.08), ks=0.6, shininess=60.0),
                        transform=ds.model_matrix((-0.6, 0.5, 0.1))),
        ds.scene_object(ds.torus(0.45, 0.15, 48, 24),
                        ds.material(ka=0.2, kd=(0.1, 0.25, 0.7), ks=0.3, shininess=20.0),
                        transform=ds.model_matrix((0.75, 0.15, 0.2), (0.0, 30.0, 0.0))),
    ]
    camera = ds.look_at((0.0, 1.6, 3.4), (0.0, 0.2, 0.0), width=width, height=height,
                        fov_y=40.0)
    lights = [ds.directional_light((-0.4, -1.0, -0.6), 0.8),
              ds.point_light((1.5, 2.0, 2.0), (0.4, 0.38, 0.35))]
    return ds.make_scene(objects=objects, camera=camera, lights=lights, global_ambient=0.25,
                         background=(0.9, 0.92, 0.95))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "img",
                                                      "objects.png"))
    args = parser.parse_args(argv)
    image = ds.render(table_scene(), ds.RenderSettings(shading="phong"))
    print(ds.write_png(args.out, image[..., :3]))


if __name__ == "__main__":
    main()

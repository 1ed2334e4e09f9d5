"""docs/img/shadows.png: a sphere over a floor lit by a point light, rendered without
shadows | with shadows (hard raster; the exact shadow's edge drawn in red) | with shadows
in soft raster. Written as an sRGB PNG.

    PYTHONPATH=. python docs/make_shadow_figure.py [--out docs/img/shadows.png]
"""

import argparse
import os

import numpy as np

import diffshade as ds
from diffshade.analytic import SphereOverPlane

GEOMETRY = SphereOverPlane()
LIGHT = (-1.0, 1.8, -1.0)
SIZE = 192


def scene(shadows):
    camera = ds.look_at((0.0, 4.5, 3.2), (0.0, -1.0, 0.5), width=SIZE, height=SIZE, fov_y=40.0)
    light = ds.point_light(LIGHT, 0.9, ambient=0.1, shadows=shadows)
    return ds.make_scene(GEOMETRY.mesh(3, 8), camera, [light],
                         ds.material(ka=0.3, kd=(0.7, 0.6, 0.5), ks=0.3, shininess=30.0),
                         global_ambient=0.2, background=(0.05, 0.05, 0.08))


def exact_edge(camera):
    """Pixels on the boundary of the exact shadow: [H, W] bool."""
    _, shadow = GEOMETRY.shadow(camera, ("point", LIGHT))
    m = np.pad(shadow, 1, mode="edge")
    return shadow & ~(m[:-2, 1:-1] & m[2:, 1:-1] & m[1:-1, :-2] & m[1:-1, 2:])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "img",
                                                      "shadows.png"))
    args = parser.parse_args(argv)
    maps = ds.RenderSettings(shadow_map_size=512)
    soft = ds.RenderSettings(raster="soft", sigma=0.5, gamma=1e-4, shadow_map_size=512)
    plain = np.asarray(ds.render(scene(False)))[..., :3]
    hard = np.array(ds.render(scene(True), maps))[..., :3]
    hard[exact_edge(scene(True).camera)] = (1.0, 0.0, 0.0)
    smooth = np.asarray(ds.render(scene(True), soft))[..., :3]
    gap = np.ones((SIZE, 4, 3))
    ds.write_png(args.out, np.concatenate([plain, gap, hard, gap, smooth], 1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

"""docs/img/shadows.png: a sphere over a floor lit by a point light, rendered without
shadows | with shadows (hard raster; the exact shadow's edge drawn in red) | with shadows
in soft raster. docs/img/penumbra.png: the same sphere under a point light | a disk light
| a sphere light of the same power at the same place, all with shadows (umbra and
penumbra). Written as sRGB PNGs.

    PYTHONPATH=. python docs/make_shadow_figure.py [--out docs/img/shadows.png]
        [--penumbra-out docs/img/penumbra.png]
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


#: the penumbra figure's lights: centre, and a disk's normal and radius, a sphere's radius
EXTENDED_AT, DISK_RADIUS, BALL_RADIUS = (-0.5, 2.0, -1.0), 0.6, 0.6


def penumbra_scene(kind):
    """The sphere over the floor under one light with shadows: a point light (at
    EXTENDED_AT, attenuation 1/d^2 as the extended lights'), or a disk or a sphere light there."""
    camera = ds.look_at((0.0, 4.5, 3.2), (0.0, -1.0, 0.5), width=SIZE, height=SIZE, fov_y=40.0)
    colour = {"ambient": 0.05, "color": 4.0, "shadows": True}
    light = {"point": lambda: ds.point_light(EXTENDED_AT, attenuation=(1e-6, 0.0, 1.0),
                                             **colour),
             "disk": lambda: ds.area_light(EXTENDED_AT, normal=(0.0, -1.0, 0.0),
                                           radius=DISK_RADIUS, samples=32, **colour),
             "sphere": lambda: ds.sphere_light(EXTENDED_AT, BALL_RADIUS, samples=64,
                                               **colour)}[kind]()
    return ds.make_scene(GEOMETRY.mesh(3, 8), camera, [light],
                         ds.material(ka=0.3, kd=(0.7, 0.6, 0.5), ks=None),
                         global_ambient=0.2, background=(0.05, 0.05, 0.08))


def penumbra_figure(out):
    settings = ds.RenderSettings(shadow_map_size=128)
    panels = [np.asarray(ds.render(penumbra_scene(kind), settings))[..., :3]
              for kind in ("point", "disk", "sphere")]
    gap = np.ones((SIZE, 4, 3))
    ds.write_png(out, np.concatenate([panels[0], gap, panels[1], gap, panels[2]], 1))
    print(f"wrote {out}")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    here = os.path.join(os.path.dirname(__file__), "img")
    parser.add_argument("--out", default=os.path.join(here, "shadows.png"))
    parser.add_argument("--penumbra-out", default=os.path.join(here, "penumbra.png"))
    args = parser.parse_args(argv)
    penumbra_figure(args.penumbra_out)
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

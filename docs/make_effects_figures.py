"""docs/img/transparency.png and docs/img/area_lights.png.

transparency.png: a sphere whose front faces have the transparent material (kt) in front
of a floor, both seen from their back side lit by the opaque back material (two-sided
lighting), for kt = 0, 0.5, 0.8 in hard raster and kt = 0.5 in soft raster.
area_lights.png: one sphere on a floor lit by a point light (attenuation 1/d^2), a
rectangle, a disk and a sphere light of the same colour at the same place.

    PYTHONPATH=. python docs/make_effects_figures.py [--size 128]
"""

import argparse
import os

import numpy as np

import diffshade as ds

HERE = os.path.dirname(os.path.abspath(__file__))


def sphere_and_floor(floor_clockwise):
    """One mesh: an icosphere resting on a 6 x 6 floor at y = -1 (floor faces wound so that
    the camera above sees their front, or their back with floor_clockwise)."""
    ball = ds.icosphere(3)
    verts = np.asarray(ball.vertices, np.float64)
    faces = np.asarray(ball.faces)
    floor = np.array([[-3, -1, -3], [3, -1, -3], [3, -1, 3], [-3, -1, 3]], np.float64)
    quads = [[0, 2, 1], [0, 3, 2]] if not floor_clockwise else [[0, 1, 2], [0, 2, 3]]
    return ds.mesh_from_arrays(np.concatenate([verts, floor]),
                               np.concatenate([faces, np.array(quads) + len(verts)]))


def camera(size):
    return ds.look_at((0.0, 1.6, 4.2), (0.0, -0.3, 0.0), width=size, height=size, fov_y=45.0)


def transparency_panels(size):
    mesh = sphere_and_floor(floor_clockwise=True)
    light = ds.directional_light((-0.4, -1.0, -0.6), 0.8)
    back = ds.material(ka=0.3, kd=(0.25, 0.55, 0.3))
    panels = []
    for kt, raster in ((0.0, "hard"), (0.5, "hard"), (0.8, "hard"), (0.5, "soft")):
        front = ds.material(ka=0.2, kd=(0.8, 0.3, 0.2), ks=0.6, shininess=40.0, kt=kt)
        scene = ds.make_scene(mesh, camera(size), [light], front, back_material=back,
                              two_sided=True, background=(0.9, 0.9, 0.95))
        # soft: K must hold the faces whose footprint reaches a pixel (up to 6 at a vertex)
        # and the layers behind them
        settings = ds.RenderSettings(raster=raster, sigma=0.1, gamma=1e-3, faces_per_pixel=16)
        panels.append((f"kt = {kt:g}, {raster} raster", ds.render(scene, settings)))
    return panels


def area_light_panels(size):
    mesh = sphere_and_floor(floor_clockwise=False)
    mat = ds.material(ka=0.1, kd=(0.75, 0.7, 0.6), ks=0.5, shininess=30.0)
    at, colour = (1.2, 1.8, 1.0), 2.5
    down = np.array([-1.2, -1.8, -1.0]) / np.linalg.norm([1.2, 1.8, 1.0])
    tangent = np.cross(down, [0.0, 1.0, 0.0])
    tangent /= np.linalg.norm(tangent)
    lights = [
        ("point light, 1/d^2", ds.point_light(at, colour, attenuation=(1e-6, 0.0, 1.0))),
        ("rectangle 1.6 x 1.6", ds.area_light(at, 1.6 * tangent, 1.6 * np.cross(down, tangent),
                                              color=colour, samples=64)),
        ("disk, radius 0.9", ds.area_light(at, normal=down, radius=0.9, color=colour,
                                           samples=64)),
        ("sphere, radius 0.6", ds.sphere_light(at, 0.6, colour, samples=64)),
    ]
    panels = []
    for name, light in lights:
        scene = ds.make_scene(mesh, camera(size), [light], mat, global_ambient=0.05,
                              background=0.02)
        panels.append((name, ds.render(scene)))
    return panels


def save(panels, path):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(2.6 * len(panels), 2.9))
    for ax, (title, image) in zip(axes, panels, strict=True):
        ax.imshow(ds.linear_to_srgb(np.clip(np.asarray(image)[..., :3], 0.0, 1.0)))
        ax.set_title(title, fontsize=9)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    print(f"wrote {path}")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=128)
    args = parser.parse_args(argv)
    save(transparency_panels(args.size), os.path.join(HERE, "img", "transparency.png"))
    save(area_light_panels(args.size), os.path.join(HERE, "img", "area_lights.png"))


if __name__ == "__main__":
    main()

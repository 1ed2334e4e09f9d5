"""What undistorting photos on load costs in accuracy (docs/calibrated-cameras.md).

    PYTHONPATH=. python benchmarks/undistortion.py [--size 128] [--supersample 4]

diffshade renders a camera's pinhole image; a dataset whose cameras have lens distortion
has its photos resampled into that image on load (bilinear, diffshade.io.undistort). This
measures what the resampling does, against photos made exactly: the exact sphere
(diffshade.analytic) seen through a calibrated camera (fx != fy, principal point off the
centre by (+6, -4) px at 128 px, mild barrel distortion k1 = -0.12, k2 = 0.03 and
tangential terms), each photo pixel the mean of supersample^2 rays through the lens (each
sub-pixel position undistorted by fixed-point iteration). The reference is the same
sphere rendered directly into the pinhole camera. Rows:

- image error: the undistorted photo against the pinhole reference over the pixels that
  count after undistortion (io.undistort_mask), all of them and away from the silhouette
  (both images fully covered); as float photos and as 8-bit sRGB photos (then decoded).
- fit: kd and ka recovered by the linear solver (a subdivision-5 icosphere, the default
  silhouette margin of 1 px) from the pinhole reference and from the undistorted photos:
  the difference is the resampling's effect on the fitted material.
"""

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import print_table  # noqa: E402

import diffshade as ds  # noqa: E402
from diffshade.analytic import sphere_at_ndc  # noqa: E402
from diffshade.io import (  # noqa: E402
    decode,
    encode,
    pinhole,
    undistort_image,
    undistort_mask,
    undistort_points,
)
from diffshade.scene import opencv_intrinsics  # noqa: E402
from fitting import Dataset, FitSpec, View, fit  # noqa: E402

TRUTH = ds.material(ka=(0.3, 0.25, 0.2), kd=(0.6, 0.45, 0.3), ks=0.0)
DIST = [-0.12, 0.03, 0.001, -0.0005]
EYES = [(0.0, 0.3, 3.4), (2.2, 0.8, 2.4), (-2.0, -0.6, 2.6)]


def calibrated_camera(eye, size):
    """A camera looking at the origin with fx != fy, an off-centre principal point and
    DIST, for a size x (3/4 size) image."""
    width, height = size, size * 3 // 4
    look = ds.look_at(eye, (0.0, 0.0, 0.0), width=width, height=height)
    pose = ds.camera_to_opencv(look)
    scale = size / 128.0
    K = [[165.0 * scale, 0.0, width / 2 - 0.5 + 6 * scale],
         [0.0, 150.0 * scale, height / 2 - 0.5 - 4 * scale], [0.0, 0.0, 1.0]]
    return ds.camera_from_opencv(K, pose["R"], pose["t"], width, height, dist=DIST)


def sub_pixels(camera, supersample):
    """OpenCV pixel positions of supersample^2 sub-pixel samples: [H, W, S, 2]."""
    offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
    du, dv = (a.ravel() for a in np.meshgrid(offsets, offsets))
    u, v = np.meshgrid(np.arange(camera.width, dtype=float), np.arange(camera.height,
                                                                          dtype=float))
    return np.stack([u[..., None] + du, v[..., None] + dv], -1)


def exact_image(scene, settings, positions, undistort):
    """The exact sphere's RGBA [H, W, 4] at sub-pixel positions [H, W, S, 2] of the
    camera's photo (undistort: through the lens) or of its pinhole image."""
    camera = scene.camera
    K = np.asarray(opencv_intrinsics(camera), np.float64)
    xy = (positions - K[:2, 2]) / np.diag(K)[:2]
    if undistort:
        xy = undistort_points(camera.dist, xy)
    u, v = xy[..., 0] * K[0, 0] + K[0, 2], xy[..., 1] * K[1, 1] + K[1, 2]
    ndc = np.stack([2 * (u + 0.5) / camera.width - 1, 1 - 2 * (v + 0.5) / camera.height], -1)
    return np.asarray(sphere_at_ndc(ds.replace(scene, camera=pinhole(camera)), settings, ndc))


def views(size, supersample, eight_bit):
    """[(pinhole camera, lights, reference RGBA, undistorted photo, its mask)] per eye."""
    settings = ds.RenderSettings()
    lights = [ds.directional_light((-0.5, -0.6, -1.0), color=0.8),
              ds.point_light((1.5, 2.0, 3.0), color=0.6)]
    out = []
    for eye in EYES:
        camera = calibrated_camera(eye, size)
        scene = ds.make_scene(ds.icosphere(1), camera, lights, TRUTH)
        positions = sub_pixels(camera, supersample)
        reference = exact_image(scene, settings, positions, undistort=False)
        photo = exact_image(scene, settings, positions, undistort=True)[..., :3]
        if eight_bit:
            photo = decode(np.round(encode(photo, "srgb") * 255) / 255, "srgb")
        out.append((pinhole(camera), lights, reference, undistort_image(photo, camera),
                    undistort_mask(None, camera)))
    return out


def image_row(shots, label):
    errors, interior = [], []
    for _, _, reference, undistorted, mask in shots:
        diff = np.abs(undistorted - reference[..., :3])
        covered = np.ones_like(mask)
        for shift in ((0, 1), (0, -1), (1, 0), (-1, 0)):  # no neighbour on the silhouette
            covered &= np.roll(reference[..., 3], shift, (0, 1)) == 1
        covered &= reference[..., 3] == 1
        errors.append(diff[mask])
        interior.append(diff[mask & covered])
    every, inner = np.concatenate(errors), np.concatenate(interior)
    rms = float(np.sqrt(np.mean(every**2)))
    kept = float(np.mean([m.mean() for *_, m in shots]))
    return {"photos": label, "kept": kept, "rms": rms, "psnr": -20 * math.log10(rms),
            "max": float(every.max()), "inner_rms": float(np.sqrt(np.mean(inner**2))),
            "inner_max": float(inner.max())}


def fitted(shots, use_reference):
    data = [View(cam, lights, ref[..., :3] if use_reference else photo,
                 mask if not use_reference else None)
            for cam, lights, ref, photo, mask in shots]
    dataset = Dataset(ds.icosphere(5), data, truth=TRUTH, settings=ds.RenderSettings())
    start = ds.material(ka=0.5, kd=0.5, ks=0.0)  # no specular, as the truth
    result = fit(dataset, FitSpec(ks=None, shininess=None), start, method="linear",
                 with_uncertainty=False)
    return {name: np.asarray(getattr(result.material, name)) for name in ("ka", "kd")}


def fit_row(shots, label):
    reference, photos = fitted(shots, True), fitted(shots, False)
    row = {"photos": label}
    for name in ("ka", "kd"):
        truth = np.asarray(getattr(TRUTH, name))
        row[f"{name}_ref"] = float(np.max(np.abs(reference[name] - truth) / truth))
        row[f"{name}_undist"] = float(np.max(np.abs(photos[name] - truth) / truth))
        row[f"{name}_diff"] = float(np.max(np.abs(photos[name] - reference[name])))
    return row


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=128)
    parser.add_argument("--supersample", type=int, default=4)
    args = parser.parse_args(argv)
    images, fits = [], []
    for eight_bit, label in ((False, "float"), (True, "8-bit sRGB")):
        shots = views(args.size, args.supersample, eight_bit)
        images.append(image_row(shots, label))
        fits.append(fit_row(shots, label))
    print(f"undistorted photos against the pinhole reference ({args.size} px wide, "
          f"{args.supersample}x{args.supersample} rays per pixel, {len(EYES)} views)")
    print_table(images, [("photos", "photos", "{}"), ("kept", "pixels kept", "{:.3f}"),
                         ("rms", "RMS", "{:.2e}"), ("psnr", "PSNR dB", "{:.1f}"),
                         ("max", "max", "{:.3f}"), ("inner_rms", "RMS inside", "{:.2e}"),
                         ("inner_max", "max inside", "{:.2e}")])
    print("\nlinear fit of ka, kd (relative error against the truth; abs. difference)")
    print_table(fits, [("photos", "photos", "{}"),
                       ("kd_ref", "kd err (pinhole)", "{:.2e}"),
                       ("kd_undist", "kd err (undistorted)", "{:.2e}"),
                       ("kd_diff", "|kd diff|", "{:.1e}"),
                       ("ka_ref", "ka err (pinhole)", "{:.2e}"),
                       ("ka_undist", "ka err (undistorted)", "{:.2e}"),
                       ("ka_diff", "|ka diff|", "{:.1e}")])


if __name__ == "__main__":
    main()

"""A calibrated capture made by another renderer (Mitsuba 3), fitted with `diffshade fit`.

    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 \\
        PYTHONPATH=. python benchmarks/capture.py [--spp 16] [--oversample 3]

The capture: a unit sphere (icosphere, subdivision 4, exact vertex normals) of known
diffuse albedo ALBEDO, lit by two point emitters of known radiant intensity (W/sr), seen
by five calibrated cameras with OpenCV intrinsics as a real calibration has them:
non-square pixels (fx != fy), a principal point off the centre by (+7, -5) px, and mild
barrel distortion (k1, k2). Diffuse only: Mitsuba 3 has no BSDF that is diffshade's
Blinn-Phong lobe, so the specular terms are not compared (ks = 0 is kept fixed).

How the photos are made (the lens): Mitsuba (variant llvm_ad_rgb, the `direct` integrator
with one emitter sample and no BSDF sample, which is all a convex object under point
lights receives, one render per emitter summed so that no light is chosen at random; a
`diffuse` BSDF of reflectance ALBEDO; box pixel filter) renders each camera's *pinhole*
image with square pixels, `--oversample` times finer than the photo and wide enough for every
photo pixel's undistorted position. Mitsuba's sensor has principal-point offsets but no
fx != fy and no lens distortion, so the photo is made from that image in NumPy: each
photo pixel is the mean of `--lens-samples`^2 sub-pixel positions, each taken through
OpenCV's model backwards (normalized distorted coordinates undistorted by fixed-point
iteration, `lens.undistort_normalized`) into the pinhole image and sampled there bilinearly
(`lens.lens_photo`). The photo is then 8-bit sRGB, its mask the lens-resampled coverage.

The dataset folder (written to --data, a temporary folder by default) is what a user with
a capture writes: scene.json with the cameras in OpenCV form (K, R, t, dist), the lights
as point lights of attenuation (0, 0, 1) and colour I / pi (docs/light-units.md), the
built-in mesh; dataset.json with one view per photo and its mask. `diffshade fit --fit kd
--holdout 4 --edge-margin 2` fits the albedo on four views (undistorting photos and
masks on load) and scores the fifth; the margin is 2 px because the outline is resampled
twice (by the lens here, by the undistortion on load), each bilinear step reaching one
pixel further. Printed: kd against the albedo beside the 8-bit rounding bound (and the
standard error), the held-out view's PSNR beside what 8-bit quantization allows (and how
much of its sRGB error lies on the terminator's darkest pixels), the misfit check, and a
camera check (silhouette IoU of the undistorted photo's coverage against diffshade's own
render of the pinhole camera). Without Mitsuba one line says so and the script exits 0.

The 8-bit figures are `diffshade fit`'s own (result.json's rounding_bound and the
held-out view's psnr_*_8bit): undistortion on load mixes neighbouring codes, so the
loaded targets are no longer 8-bit codes, and the fit carries each photo pixel's half code
step through the bilinear weights instead (fitting.data.rounding, docs/real-capture.md).
"""

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peers  # noqa: E402
from common import finish_record, run_record  # noqa: E402
from lens import lens_photo, pinhole_frame  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
ALBEDO = (0.62, 0.45, 0.28)
WIDTH, HEIGHT = 160, 120
K = [[190.0, 0.0, WIDTH / 2 - 0.5 + 7.0], [0.0, 174.0, HEIGHT / 2 - 0.5 - 5.0],
     [0.0, 0.0, 1.0]]
DIST = [-0.08, 0.015, 0.0, 0.0]
EYES = [(0.4, 0.6, 3.5), (2.4, 1.2, 2.4), (-2.0, 0.9, 2.8), (1.0, 2.6, 2.3),
        (-0.6, -0.4, 3.5)]
#: (position, radiant intensity W/sr per channel)
EMITTERS = [((2.5, 3.0, 3.5), (60.0, 60.0, 60.0)), ((-3.0, 1.0, 2.0), (20.0, 24.0, 30.0))]
HOLDOUT, EDGE_MARGIN = 4, 2
SUBDIVISIONS = 4
VARIANT = "llvm_ad_rgb"


def opencv_pose(eye):
    """OpenCV (R, t) of a camera at `eye` looking at the origin, y up in the world."""
    import diffshade as ds

    pose = ds.camera_to_opencv(ds.look_at(eye, (0.0, 0.0, 0.0), width=WIDTH, height=HEIGHT))
    return np.asarray(pose["R"], np.float64), np.asarray(pose["t"], np.float64)


def mitsuba_to_world(R, t):
    """Mitsuba's sensor to_world for OpenCV pose (R, t): the camera-to-world matrix with
    Mitsuba's local axes (x left, y up, z forward) = OpenCV's (-x, -y, z)."""
    to_world = np.eye(4)
    to_world[:3, :3], to_world[:3, 3] = R.T, -R.T @ t
    return to_world @ np.diag([-1.0, -1.0, 1.0, 1.0])


def mitsuba_pinhole(mi, shape, R, t, frame, spp, emitters=EMITTERS):
    """Mitsuba's RGBA pinhole image [H, W, 4] (linear radiance) of the shape made by
    `shape()` (a fresh Mitsuba shape per render) from pose (R, t) in the square-pixel frame
    (focal, width, height) of pinhole_frame, lit by `emitters` ((position, radiant
    intensity)). One render per emitter, summed: with several lights Mitsuba samples one
    of them per path, which is noise; a single point light seen directly is exact (only
    the pixel filter samples)."""
    focal, big_w, big_h = frame
    film = {"type": "hdrfilm", "width": big_w, "height": big_h, "rfilter": {"type": "box"},
            "pixel_format": "rgba"}
    sensor = {"type": "perspective", "fov_axis": "x",
              "fov": math.degrees(2 * math.atan(big_w / 2 / focal)), "near_clip": 0.1,
              "far_clip": 100.0, "film": film,
              "to_world": mi.ScalarTransform4f(mitsuba_to_world(R, t).tolist()),
              "sampler": {"type": "independent", "sample_count": spp}}
    renders = []
    for position, intensity in emitters:
        light = {"type": "point", "position": list(position),
                 "intensity": {"type": "rgb", "value": list(intensity)}}
        scene = mi.load_dict({"type": "scene", "sensor": sensor, "light": light,
                              "integrator": {"type": "direct", "emitter_samples": 1,
                                             "bsdf_samples": 0},
                              "object": shape()})
        renders.append(np.asarray(mi.render(scene, spp=spp), np.float64))
    # the colours add; the coverage (alpha) is the same in every render
    return np.concatenate([sum(r[..., :3] for r in renders), renders[0][..., 3:]], -1)


def scene_file():
    """The capture's scene file (cameras in OpenCV form, lights in physical units)."""
    cameras = []
    for eye in EYES:
        R, t = opencv_pose(eye)
        cameras.append({"K": K, "R": R.tolist(), "t": t.tolist(), "width": WIDTH,
                        "height": HEIGHT, "dist": DIST})
    lights = [{"type": "point", "position": list(position),
               "color": [i / math.pi for i in intensity], "attenuation": [0, 0, 1]}
              for position, intensity in EMITTERS]
    return {"mesh": {"builtin": {"icosphere": {"subdivisions": SUBDIVISIONS}}},
            "cameras": cameras, "lights": lights, "global_ambient": 0.0,
            "material": {"ka": 0.0, "kd": 0.5, "ks": 0.0, "shininess": 10.0},
            "settings": {"shading": "phong"}}


def write_dataset(folder, photos, masks):
    """The dataset folder a user with this capture writes: scene.json, the 8-bit sRGB
    photos and masks, dataset.json."""
    from diffshade.io import write_json, write_png

    os.makedirs(folder, exist_ok=True)
    write_json(os.path.join(folder, "scene.json"), scene_file())
    views = []
    for i, (photo, mask) in enumerate(zip(photos, masks, strict=True)):
        write_png(os.path.join(folder, f"photo_{i}.png"), photo, color_space="srgb")
        write_png(os.path.join(folder, f"mask_{i}.png"),
                  np.repeat((mask > 0.5)[..., None], 3, -1).astype(np.float32),
                  color_space="linear")
        views.append({"scene": "scene.json", "camera": i, "image": f"photo_{i}.png",
                      "mask": f"mask_{i}.png"})
    write_json(os.path.join(folder, "dataset.json"),
               {"format": "diffshade-dataset", "version": 1, "views": views,
                "info": {"made_by": "benchmarks/capture.py (Mitsuba 3)",
                         "albedo": list(ALBEDO)}})


def photograph(args):
    """(photos [H, W, 3] linear, coverage [H, W]) per camera, from Mitsuba; or the reason
    Mitsuba cannot run (a string)."""
    try:
        import mitsuba as mi
        mi.set_variant(VARIANT)
    except (ImportError, AttributeError) as err:
        return f"{type(err).__name__}: {err}".splitlines()[0]
    import diffshade as ds

    sphere = ds.icosphere(SUBDIVISIONS)
    mesh = {name: np.asarray(getattr(sphere, name), np.float32)
            for name in ("vertices", "normals")}
    mesh["faces"] = np.asarray(sphere.faces, np.uint32)
    frame = pinhole_frame(K, DIST, WIDTH, HEIGHT, args.lens_samples, args.oversample)
    shots = []
    for eye in EYES:
        image = mitsuba_pinhole(mi, lambda: peers.mitsuba_mesh(mi, mesh, ALBEDO),
                                *opencv_pose(eye), frame, args.spp)
        photo = lens_photo(image, frame[0], K, DIST, WIDTH, HEIGHT, args.lens_samples)
        shots.append((photo[..., :3], photo[..., 3]))
    return shots


def camera_check(coverages):
    """Per view, the silhouette IoU of the photo's coverage [H, W] undistorted as on load
    (> 0.5) against diffshade's render of the pinhole camera (alpha > 0.5)."""
    import diffshade as ds
    from diffshade.io import pinhole, undistort_image

    scenes, settings = ds.scenes_from_dict(scene_file())
    out = []
    for scene, coverage in zip(scenes, coverages, strict=True):
        flat = ds.replace(scene, camera=pinhole(scene.camera))
        ours = np.asarray(ds.render(flat, settings))[..., 3] > 0.5
        theirs = undistort_image(coverage[..., None], scene.camera)[..., 0] > 0.5
        out.append(float((ours & theirs).sum() / max(int((ours | theirs).sum()), 1)))
    return out


def fit(folder, result_dir, steps):
    """Run `diffshade fit` on the folder (kd only, view HOLDOUT held out); its result.json.
    ka = ks = 0 fixed: the capture has no ambient light and no specular lobe."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    cmd = [sys.executable, "-m", "diffshade", "fit", folder, "-o", result_dir, "--fit", "kd",
           "--init", "0,0.5,0,10", "--holdout", str(HOLDOUT), "--steps", str(steps),
           "--edge-margin", str(EDGE_MARGIN), "--quiet"]
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    print(done.stdout + done.stderr, end="")
    if done.returncode != 0:
        raise SystemExit(f"diffshade fit exited with status {done.returncode}")
    with open(os.path.join(result_dir, "result.json")) as f:
        return json.load(f)


def dark_figures(folder, kd):
    """dark_share of the held-out view of the dataset in `folder`, rendered with kd."""
    import diffshade as ds
    from fitting import load_dataset
    from fitting.report.holdout import evaluate

    dataset = load_dataset(folder)
    material = ds.material(ka=0.0, kd=kd, ks=0.0, shininess=10.0)
    prediction, counted, _ = evaluate(dataset, HOLDOUT, material, EDGE_MARGIN)
    fitted = np.clip(np.asarray(prediction, np.float64), 0.0, 1.0)
    return dark_share(fitted, dataset.views[HOLDOUT].target, counted)


def dark_share(prediction, target, counted):
    """Where the held-out view's sRGB error lies: {"pixels": counted pixels darker than
    one 8-bit level (every channel of the target below 1/255: the terminator, where the
    sRGB curve is steepest), "share": their part of the squared sRGB error, "psnr_srgb_rest":
    the sRGB PSNR over the other counted pixels}."""
    from diffshade.io import encode

    target = np.clip(np.asarray(target, np.float64), 0.0, 1.0)
    error2 = (encode(prediction, "srgb") - encode(target, "srgb")) ** 2
    dark = counted & (target.max(axis=-1) < 1 / 255)
    rest = counted & ~dark
    return {"pixels": int(dark.sum()), "share": float(error2[dark].sum() / error2[counted].sum()),
            "psnr_srgb_rest": float(10 * np.log10(1 / error2[rest].mean()))}


def summary(result, dark, ious):
    """The benchmark's figures: kd against the albedo with the fit's rounding bound, the
    held-out view's PSNR and what 8-bit quantization allows (the fit's), and the camera
    check."""
    rows = []
    for channel, albedo, fitted in zip("rgb", ALBEDO, result["values"]["kd"], strict=True):
        name = f"kd[{channel}]"
        bound = result["rounding_bound"][name]
        rows.append({"parameter": name, "albedo": albedo, "fitted": fitted,
                     "error": fitted - albedo, "std_error": result["std_errors"][name],
                     "rounding_bound": bound, "within": bool(abs(fitted - albedo) <= bound)})
    held = {**result["holdout"][0], "dark": dark}
    return {"kd": rows, "holdout": held, "std_error_kind": result["std_error_kind"],
            "misfit": result["misfit"], "silhouette_iou": ious}


def report(figures):
    print("\nkd against the albedo (Mitsuba's diffuse reflectance)")
    print(f"{'parameter':>9}  {'albedo':>7}  {'fitted':>8}  {'error':>9}  {'± s.e.':>8}"
          f"  {'8-bit rounding bound':>20}  within")
    for r in figures["kd"]:
        print(f"{r['parameter']:>9}  {r['albedo']:7.4f}  {r['fitted']:8.5f}  "
              f"{r['error']:+9.2e}  {r['std_error']:8.1e}  {r['rounding_bound']:20.1e}  "
              f"{'yes' if r['within'] else 'NO'}")
    h = figures["holdout"]
    print(f"\nheld-out view {h['view']} ({h['pixels']} pixels): PSNR linear "
          f"{h['psnr_linear']:.2f} dB (8-bit allows {h['psnr_linear_8bit']:.2f} dB), sRGB "
          f"{h['psnr_srgb']:.2f} dB (8-bit allows {h['psnr_srgb_8bit']:.2f} dB)")
    dark = h["dark"]
    print(f"  its {dark['pixels']} pixels darker than 1/255 (the terminator) hold "
          f"{100 * dark['share']:.0f} % of the squared sRGB error; the other pixels: PSNR "
          f"sRGB {dark['psnr_srgb_rest']:.2f} dB")
    m = figures["misfit"]
    print(f"misfit ratio {m['ratio']:.2f} (rms {m['rms']:.2e}, floor {m['floor']:.2e}); "
          f"table shows {figures['std_error_kind']} standard errors")
    print("camera check: silhouette IoU, undistorted photo against diffshade's pinhole "
          "render, per view: " + ", ".join(f"{v:.4f}" for v in figures["silhouette_iou"]))



def add_photo_options(parser):
    """The options of how the photos are made (this script and texture_capture.py)."""
    parser.add_argument("--oversample", type=int, default=3,
                        help="the pinhole render's resolution over the photo's")
    parser.add_argument("--lens-samples", type=int, default=3,
                        help="sub-pixel positions a side per photo pixel")


def not_run(shots):
    """Whether photograph() said Mitsuba did not run (a message: printed here)."""
    if isinstance(shots, str):
        print(f"Mitsuba 3 did not run ({shots}); pip install '.[peers]' and see "
              "docs/performance.md")
    return isinstance(shots, str)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spp", type=int, default=16, help="Mitsuba samples per pixel")
    add_photo_options(parser)
    parser.add_argument("--steps", type=int, default=50, help="diffshade fit --steps")
    parser.add_argument("--data", help="write the dataset and result here (default: a "
                        "temporary folder)")
    parser.add_argument("--out", default=str(ROOT / "benchmarks/results/capture.json"))
    args = parser.parse_args(argv)
    record = run_record()
    shots = photograph(args)
    if not_run(shots):
        return
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.data or tmp
        write_dataset(os.path.join(folder, "data"), [p for p, _ in shots],
                      [c for _, c in shots])
        result = fit(os.path.join(folder, "data"), os.path.join(folder, "result"),
                     args.steps)
        dark = dark_figures(os.path.join(folder, "data"), result["values"]["kd"])
    figures = summary(result, dark, camera_check([c for _, c in shots]))
    report(figures)
    from diffshade.io import write_json

    write_json(args.out, {"run": finish_record(record), "spp": args.spp,
                          "oversample": args.oversample, "lens_samples": args.lens_samples,
                          "size": [WIDTH, HEIGHT], "K": K, "dist": DIST,
                          "emitters": EMITTERS, "albedo": ALBEDO, **figures})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

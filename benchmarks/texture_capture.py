"""A textured object photographed by another renderer (Mitsuba 3); its kd map recovered by
`diffshade fit --texture`.

    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 \\
        PYTHONPATH=. python benchmarks/texture_capture.py [--res 64] [--spp 16]

The capture: the unit sphere with longitude / latitude UVs (icosphere(4, uv=True): 5,120
faces, the seam's vertices split) whose diffuse albedo is data_synth's procedural kd
(data_synth.materials.procedural_kd_at, shifted by V_SHIFT in v) at the texel centres of
a RES x RES map (linear), lit by EMITTERS
(point lights of known radiant intensity all around it), seen by eight cameras around it
with benchmarks/capture.py's calibration (fx != fy, the principal point off the centre,
barrel distortion). Mitsuba (as capture.py: `direct` integrator, one render per emitter
summed, box pixel filter) renders a `diffuse` BSDF whose reflectance is a `bitmap` of the
same texels (bilinear, repeat, raw: read as linear) on the mesh's UVs; each photo is made
from a finer pinhole render through OpenCV's lens model (benchmarks/lens.py) and stored as
8-bit sRGB.

The texture conventions agree: Mitsuba's bitmap puts v = 0 on the image's top row,
diffshade (OBJ, OpenGL) on its bottom row, so the mesh goes to Mitsuba with (u, 1 - v)
(peers.mitsuba_mesh); both put texel centres at (i + 0.5) / RES and interpolate
bilinearly, neither mip-maps. The forward check tests that before any fit: diffshade's
render of each view with the true map against Mitsuba's photo; and again with the map
upside down, which a wrong v convention would read.

The dataset is what a user with this capture writes (scene.json: the cameras in OpenCV
form, the emitters as point lights of colour I / pi and attenuation (0, 0, 1), the
built-in icosphere with "uv": true; 8-bit sRGB photos; masks). `fit --texture` counts
every pixel its mask allows (it has no --edge-margin), so each mask is the photo's
coverage eroded by EDGE_MARGIN pixels: the outline's pixels mix object and background.
View HOLDOUT stays out of the folder that is fitted. `diffshade fit --texture kd=RES
--fit kd --init 0,0.5,0,10` (the map alone; ka = ks = 0: no ambient light, no specular
lobe) recovers the map.

Printed: the forward check (PSNR of diffshade's render with the true map against the
photos, per view, and what 8-bit rounding allows); the coverage (texels seen by 0, 1 and
>= 2 fitted views); the recovered map's PSNR against the truth over the texels >= 2 views
see, and over those of them at least two pixels wide (wide_texels: near the poles a
texel is narrower, a photo pixel averages several texels and the fit's model reads one
point) (linear, peak 1), beside the same fit on diffshade's own renders of the fitted
views rounded to 8-bit sRGB (what the rounding and the prior allow); the held-out view rendered
with the recovered map, PSNR linear and sRGB over the pixels that count
(fitting.report.holdout.evaluate's) and read no texel the fitted views leave unseen (the
map has no value there; how many are left out is printed), beside what 8-bit rounding
allows on those pixels; times (Mitsuba's photos; the `diffshade fit` command,
start to files written). Without Mitsuba one line says so and the script exits 0.
"""

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import peers  # noqa: E402
from capture import (  # noqa: E402
    DIST,
    HEIGHT,
    VARIANT,
    WIDTH,
    K,
    add_photo_options,
    mitsuba_pinhole,
    not_run,
    opencv_pose,
)
from common import finish_record, run_record  # noqa: E402
from lens import lens_photo, pinhole_frame  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
SUBDIVISIONS, DISTANCE = 4, 3.6
#: (azimuth about +y from +z, elevation) of each camera, degrees
VIEWS = [(0, 35), (51, -30), (103, 35), (154, -30), (206, 35), (257, -30), (309, 35),
         (25, 0)]
HOLDOUT, EDGE_MARGIN = 7, 2
#: (position, radiant intensity W/sr per channel): light from every side
EMITTERS = [((2.5, 3.0, 3.5), (50.0, 50.0, 50.0)), ((-3.5, 1.0, 2.5), (30.0, 34.0, 40.0)),
            ((-2.5, 2.5, -3.5), (50.0, 48.0, 44.0)), ((3.5, -1.5, -2.5), (34.0, 34.0, 34.0)),
            ((0.5, -4.0, 1.0), (30.0, 30.0, 30.0))]
#: data_synth's pattern, cos(2 pi 2 v) in v, is symmetric about the equator and varies
#: with u at the poles; shifted by a quarter of its period it is neither: a flipped v shows
#: in the forward check, and the poles (where a texel is narrower than a pixel) are uniform
V_SHIFT = 0.125
MATERIAL = (0.0, 0.5, 0.0, 10.0)  # --init ka, kd, ks, shininess: kd is the map's


def eyes():
    """Each camera's position: DISTANCE from the sphere's centre at VIEWS' angles."""
    out = []
    for azimuth, elevation in VIEWS:
        a, e = math.radians(azimuth), math.radians(elevation)
        out.append((DISTANCE * math.cos(e) * math.sin(a), DISTANCE * math.sin(e),
                    DISTANCE * math.cos(e) * math.cos(a)))
    return out


def truth(res):
    """The true kd map [res, res, 3] (linear, row 0 = v = 1): data_synth's procedural kd
    at the texel centres, shifted by V_SHIFT in v."""
    from data_synth.materials import procedural_kd_at

    centres = (np.arange(res) + 0.5) / res
    return procedural_kd_at(centres[None, :], 1.0 - centres[:, None] + V_SHIFT).astype(
        np.float32)


def scene_file():
    """The capture's scene file (cameras in OpenCV form, lights in physical units)."""
    cameras = []
    for eye in eyes():
        R, t = opencv_pose(eye)
        cameras.append({"K": K, "R": R.tolist(), "t": t.tolist(), "width": WIDTH,
                        "height": HEIGHT, "dist": DIST})
    lights = [{"type": "point", "position": list(position),
               "color": [i / math.pi for i in intensity], "attenuation": [0, 0, 1]}
              for position, intensity in EMITTERS]
    ka, kd, ks, shininess = MATERIAL
    return {"mesh": {"builtin": {"icosphere": {"subdivisions": SUBDIVISIONS, "uv": True}}},
            "cameras": cameras, "lights": lights, "global_ambient": 0.0,
            "material": {"ka": ka, "kd": kd, "ks": ks, "shininess": shininess},
            "settings": {"shading": "phong"}}


def write_dataset(folder, shots, views):
    """A dataset folder of the views numbered `views`: scene.json (every camera), their
    8-bit sRGB photos and eroded masks, dataset.json."""
    from diffshade.io import write_json, write_png
    from fitting.model.cache import erode

    os.makedirs(folder, exist_ok=True)
    write_json(os.path.join(folder, "scene.json"), scene_file())
    entries = []
    for i in views:
        photo, coverage = shots[i]
        mask = erode(coverage > 0.5, EDGE_MARGIN)
        write_png(os.path.join(folder, f"photo_{i}.png"), photo, color_space="srgb")
        write_png(os.path.join(folder, f"mask_{i}.png"),
                  np.repeat(mask[..., None], 3, -1).astype(np.float32), color_space="linear")
        entries.append({"scene": "scene.json", "camera": i, "image": f"photo_{i}.png",
                        "mask": f"mask_{i}.png"})
    write_json(os.path.join(folder, "dataset.json"),
               {"format": "diffshade-dataset", "version": 1, "views": entries,
                "info": {"made_by": "benchmarks/texture_capture.py (Mitsuba 3)"}})


def photograph(args):
    """(photos [H, W, 3] linear, coverage [H, W]) per camera and the seconds Mitsuba took;
    or the reason Mitsuba cannot run (a string)."""
    try:
        import mitsuba as mi
        mi.set_variant(VARIANT)
    except (ImportError, AttributeError) as err:
        return f"{type(err).__name__}: {err}".splitlines()[0]
    import diffshade as ds

    sphere = ds.icosphere(SUBDIVISIONS, uv=True)
    mesh = {name: np.asarray(getattr(sphere, name), np.float32)
            for name in ("vertices", "normals", "uv")}
    mesh["faces"] = np.asarray(sphere.faces, np.uint32)
    texels = truth(args.res)
    frame = pinhole_frame(K, DIST, WIDTH, HEIGHT, args.lens_samples, args.oversample)
    start, shots = time.perf_counter(), []
    for eye in eyes():
        image = mitsuba_pinhole(mi, lambda: peers.mitsuba_mesh(mi, mesh, texels),
                                *opencv_pose(eye), frame, args.spp, EMITTERS)
        photo = lens_photo(image, frame[0], K, DIST, WIDTH, HEIGHT, args.lens_samples)
        shots.append((photo[..., :3], photo[..., 3]))
    return shots, time.perf_counter() - start


def fit(folder, result_dir, res):
    """`diffshade fit FOLDER --texture kd=RES` in its own process: (result.json, seconds
    from start to files written)."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    cmd = [sys.executable, "-m", "diffshade", "fit", folder, "-o", result_dir, "--texture",
           f"kd={res}", "--fit", "kd", "--init", ",".join(map(str, MATERIAL))]
    start = time.perf_counter()
    done = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        print(done.stdout + done.stderr, end="")
        raise SystemExit(f"diffshade fit exited with status {done.returncode}")
    with open(os.path.join(result_dir, "result.json")) as f:
        return json.load(f), seconds


def textured(texels):
    """The capture's material with kd the map `texels` (NaN, unseen, read as 0)."""
    import diffshade as ds

    ka, _, ks, shininess = MATERIAL
    return ds.material(ka=ka, kd=ds.texture(np.nan_to_num(texels, nan=0.0)), ks=ks,
                       shininess=shininess)


def forward_check(dataset, res, flip=False):
    """Per view of `dataset`, holdout.evaluate's scores of diffshade's render with the true
    map against the photo: the conventions' check (flip: with the map upside down, as a
    renderer that took v = 0 for the top row would read it)."""
    from fitting.report.holdout import evaluate

    texels = truth(res)[::-1] if flip else truth(res)
    return [evaluate(dataset, i, textured(texels), EDGE_MARGIN)[2]
            for i in range(len(dataset.views))]


def reads_unseen(dataset, index, coverage):
    """[H, W] bool: the pixels of view `index` that read a texel no fitted view sees (lit
    where the map is 1 on the unseen texels and 0 elsewhere)."""
    from fitting.report.result import render_rgb

    unseen = np.repeat((coverage == 0)[..., None], 3, -1).astype(np.float32)
    return render_rgb(dataset, index, textured(unseen)).max(-1) > 0


def holdout_scores(dataset, texels, coverage):
    """The held-out view rendered with the recovered map against its photo, over the
    pixels that count (fitting.report.holdout.evaluate's) and read no unseen texel: their
    count, PSNR linear and sRGB, and what 8-bit rounding allows there; and the counted
    pixels left out."""
    from diffshade.io import encode
    from fitting.report.holdout import evaluate, psnr, rounding_limits

    view = dataset.views[HOLDOUT]
    prediction, counted, _ = evaluate(dataset, HOLDOUT, textured(texels), EDGE_MARGIN)
    unseen = counted & reads_unseen(dataset, HOLDOUT, coverage)
    kept = counted & ~unseen
    shown = [np.clip(np.asarray(x, np.float64), 0.0, 1.0) for x in (prediction, view.target)]
    linear_8bit, srgb_8bit = rounding_limits(view.target, kept, view.rounding)
    return {"view": HOLDOUT, "pixels": int(kept.sum()), "unseen_pixels": int(unseen.sum()),
            "psnr_linear": psnr(*shown, kept),
            "psnr_srgb": psnr(*(encode(x, "srgb") for x in shown), kept),
            "psnr_linear_8bit": linear_8bit, "psnr_srgb_8bit": srgb_8bit}


def own_renders_fit(dataset, res):
    """The map that fit_texture recovers from diffshade's own renders of the fitted views
    (with the true map) rounded to 8-bit sRGB, the same masks: what rounding and the
    prior allow."""
    import diffshade as ds
    from diffshade.io import decode, encode
    from fitting.data.views import View
    from fitting.report.holdout import dataset_with
    from fitting.report.result import render_rgb
    from fitting.texture_fit import fit_texture

    material = textured(truth(res))
    views = []
    for i, view in enumerate(dataset.views):
        rgb = np.clip(render_rgb(dataset, i, material), 0.0, 1.0)
        coded = decode(np.round(encode(rgb, "srgb") * 255) / 255, "srgb")
        views.append(View(view.camera, view.lights, coded.astype(np.float32), view.mask))
    ka, kd, ks, shininess = MATERIAL
    others = ds.material(ka=ka, kd=kd, ks=ks, shininess=shininess)
    return np.asarray(fit_texture(dataset_with(dataset, views), res, others).texels)


def wide_texels(res):
    """[res, res] bool: the texels at least two pixels wide at the sphere's nearest point.
    On the longitude / latitude map a texel at latitude phi is 2 pi cos(phi) / res wide, a
    pixel there (DISTANCE - 1 away) (DISTANCE - 1) / fy (the larger of its sides), and two
    pixels the width of one seen 60 degrees off the surface's normal. Nearer the poles a
    texel is narrower, and a photo pixel averages several."""
    latitude = np.pi * (0.5 - (np.arange(res) + 0.5) / res)  # row 0 = v = 1: the north
    pixel = (DISTANCE - 1.0) / min(K[0][0], K[1][1])
    return np.repeat((2 * np.pi * np.cos(latitude) / res >= 2 * pixel)[:, None], res, 1)


def map_psnr(texels, res, chosen):
    """PSNR (linear, peak 1) of a recovered map against the truth over the texels
    `chosen`."""
    error = np.asarray(texels, np.float64)[chosen] - truth(res)[chosen]
    return float(10 * np.log10(1.0 / np.mean(error ** 2)))


def map_scores(texels, coverage, res):
    """{"twice", "twice_wide"}: map_psnr over the texels >= 2 views see, and over those of
    them at least two pixels wide (wide_texels)."""
    twice = coverage >= 2
    return {"twice": map_psnr(texels, res, twice),
            "twice_wide": map_psnr(texels, res, twice & wide_texels(res))}


def measure(folder, res):
    """Every figure of the module docstring but the times, from the written folders."""
    from fitting import load_dataset

    texels = np.load(os.path.join(folder, "result", "kd.npy"))
    coverage = np.load(os.path.join(folder, "result", "kd_coverage.npy"))
    data = load_dataset(os.path.join(folder, "data"))
    train = load_dataset(os.path.join(folder, "train"))
    flipped = [s["psnr_linear"] for s in forward_check(data, res, flip=True)]
    return {"forward_check": forward_check(data, res), "forward_check_v_flipped": flipped,
            "coverage": {"unseen": int(np.sum(coverage == 0)), "once": int(np.sum(coverage == 1)),
                         "twice_or_more": int(np.sum(coverage >= 2)),
                         "twice_wide": int(np.sum((coverage >= 2) & wide_texels(res)))},
            "map_psnr": map_scores(texels, coverage, res),
            "map_psnr_own_8bit": map_scores(own_renders_fit(train, res), coverage, res),
            "holdout": holdout_scores(data, texels, coverage)}


def report(figures, res):
    print("forward check: diffshade's render with the true map against Mitsuba's photo "
          "(PSNR linear / sRGB, and what 8-bit rounding allows)")
    for i, s in enumerate(figures["forward_check"]):
        print(f"  view {i}: {s['psnr_linear']:.2f} / {s['psnr_srgb']:.2f} dB "
              f"(8-bit allows {s['psnr_linear_8bit']:.2f} / {s['psnr_srgb_8bit']:.2f} dB)")
    flipped = figures["forward_check_v_flipped"]
    print(f"  with the map upside down (v = 0 read as the top row): {min(flipped):.2f}–"
          f"{max(flipped):.2f} dB linear")
    c, fit = figures["coverage"], figures["fit"]
    print(f"\nkd map {res}x{res} from the {len(VIEWS) - 1} fitted views: {c['twice_or_more']} "
          f"texels seen by >= 2 views, {c['once']} by 1, {c['unseen']} unseen; "
          f"{fit.get('stencil_iterations', 0)} CG iterations on the stencil, "
          f"{fit['iterations']} on the renders")
    ours, own = figures["map_psnr"], figures["map_psnr_own_8bit"]
    print(f"  PSNR (linear) over the texels seen by >= 2 views: {ours['twice']:.2f} dB; over "
          f"the {c['twice_wide']} of them at least two pixels wide: {ours['twice_wide']:.2f} dB")
    print(f"  the same fit on diffshade's own renders of the views, 8-bit: {own['twice']:.2f} "
          f"/ {own['twice_wide']:.2f} dB")
    h = figures["holdout"]
    print(f"held-out view {h['view']} ({h['pixels']} pixels; {h['unseen_pixels']} more read "
          f"an unseen texel and are left out): PSNR linear {h['psnr_linear']:.2f} dB (8-bit allows "
          f"{h['psnr_linear_8bit']:.2f} dB), sRGB {h['psnr_srgb']:.2f} dB (8-bit allows "
          f"{h['psnr_srgb_8bit']:.2f} dB)")
    t = figures["times"]
    print(f"times: Mitsuba's {len(VIEWS)} photos {t['photos_s']:.1f} s; diffshade fit "
          f"--texture kd={res} {t['fit_s']:.1f} s (start, load, compile, solve, write)")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--res", type=int, default=64, help="the texture's side (texels)")
    parser.add_argument("--spp", type=int, default=16, help="Mitsuba samples per pixel")
    add_photo_options(parser)
    parser.add_argument("--data", help="write the datasets and the result here (default: a "
                        "temporary folder)")
    parser.add_argument("--out", default=str(ROOT / "benchmarks/results/texture_capture.json"))
    args = parser.parse_args(argv)
    record = run_record()
    shots = photograph(args)
    if not_run(shots):
        return
    shots, photos_s = shots
    fitted = [i for i in range(len(VIEWS)) if i != HOLDOUT]
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.data or tmp
        write_dataset(os.path.join(folder, "data"), shots, range(len(VIEWS)))
        write_dataset(os.path.join(folder, "train"), shots, fitted)
        result, fit_s = fit(os.path.join(folder, "train"), os.path.join(folder, "result"),
                            args.res)
        figures = measure(folder, args.res)
    figures |= {"fit": result["textures"]["kd"], "times": {"photos_s": photos_s,
                                                           "fit_s": fit_s}}
    report(figures, args.res)
    from diffshade.io import write_json

    write_json(args.out, {"run": finish_record(record), "res": args.res, "spp": args.spp,
                          "oversample": args.oversample, "lens_samples": args.lens_samples,
                          "size": [WIDTH, HEIGHT], "K": K, "dist": DIST, "views": VIEWS,
                          "holdout": HOLDOUT, "edge_margin": EDGE_MARGIN,
                          "emitters": EMITTERS, **figures})
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

"""8-bit rounding carried through undistortion on load: an undistorted photo is no longer
8-bit codes, so each target pixel's rounding shift bound is the bilinear mix of its four
photo pixels' half code steps (sum w h) and its quantization variance the mix of their
variances with squared weights (sum w^2 h^2 / 3).

The reference is a naive per-pixel loop: OpenCV's distortion written out, the four photo
pixels and weights found by hand, and each half code step through the sRGB formula."""

import json

import numpy as np
import pytest

import diffshade as ds
from diffshade.io import distort_image, undistort_mask
from fitting import FitSpec, fit
from fitting.data.folder import load_dataset
from fitting.data.rounding import resampled_rounding
from fitting.model.cache import view_samples
from fitting.report.holdout import evaluate

W, H = 24, 20
K = np.array([[30.0, 0.0, 12.3], [0.0, 27.0, 8.8], [0.0, 0.0, 1.0]])
DIST = [-0.12, 0.03, 0.002, -0.001]
TRUTH = ds.material(ka=0.1, kd=(0.6, 0.4, 0.3), ks=0.3, shininess=20.0)


def srgb_decode(y):
    return np.where(y <= 0.04045, y / 12.92, ((y + 0.055) / 1.055) ** 2.4)


def naive_rounding(codes):
    """(shift, variance, inside) [H, W, 3] of each pinhole pixel of an 8-bit sRGB photo
    (codes [H, W, 3]) seen through K, DIST: a loop over pixels and corners."""
    shift, variance = np.zeros(codes.shape), np.zeros(codes.shape)
    inside = np.zeros(codes.shape[:2], bool)
    k1, k2, p1, p2 = DIST
    for v in range(H):
        for u in range(W):
            x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2 * r2
            xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            ud, vd = K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]
            if not (0 <= ud <= W - 1 and 0 <= vd <= H - 1):
                continue
            inside[v, u] = True
            u0, v0 = min(int(np.floor(ud)), W - 2), min(int(np.floor(vd)), H - 2)
            fu, fv = ud - u0, vd - v0
            for row, col, w in ((v0, u0, (1 - fu) * (1 - fv)), (v0, u0 + 1, fu * (1 - fv)),
                                (v0 + 1, u0, (1 - fu) * fv), (v0 + 1, u0 + 1, fu * fv)):
                for c in range(3):
                    code = codes[row, col, c]
                    centre = srgb_decode(code / 255)
                    half = max(srgb_decode(min(code + 0.5, 255) / 255) - centre,
                               centre - srgb_decode(max(code - 0.5, 0) / 255))
                    shift[v, u, c] += w * half
                    variance[v, u, c] += w * w * half * half / 3
    return shift, variance, inside


def camera(eye=(0.3, 0.4, 3.0)):
    pose = ds.camera_to_opencv(ds.look_at(eye, (0.0, 0.0, 0.0), width=W, height=H))
    return ds.camera_from_opencv(K, pose["R"], pose["t"], W, H, dist=DIST)


def test_resampled_rounding_is_the_bilinear_mix_of_the_photos_half_steps():
    codes = np.random.default_rng(4).integers(0, 256, size=(H, W, 3))
    got = resampled_rounding(srgb_decode(codes / 255), camera())
    shift, variance, inside = naive_rounding(codes)
    assert inside.mean() > 0.5
    # rtol 1e-6: the camera holds K and dist in float32 (weights off by ~1e-7)
    np.testing.assert_allclose(got.shift[inside], shift[inside], rtol=1e-6)
    np.testing.assert_allclose(got.variance[inside], variance[inside], rtol=1e-6)
    assert not np.any(got.shift[~inside]) and "resampled" in got.source
    assert resampled_rounding(srgb_decode(codes / 255) + 1e-3, camera()) is None


def distorted_capture(folder, eyes):
    """A dataset folder of 8-bit sRGB photos of TRUTH on a sphere, taken through K, DIST
    (the pinhole render distorted), one per eye; returns (the photos' codes, cameras)."""
    folder.mkdir()
    lights = [{"type": "point", "position": [2.0, 2.5, 3.0], "color": 1.0}]
    views, all_codes, cameras = [], [], []
    for i, eye in enumerate(eyes):
        cam = camera(eye)
        pose = ds.camera_to_opencv(cam)
        scene = ds.make_scene(ds.icosphere(2), ds.replace(cam, dist=0 * cam.dist),
                              [ds.point_light((2.0, 2.5, 3.0))], TRUTH)
        photo = distort_image(np.asarray(ds.render(scene))[..., :3], cam)
        codes = np.round(np.clip(ds.linear_to_srgb(photo), 0, 1) * 255)
        ds.write_png(folder / f"p{i}.png", srgb_decode(codes / 255))
        (folder / f"s{i}.json").write_text(json.dumps({
            "version": 1, "mesh": {"builtin": {"icosphere": {"subdivisions": 2}}},
            "camera": {"K": K.tolist(), "R": np.asarray(pose["R"]).tolist(),
                       "t": np.asarray(pose["t"]).tolist(), "width": W, "height": H,
                       "dist": DIST},
            "lights": lights}))
        views.append({"scene": f"s{i}.json", "image": f"p{i}.png"})
        all_codes.append(codes)
        cameras.append(cam)
    (folder / "dataset.json").write_text(json.dumps(
        {"format": "diffshade-dataset", "version": 1, "views": views}))
    return all_codes, cameras


@pytest.mark.cost(10)
def test_a_fit_on_undistorted_photos_reports_the_rounding_figures(tmp_path):
    codes, cameras = distorted_capture(tmp_path / "data", [(0.3, 0.4, 3.0), (1.5, 0.6, 2.5)])
    dataset = load_dataset(tmp_path / "data")
    naive = [naive_rounding(c) for c in codes]
    for view, (shift, variance, _), cam in zip(dataset.views, naive, cameras, strict=True):
        counted = undistort_mask(None, cam)
        np.testing.assert_allclose(view.rounding.shift[counted], shift[counted], rtol=1e-6)
        np.testing.assert_allclose(view.rounding.variance[counted], variance[counted],
                                   rtol=1e-6)
    result = fit(dataset, FitSpec(ka=None, ks=None, shininess=False), TRUTH, method="linear")
    bound = result.uncertainty.rounding_bound
    assert bound is not None and np.all(np.isfinite(bound)) and np.all(bound > 0)
    assert "resampled" in result.uncertainty.notes[0]
    # the misfit floor: the rms of the kept pixels' rounding errors (sum w^2 h^2 / 3)
    kept = [view_samples(dataset, i).pixels for i in range(2)]
    variances = np.concatenate([n[1].reshape(-1, 3)[np.asarray(p)]
                                for n, p in zip(naive, kept, strict=True)])
    assert result.misfit.quantization == pytest.approx(np.sqrt(variances.mean()), rel=1e-6)
    # the held-out 8-bit limit on linear values: 10 log10(1 / mean variance), counted pixels
    _, counted, scores = evaluate(dataset, 0, result.material)
    want = 10 * np.log10(1 / np.mean(naive[0][1][counted]))
    assert scores["psnr_linear_8bit"] == pytest.approx(want, rel=1e-6)
    assert scores["psnr_srgb_8bit"] is not None

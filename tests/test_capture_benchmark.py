"""benchmarks/capture.py and texture_capture.py without Mitsuba: their lens
(benchmarks/lens.py, a pinhole image resampled through OpenCV's model) against the forward
model written out here, and the one line and exit status 0 when Mitsuba cannot run."""

import os
import subprocess
import sys

import numpy as np
import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "benchmarks"))

from lens import lens_photo, pinhole_frame  # noqa: E402
from test_peers_benchmark import broken_mitsuba_env  # noqa: E402

K = [[52.0, 0.0, 20.0], [0.0, 47.0, 13.0], [0.0, 0.0, 1.0]]  # fx != fy, off-centre


def forward(dist, x, y):
    """OpenCV's radial-tangential distortion of normalized (x, y), written out."""
    k1, k2, p1, p2, k3 = dist
    r2 = x**2 + y**2
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    return (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x**2),
            y * radial + p1 * (r2 + 2 * y**2) + 2 * p2 * x * y)


def ramp(frame):
    """The pinhole image whose two channels are the normalized coordinates (x, y) of each
    pixel centre: bilinear interpolation reproduces it exactly anywhere inside."""
    focal, width, height = frame
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    return np.stack([(u - (width / 2 - 0.5)) / focal, (v - (height / 2 - 0.5)) / focal], -1)


def test_each_photo_pixel_sees_the_ray_the_opencv_model_sends_it():
    dist = (-0.09, 0.02, 0.002, -0.001, 0.004)
    width, height = 40, 28
    frame = pinhole_frame(K, dist, width, height, 1, 2)
    photo = lens_photo(ramp(frame), frame[0], K, dist, width, height, 1)
    xd, yd = forward(dist, photo[..., 0], photo[..., 1])
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    np.testing.assert_allclose(xd, (u - K[0][2]) / K[0][0], atol=1e-9)
    np.testing.assert_allclose(yd, (v - K[1][2]) / K[1][1], atol=1e-9)


def test_without_distortion_a_photo_pixel_is_the_mean_over_its_area():
    # the sub-pixel samples are symmetric about the centre: the mean of a ramp is its value
    # at the pixel centre, (u - cx) / fx, (v - cy) / fy
    width, height = 40, 28
    frame = pinhole_frame(K, (0.0,) * 4, width, height, 3, 3)
    photo = lens_photo(ramp(frame), frame[0], K, (0.0,) * 4, width, height, 3)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    np.testing.assert_allclose(photo[..., 0], (u - K[0][2]) / K[0][0], atol=1e-12)
    np.testing.assert_allclose(photo[..., 1], (v - K[1][2]) / K[1][1], atol=1e-12)


@pytest.mark.parametrize("script", ["capture.py", "texture_capture.py"])
def test_without_mitsuba_one_line_and_exit_status_0(tmp_path, script):
    env = broken_mitsuba_env(tmp_path)
    out = tmp_path / "capture.json"
    done = subprocess.run([sys.executable, os.path.join(ROOT, "benchmarks", script),
                           "--out", str(out)], capture_output=True, text=True, env=env,
                          timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.splitlines() == [
        "Mitsuba 3 did not run (ImportError: libLLVM not found (simulated)); "
        "pip install '.[peers]' and see docs/performance.md"]
    assert not out.exists()

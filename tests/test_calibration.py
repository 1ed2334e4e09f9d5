"""Calibrated cameras: OpenCV's K, R, t (+ dist), COLMAP text models and transforms.json
(diffshade.scene.calibration, diffshade.io.colmap, diffshade.io.nerf, diffshade.io.undistort).

References, all independent of the code under test: the pinhole projection written out in
NumPy in each format's own convention (OpenCV: u = fx x / z + cx, top-left pixel centre
(0, 0); COLMAP: the same with (0.5, 0.5); transforms.json: an OpenGL camera-to-world
matrix and a horizontal field of view), a NumPy point-in-triangle test at pixel centres
for what the hard rasterizer covers, the lens model written from COLMAP's formulas, images
linear in the pixel position (which bilinear resampling reproduces exactly) and central
finite differences in float64 for the pose gradients.
"""

import json
import os
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy.spatial.transform import Rotation

import diffshade as ds
from diffshade import cli
from diffshade.io import (
    colmap_text,
    distort_image,
    read_colmap,
    read_transforms,
    transforms_dict,
    undistort_image,
    undistort_mask,
    undistort_points,
)
from diffshade.scene import distort, opencv_pose, with_pose
from fitting.data import import_capture, load_dataset
from fitting.import_cli import register as register_import

pytestmark = pytest.mark.usefixtures("x64")

W, H = 40, 30
K = np.array([[52.0, 0.0, 23.25], [0.0, 47.5, 12.5], [0.0, 0.0, 1.0]])  # fx != fy, off-centre
ROTVEC = np.array([0.25, -0.4, 0.15])
T = np.array([0.2, -0.1, 3.2])


def rotation(rotvec=ROTVEC):
    return Rotation.from_rotvec(rotvec).as_matrix()


def points(count=50, seed=0):
    """World points around the origin, in front of every camera here."""
    return np.random.default_rng(seed).uniform(-0.6, 0.6, size=(count, 3))


def opencv_project(K, R, t, xyz):
    """The reference: OpenCV's pinhole projection, [N, 2] pixels (centre of pixel 0 at 0)."""
    cam = xyz @ R.T + t
    return np.stack([K[0, 0] * cam[:, 0] / cam[:, 2] + K[0, 2],
                     K[1, 1] * cam[:, 1] / cam[:, 2] + K[1, 2]], axis=-1)


def diffshade_pixels(camera, xyz):
    """Where diffshade's projection (clip coordinates, as the rasterizer gets them) puts
    the points, in OpenCV's pixel convention."""
    scene = ds.make_scene(ds.mesh_from_arrays(xyz, [[0, 1, 2]]), camera, [], ds.material())
    clip = np.asarray(ds.project(scene).clip)
    ndc = clip[:, :2] / clip[:, 3:]
    # diffshade: pixel centres at half-integers, NDC y up
    u = (ndc[:, 0] + 1.0) * camera.width / 2.0 - 0.5
    v = (1.0 - ndc[:, 1]) * camera.height / 2.0 - 0.5
    return np.stack([u, v], axis=-1)


# ---- OpenCV form ----


def test_opencv_camera_projects_as_opencv_does_and_converts_back():
    camera = ds.camera_from_opencv(K, rotation(), T, W, H)
    xyz = points()
    np.testing.assert_allclose(diffshade_pixels(camera, xyz),
                               opencv_project(K, rotation(), T, xyz), atol=1e-6, rtol=0)
    back = ds.camera_to_opencv(camera)
    for key, want in (("K", K), ("R", rotation()), ("t", T), ("dist", np.zeros(5))):
        np.testing.assert_allclose(back[key], want, atol=1e-12, err_msg=key)
    assert (back["width"], back["height"]) == (W, H)


def test_float32_cameras_project_to_a_thousandth_of_a_pixel():
    with jax.enable_x64(False):
        camera = ds.camera_from_opencv(K, rotation(), T, W, H)
        assert camera.eye.dtype == camera.shift.dtype == jnp.float32
        np.testing.assert_allclose(diffshade_pixels(camera, points()),
                                   opencv_project(K, rotation(), T, points()), atol=1e-3)


def test_look_at_camera_converts_to_the_opencv_camera_that_projects_alike():
    camera = ds.look_at((0.7, 1.1, 2.6), (0.1, -0.2, 0.0), (0.1, 1.0, 0.0), width=W,
                        height=H, fov_y=38.0)
    cv = ds.camera_to_opencv(camera)
    xyz = points(seed=1)
    # the reference K of a centred camera with vertical field of view 38 degrees
    f = H / 2.0 / np.tan(np.deg2rad(19.0))
    np.testing.assert_allclose(cv["K"], [[f, 0, W / 2 - 0.5], [0, f, H / 2 - 0.5], [0, 0, 1]],
                               atol=1e-10)
    np.testing.assert_allclose(diffshade_pixels(camera, xyz),
                               opencv_project(cv["K"], cv["R"], cv["t"], xyz), atol=1e-6)


def _inside(tri, pix):
    """NumPy point-in-triangle of pix [P, 2] against tri [3, 2] (either winding)."""
    def side(a, b):
        return (b[0] - a[0]) * (pix[:, 1] - a[1]) - (b[1] - a[1]) * (pix[:, 0] - a[0])
    signs = np.stack([side(tri[i], tri[(i + 1) % 3]) for i in range(3)])
    return np.all(signs > 0, axis=0) | np.all(signs < 0, axis=0)


@pytest.mark.parametrize("principal", [(23.25, 12.5), (5.0, 27.0)])
def test_hard_render_covers_the_pixels_whose_centres_opencv_puts_inside(principal):
    """fx != fy and an off-centre principal point render exactly: coverage at each pixel
    centre is the NumPy point-in-triangle test on OpenCV's projection of the vertices."""
    K2 = K.copy()
    K2[:2, 2] = principal
    camera = ds.camera_from_opencv(K2, rotation(), T, W, H)
    tri = np.array([[-0.5, -0.4, 0.1], [0.6, -0.3, -0.2], [0.0, 0.5, 0.3]])
    scene = ds.make_scene(ds.mesh_from_arrays(tri, [[0, 1, 2]]), camera,
                          [ds.ambient_light(1.0)], ds.material(ka=1.0, kd=0.0, ks=0.0),
                          global_ambient=0.0)
    image = np.asarray(ds.render(scene, ds.RenderSettings(raster="hard")))
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    pix = np.stack([u.ravel(), v.ravel()], -1)
    want = _inside(opencv_project(K2, rotation(), T, tri), pix).reshape(H, W)
    assert want.sum() > 20
    np.testing.assert_array_equal(image[..., 0] > 0.5, want)


def test_pose_gradients_match_central_differences():
    """Pixel positions as a function of the pose (a rotation vector and t) through
    with_pose: jax's gradient against central differences in float64."""
    base = ds.camera_from_opencv(K, np.eye(3), np.zeros(3), W, H)
    xyz = points(4, seed=2)

    def pixels(rotvec, t):
        angle = jnp.sqrt(jnp.sum(rotvec**2))
        axis = rotvec / angle
        cross = jnp.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]],
                           [-axis[1], axis[0], 0]])
        R = jnp.eye(3) + jnp.sin(angle) * cross + (1 - jnp.cos(angle)) * cross @ cross
        camera = with_pose(base, R, t)
        scene = ds.make_scene(ds.mesh_from_arrays(xyz, [[0, 1, 2]]), base, [], ds.material())
        clip = ds.project(ds.replace(scene, camera=camera)).clip
        return clip[:, :2] / clip[:, 3:]

    check_grads(pixels, (jnp.asarray(ROTVEC), jnp.asarray(T)), order=1,
                              modes=["rev"], eps=1e-6, atol=1e-6, rtol=1e-6)
    R, t = opencv_pose(with_pose(base, rotation(), T))
    np.testing.assert_allclose(R, rotation(), atol=1e-12)
    np.testing.assert_allclose(t, T, atol=1e-12)


# ---- bad input ----


def rotated_by(degrees):
    return Rotation.from_euler("z", degrees, degrees=True).as_matrix()


BAD = {  # case: (arguments changed, the argument named, part of the message)
    "skew": (dict(K=[[52, 1, 20], [0, 47, 12], [0, 0, 1]]), "K", "(no skew)"),
    "lower": (dict(K=[[52, 0, 20], [3, 47, 12], [0, 0, 1]]), "K", "[3.0, 47.0, 12.0]"),
    "negative focal": (dict(K=[[-52, 0, 20], [0, 47, 12], [0, 0, 1]]), "K", "fx > 0"),
    "last row": (dict(K=[[52, 0, 20], [0, 47, 12], [0, 0, 2]]), "K", "[0, 0, 1]]"),
    "scaled R": (dict(R=1.001 * np.eye(3)), "R", "R^T R differs from I by 0.002"),
    "reflection": (dict(R=np.diag([1.0, 1.0, -1.0])), "R", "det R = -1"),
    "t nan": (dict(t=[0.0, float("nan"), 3.0]), "t", "3 finite numbers"),
    "dist length": (dict(dist=[0.1, 0.0, 0.0]), "dist", "[k1, k2, p1, p2]"),
    # r (1 + k1 r^2) stops increasing at r = 1 / sqrt(-3 k1) = 0.8165 < the corner's 0.98
    "folding": (dict(K=[[25, 0, 19.5], [0, 25, 14.5], [0, 0, 1]], dist=[-0.5, 0, 0, 0]),
                "dist", "stops increasing at r = 0.8165"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_calibrations_are_refused_naming_the_argument(case):
    change, name, message = BAD[case]
    args = dict(K=K, R=np.eye(3), t=T, width=W, height=H, dist=None) | change
    with pytest.raises(ValueError) as err:
        ds.camera_from_opencv(**args)
    text = str(err.value)
    assert text.startswith(f"{name}: got ") and message in text and "expected" in text, text


def test_a_nearly_orthonormal_rotation_passes_and_the_fold_check_is_at_the_corner():
    ds.camera_from_opencv(K, np.round(rotation(), 7), T, W, H)  # as calibrations print R
    # barrel distortion that is monotone over this image (slope at the corner > 0)
    corner = np.hypot(23.75 / 52.0, 17.0 / 47.5)  # the farthest corner, at pixel edges
    k1 = -0.99 / (3 * corner**2)
    ds.camera_from_opencv(K, np.eye(3), T, W, H, dist=[k1, 0, 0, 0])
    with pytest.raises(ValueError, match="dist: got"):
        ds.camera_from_opencv(K, np.eye(3), T, W, H, dist=[-1.01 / (3 * corner**2), 0, 0, 0])


def opencv_scene(camera):
    return {"version": 1, "mesh": {"builtin": {"icosphere": {"subdivisions": 1}}},
            "camera": camera, "lights": [{"type": "directional", "direction": [0, 0, -1]}]}


CAMERA = {"K": K.tolist(), "R": np.eye(3).tolist(), "t": [0, 0, 3], "width": 16,
          "height": 12}
BAD_FILES = {
    "mixed keys": ({**CAMERA, "eye": [0, 0, 3]}, "camera.eye: unknown key"),
    "missing K": ({k: v for k, v in CAMERA.items() if k != "K"}, "camera.K: missing"),
    "K shape": ({**CAMERA, "K": [[1, 0], [0, 1]]}, "camera.K: got [[1, 0], [0, 1]]; expected a"),
    "skew": ({**CAMERA, "K": [[52, 2, 20], [0, 47, 12], [0, 0, 1]]}, "camera.K: got"),
    "rotation": ({**CAMERA, "R": [[1, 0, 0], [0, 1, 0], [0, 0.1, 1]]}, "camera.R: got"),
    "dist": ({**CAMERA, "dist": [0.1]}, "camera.dist: got [0.1]; expected [k1, k2, p1, p2]"),
    "fold": ({**CAMERA, "dist": [-3.0, 0, 0, 0]}, "camera.dist: got [-3.0"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_scene_file_cameras_exit_2_with_one_line_and_write_nothing(case, tmp_path,
                                                                        capsys):
    camera, message = BAD_FILES[case]
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(opencv_scene(camera)))
    out = tmp_path / "out.png"
    assert cli.main(["render", str(path), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err, err
    assert not out.exists()


def test_scene_files_round_trip_an_opencv_camera():
    camera = {**CAMERA, "dist": [-0.05, 0.01, 0.001, -0.002, 0.0], "near": 0.5, "far": 20.0}
    scene, settings = ds.scene_from_dict(opencv_scene(camera))
    written = ds.io.scene_to_dict(scene, settings)["camera"]
    assert sorted(written) == sorted(camera)
    for key in ("K", "R", "t", "dist"):
        np.testing.assert_allclose(written[key], camera[key], atol=1e-12, err_msg=key)
    # a plain look-at camera is still written in its own form
    look = ds.scene_from_dict({**opencv_scene(None), "camera": {
        "eye": [0, 0, 3], "target": [0, 0, 0], "width": 8, "height": 8}})[0].camera
    assert "eye" in ds.io.camera_to_dict(look)


# ---- COLMAP ----

#: model -> (parameters in COLMAP's convention, fx, fy, cx, cy, k1, k2, p1, p2)
MODELS = {
    "SIMPLE_PINHOLE": ([50.0, 20.5, 15.25], (50.0, 50.0, 20.5, 15.25, 0, 0, 0, 0)),
    "PINHOLE": ([50.0, 44.0, 21.0, 14.0], (50.0, 44.0, 21.0, 14.0, 0, 0, 0, 0)),
    "SIMPLE_RADIAL": ([50.0, 19.0, 16.0, -0.04], (50.0, 50.0, 19.0, 16.0, -0.04, 0, 0, 0)),
    "RADIAL": ([50.0, 20.0, 15.0, -0.04, 0.01], (50.0, 50.0, 20.0, 15.0, -0.04, 0.01, 0, 0)),
    "OPENCV": ([50.0, 46.0, 20.0, 15.0, -0.03, 0.01, 0.002, -0.001],
               (50.0, 46.0, 20.0, 15.0, -0.03, 0.01, 0.002, -0.001)),
}


def colmap_model(folder, rotvec=ROTVEC, t=T):
    """cameras.txt (one camera per model) and images.txt (one image per camera), written
    by hand; returns the quaternions' rotation."""
    R = rotation(rotvec)
    x, y, z, w = Rotation.from_matrix(R).as_quat().tolist()
    t = [float(v) for v in t]
    lines = ["# Camera list", *(f"{i} {m} {W} {H} {' '.join(map(repr, p))}"
                                for i, (m, (p, _)) in enumerate(MODELS.items(), 1))]
    (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
    images = ["# Image list with two lines of data per image:"]
    for i in range(1, len(MODELS) + 1):
        images += [f"{i} {w!r} {x!r} {y!r} {z!r} {t[0]!r} {t[1]!r} {t[2]!r} {i} im {i}.png",
                   "1.0 2.0 -1" if i % 2 else ""]
    (folder / "images.txt").write_text("\n".join(images) + "\n")
    return R


def test_colmap_models_project_as_colmap_does(tmp_path):
    R = colmap_model(tmp_path)
    named = read_colmap(tmp_path)
    assert [name for name, _ in named] == [f"im {i}.png" for i in range(1, 6)]
    xyz = points(seed=3)
    cam = xyz @ R.T + T
    x, y = cam[:, 0] / cam[:, 2], cam[:, 1] / cam[:, 2]
    for (model, (_, want)), (_, camera) in zip(MODELS.items(), named, strict=True):
        fx, fy, cx, cy, k1, k2, p1, p2 = want
        # COLMAP's pixel coordinates minus half a pixel are OpenCV's
        reference = np.stack([fx * x + cx - 0.5, fy * y + cy - 0.5], -1)
        np.testing.assert_allclose(diffshade_pixels(camera, xyz), reference, atol=1e-6,
                                   err_msg=model)
        # the lens: COLMAP's formula (OpenCVCameraModel::Distortion), written out here
        r2 = x * x + y * y
        radial = k1 * r2 + k2 * r2 * r2
        du = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dv = y * radial + 2 * p2 * x * y + p1 * (r2 + 2 * y * y)
        np.testing.assert_allclose(distort(camera.dist, np.stack([x, y], -1)),
                                   np.stack([x + du, y + dv], -1), atol=1e-12, err_msg=model)


def test_colmap_text_round_trips_cameras(tmp_path):
    cameras = [("a.png", ds.camera_from_opencv(K, rotation(), T, W, H)),
               ("b c.png", ds.camera_from_opencv(K, rotation(-3 * ROTVEC), -T, W, H,
                                                 dist=[-0.05, 0.01, 0.001, 0.002]))]
    cameras_txt, images_txt = colmap_text(cameras)
    (tmp_path / "cameras.txt").write_text(cameras_txt)
    (tmp_path / "images.txt").write_text(images_txt)
    for (name, camera), (name2, camera2) in zip(cameras, read_colmap(tmp_path), strict=True):
        assert name == name2
        a, b = ds.camera_to_opencv(camera), ds.camera_to_opencv(camera2)
        for key in ("K", "R", "t", "dist"):
            np.testing.assert_allclose(b[key], a[key], atol=1e-12, err_msg=key)


@pytest.mark.parametrize("edit, message", [
    (lambda c, i: (c.replace("PINHOLE 40", "FISHEYE 40", 1), i), "expected CAMERA_ID MODEL"),
    (lambda c, i: (c, i.replace(" 3 im 3", " 9 im 3")), "CAMERA_ID 9 is not in"),
    (lambda c, i: (c.replace("50.0 44.0", "-50.0 44.0"), i), "(camera 2): K: got"),
    (lambda c, i: (c, i.replace("\n1 ", "\n1 2.0 ", 1)), "has norm"),
])
def test_bad_colmap_models_name_file_and_line(tmp_path, edit, message):
    colmap_model(tmp_path)
    c, i = ((tmp_path / n).read_text() for n in ("cameras.txt", "images.txt"))
    c, i = edit(c, i)
    (tmp_path / "cameras.txt").write_text(c)
    (tmp_path / "images.txt").write_text(i)
    with pytest.raises(ValueError, match=r"\.txt, line \d+") as err:
        read_colmap(tmp_path)
    assert message in str(err.value)


# ---- transforms.json ----


def test_transforms_json_projects_as_nerf_does_and_round_trips(tmp_path):
    angle_x = 0.9
    c2w = np.eye(4)
    c2w[:3, :3] = Rotation.from_rotvec([0.2, 0.5, -0.1]).as_matrix()
    c2w[:3, 3] = [1.0, 0.4, 3.0]
    frames = [{"file_path": "./r_0", "transform_matrix": c2w.tolist(), "rotation": 0.1}]
    (tmp_path / "transforms.json").write_text(json.dumps(
        {"camera_angle_x": angle_x, "frames": frames}))
    ds.write_png(tmp_path / "r_0.png", np.zeros((H, W, 3)))
    ((name, camera),) = read_transforms(tmp_path / "transforms.json")
    assert name == "r_0.png"
    # NeRF: OpenGL camera axes, focal from the horizontal angle, the centre at (W/2, H/2)
    xyz = points(seed=4) * 0.5
    local = (np.c_[xyz, np.ones(len(xyz))] @ np.linalg.inv(c2w).T)[:, :3]
    focal = 0.5 * W / np.tan(0.5 * angle_x)
    u = W / 2 + focal * local[:, 0] / -local[:, 2]
    v = H / 2 - focal * local[:, 1] / -local[:, 2]
    np.testing.assert_allclose(diffshade_pixels(camera, xyz), np.stack([u, v], -1) - 0.5,
                               atol=1e-6)
    data = transforms_dict([("r_0.png", camera)])
    np.testing.assert_allclose(data["frames"][0]["transform_matrix"], c2w, atol=1e-12)
    assert data["camera_angle_x"] == pytest.approx(angle_x, abs=1e-12)
    (tmp_path / "again.json").write_text(json.dumps(data))
    ((_, again),) = read_transforms(tmp_path / "again.json")
    for key in ("K", "R", "t"):
        np.testing.assert_allclose(ds.camera_to_opencv(again)[key],
                                   ds.camera_to_opencv(camera)[key], atol=1e-12)


def test_transforms_json_problems_name_the_key(tmp_path):
    path = tmp_path / "transforms.json"
    ds.write_png(tmp_path / "a.png", np.zeros((H, W, 3)))
    frame = {"file_path": "a.png", "transform_matrix": np.eye(4).tolist()}
    for data, message in (({"frames": [frame]}, "camera_angle_x: missing"),
                          ({"camera_angle_x": 4.0, "frames": [frame]}, "camera_angle_x: got"),
                          ({"camera_angle_x": 1.0, "frames": [{**frame, "fl_x": 3}]},
                           "frames[0]: fl_x: per-frame"),
                          ({"camera_angle_x": 1.0, "frames": [
                              {**frame, "transform_matrix": np.diag([1, 1, 2, 1]).tolist()}]},
                           "frames[0]: R: got")):
        path.write_text(json.dumps(data))
        with pytest.raises(ValueError, match=re.escape(message)):
            read_transforms(path)


# ---- distortion: resampling into the pinhole image ----


def test_undistort_image_samples_the_photo_where_the_lens_puts_each_pixel():
    """A photo linear in the pixel position is resampled exactly by bilinear
    interpolation, so the undistorted image must equal the photo's formula evaluated at
    the distorted position (COLMAP's formulas, written out here)."""
    dist = [0.08, 0.02, 0.003, -0.002]  # pincushion: the corners sample outside the photo
    camera = ds.camera_from_opencv(K, np.eye(3), T, W, H, dist=dist)
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    photo = np.stack([0.01 * u + 0.002 * v, 0.5 - 0.01 * v, 0.3 + 0 * u], -1)
    x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    r2 = x * x + y * y
    radial = 1 + dist[0] * r2 + dist[1] * r2 * r2
    xd = x * radial + 2 * dist[2] * x * y + dist[3] * (r2 + 2 * x * x)
    yd = y * radial + 2 * dist[3] * x * y + dist[2] * (r2 + 2 * y * y)
    ud, vd = K[0, 0] * xd + K[0, 2], K[1, 1] * yd + K[1, 2]
    inside = (ud >= 0) & (ud <= W - 1) & (vd >= 0) & (vd <= H - 1)
    want = np.stack([0.01 * ud + 0.002 * vd, 0.5 - 0.01 * vd, 0.3 + 0 * ud], -1)
    got = undistort_image(photo, camera)
    assert 0.5 < inside.mean() < 1.0
    np.testing.assert_allclose(got[inside], want[inside], atol=1e-12)
    assert not np.any(got[~inside])
    np.testing.assert_array_equal(undistort_mask(None, camera), inside)
    # a photo pixel left out removes every pinhole pixel that samples it
    photo_mask = np.ones((H, W), bool)
    photo_mask[10, 20] = False
    near = inside & (np.abs(ud - 20) < 1) & (np.abs(vd - 10) < 1)
    np.testing.assert_array_equal(undistort_mask(photo_mask, camera), inside & ~near)


def test_distort_inverts_undistort():
    dist = np.array([-0.08, 0.02, 0.003, -0.002, 0.001])
    xy = np.random.default_rng(5).uniform(-0.4, 0.4, (100, 2))
    np.testing.assert_allclose(undistort_points(dist, distort(dist, xy)), xy, atol=1e-12)
    camera = ds.camera_from_opencv(K, np.eye(3), T, W, H, dist=dist[:4])
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    image = np.stack([0.01 * u, 0.01 * v, np.full_like(u, 0.2)], -1)
    back = undistort_image(distort_image(image, camera), camera)
    valid = undistort_mask(distort_image(np.ones((H, W, 1)), camera)[..., 0] >= 1 - 1e-12,
                           camera)
    # bilinear twice: exact for linear images up to the lens map's curvature over a pixel
    np.testing.assert_allclose(back[valid], image[valid], atol=2e-5)


# ---- datasets from captures ----


def capture(tmp_path, dist=None):
    """A COLMAP model of one PINHOLE camera (OPENCV with dist) and its photo."""
    sparse, photos = tmp_path / "sparse", tmp_path / "photos"
    sparse.mkdir()
    photos.mkdir()
    camera = ds.camera_from_opencv(K, rotation(), T, W, H, dist=dist)
    cameras_txt, images_txt = colmap_text([("p.png", camera)])
    (sparse / "cameras.txt").write_text(cameras_txt)
    (sparse / "images.txt").write_text(images_txt)
    u, v = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    photo = np.stack([np.full_like(u, 0.25), 0.01 * v, 0.005 * u], -1)
    np.save(photos / "p.npy", photo)
    ds.write_png(photos / "p.png", photo)
    scene = {"version": 1, "mesh": {"builtin": {"icosphere": {"subdivisions": 1}}},
             "lights": [{"type": "point", "position": [0, 2, 3]}]}
    (tmp_path / "base.json").write_text(json.dumps(scene))
    return sparse, photos, camera


def test_import_writes_a_dataset_whose_views_have_the_calibrated_cameras(tmp_path, capsys,
                                                                          monkeypatch):
    sparse, photos, camera = capture(tmp_path)
    monkeypatch.setitem(cli.COMMANDS, "import", register_import)
    out = tmp_path / "deep" / "data"
    argv = ["import", str(sparse), "--images", str(photos), "--scene",
            str(tmp_path / "base.json"), "-o", str(out)]
    assert cli.main(argv) == 0
    assert capsys.readouterr().out.strip() == str(out)
    dataset = load_dataset(out)
    (view,) = dataset.views
    for key in ("K", "R", "t"):
        np.testing.assert_allclose(ds.camera_to_opencv(view.camera)[key],
                                   ds.camera_to_opencv(camera)[key], atol=1e-6)
    np.testing.assert_allclose(view.target, ds.read_image(photos / "p.png"), atol=0)
    # moved together with its photos, the dataset still loads
    (tmp_path / "new").mkdir()
    os.rename(tmp_path / "deep", tmp_path / "new" / "deep")
    os.rename(photos, tmp_path / "new" / "photos")
    assert len(load_dataset(tmp_path / "new" / "deep" / "data").views) == 1


def test_a_distorted_capture_loads_as_its_pinhole_image(tmp_path):
    dist = [0.06, 0.01, 0.0, 0.0]
    sparse, photos, camera = capture(tmp_path, dist=dist)
    import_capture(sparse, tmp_path / "base.json", tmp_path / "data", photos)
    (view,) = load_dataset(tmp_path / "data").views
    assert not np.any(np.asarray(view.camera.dist))
    photo = ds.read_image(photos / "p.png")
    mask = undistort_mask(None, camera)
    np.testing.assert_allclose(view.target, undistort_image(photo, camera), atol=1e-6)
    np.testing.assert_array_equal(view.mask, mask)
    assert 0.5 < mask.mean() < 1.0


def test_import_checks_everything_before_writing(tmp_path, capsys, monkeypatch):
    sparse, photos, _ = capture(tmp_path)
    monkeypatch.setitem(cli.COMMANDS, "import", register_import)
    out = tmp_path / "data"
    base = ["import", str(sparse), "--scene", str(tmp_path / "base.json"), "-o", str(out)]
    ds.write_png(photos / "p.png", np.zeros((H + 1, W, 3)))
    for argv, message in ((base, "images: got none"),
                          (base + ["--images", str(photos)], f"expected {W}x{H}")):
        assert cli.main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and message in err, err
    assert not out.exists()

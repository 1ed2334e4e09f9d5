"""Pose refinement: a small rotation and translation per view, kept near its calibration.

`refine_poses(dataset, material)` moves each view's camera by a rigid correction of its
calibrated pose (OpenCV's R0, t0), 6 numbers per view: a rotation vector w that turns the
object about its own centre (the mesh's bounding box's) and a translation u, in camera
axes,

    x_cam = exp([w]x) (R0 x + t0 - c) + c + u,

c in camera coordinates, minimizing, view by view,

    sum over counted pixels |blur(render - target)|^2 / image_noise^2
        + |w|^2 / rotation_prior^2 + |u|^2 / translation_prior^2,

a Gaussian prior around the calibration (the priors: the calibration's expected error).
Turning about the object's centre rather than the camera's keeps the two halves apart:
u moves the object across the image, w turns it in place (about the camera's centre a
small turn and a sideways shift look almost alike).

The render is diffshade's soft rasterizer, so the silhouette moves smoothly with the
pose, set so that its edges sit where a photo's do (SIGMA, GAMMA, the colour composited
by coverage, back faces culled unless the dataset is two-sided); its edges pull only
within a pixel or two, so the images are compared blurred,
coarse to fine (`BLURS`, Gaussian standard deviations in pixels): a wide blur first
spreads each edge's pull over several pixels, then finer ones sharpen the estimate (as
an image pyramid does for Lucas-Kanade alignment). Interior pixels constrain the pose
through the shading too. At each level Levenberg-Marquardt steps solve the normal
equations, the Jacobian by forward-mode differentiation (6 columns), the unknowns scaled
by the prior so that the system is well conditioned. The material and lights are held.
"""

import dataclasses
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

import diffshade as ds
from diffshade.numerics import safe_norm
from diffshade.scene import opencv_pose, with_pose
from fitting.data.views import Dataset, view_scene

#: Gaussian blurs of the comparison, coarse to fine (pixels; 0.5: nearly the image itself)
BLURS = (4.0, 2.0, 1.0, 0.5)
#: the blur kernel reaches this many standard deviations of the widest blur
_REACH = 3.0
#: the soft rasterizer's sigma (pixels^2): edges within about half a pixel, as a photo's
SIGMA = 0.1
#: SoftRas's depth softness: at 1e-4 the nearer of two faces meeting at an edge takes the
#: pixels its footprint reaches, shifting the edge; 1e-3 blends them by coverage while
#: the background's weight stays negligible
GAMMA = 1e-3
_MAX_DAMPING = 1e10


class PoseRefinement(NamedTuple):
    """dataset: the Dataset with refined cameras; corrections: [V, 6] each view's w
    (radians) and u (world units) of the module docstring; rotations_deg: [V] the angle of
    each w; costs: [V, 2] each view's objective before and after."""

    dataset: Dataset
    corrections: np.ndarray
    rotations_deg: np.ndarray
    costs: np.ndarray


def rotation_matrix(rotvec):
    """exp([rotvec]x): [3, 3] (Rodrigues), smooth and exact at rotvec = 0."""
    x, y, z = rotvec
    zero = jnp.zeros_like(x)
    skew = jnp.stack([jnp.stack([zero, -z, y]), jnp.stack([z, zero, -x]),
                      jnp.stack([-y, x, zero])])
    angle = safe_norm(rotvec)
    sin_term = jnp.sinc(angle / jnp.pi)  # sin(angle) / angle
    cos_term = 0.5 * jnp.sinc(angle / (2.0 * jnp.pi)) ** 2  # (1 - cos(angle)) / angle^2
    return jnp.eye(3, dtype=rotvec.dtype) + sin_term * skew + cos_term * skew @ skew


def corrected(pose, centre, correction):
    """(R, t) of the pose (R0 [3, 3], t0 [3]) corrected by correction [6] = (w, u) about
    the world point centre [3] (module docstring)."""
    R0, t0 = pose
    turn = rotation_matrix(correction[:3])
    pivot = R0 @ centre + t0
    return turn @ R0, turn @ (t0 - pivot) + pivot + correction[3:]


def blur_matrix(size, width, reach):
    """[size, size] Gaussian blur along one image axis, standard deviation `width` pixels
    (traced: one compiled program serves every level), cut at `reach` pixels; zero
    outside the image, each row summing to 1 inside."""
    offsets = jnp.arange(size)[:, None] - jnp.arange(size)[None, :]
    taps = jnp.where(jnp.abs(offsets) <= reach, jnp.exp(-0.5 * (offsets / width) ** 2), 0.0)
    full = jnp.exp(-0.5 * (jnp.arange(-reach, reach + 1) / width) ** 2).sum()
    return taps / full


def blur(image, width, reach):
    """image [H, W, C] blurred by a Gaussian of standard deviation `width` pixels."""
    rows = blur_matrix(image.shape[0], width, reach).astype(image.dtype)
    cols = blur_matrix(image.shape[1], width, reach).astype(image.dtype)
    return jnp.einsum("ij,jkc,lk->ilc", rows, image, cols)


def _residuals(z, problem, width, settings, reach):
    """[M] the weighted blurred pixel residuals and the prior's 6, at the scaled
    correction z [6] (correction = z * scales)."""
    scene, pose, centre, target, weight, scales = problem
    camera = with_pose(scene.camera, *corrected(pose, centre, z * scales))
    rgba = ds.render(ds.replace(scene, camera=camera), settings)
    # SoftRas's rgb is the faces' colour wherever any face reaches (its background weight
    # is negligible at small gamma); coverage is in alpha: a photo's pixel over black
    image = rgba[..., :3] * rgba[..., 3:] + (1.0 - rgba[..., 3:]) * scene.background
    pixels = blur((image - target) * weight[..., None], width, reach)
    return jnp.concatenate([pixels.reshape(-1), z])


@partial(jax.jit, static_argnames=("settings", "reach"))
def _normal_system(z, problem, width, settings, reach):
    """(cost, J^T J [6, 6], J^T r [6]) at z."""
    residuals, tangents = jax.linearize(
        lambda x: _residuals(x, problem, width, settings, reach), z)
    jac = jax.vmap(tangents, out_axes=1)(jnp.eye(6, dtype=z.dtype))
    return residuals @ residuals, jac.T @ jac, jac.T @ residuals


@partial(jax.jit, static_argnames=("settings", "reach"))
def _cost(z, problem, width, settings, reach):
    residuals = _residuals(z, problem, width, settings, reach)
    return residuals @ residuals


def _levenberg_marquardt(z, solve_args, steps, tol):
    """z [6] after at most `steps` damped Gauss-Newton steps (the cost never rises)."""
    damping = 1e-3
    for _ in range(steps):
        cost, jtj, jtr = (np.asarray(a, np.float64) for a in _normal_system(z, *solve_args))
        while damping < _MAX_DAMPING:
            system = jtj + damping * np.diag(np.diag(jtj))
            trial = z - jnp.asarray(np.linalg.solve(system, jtr), z.dtype)
            trial_cost = float(_cost(trial, *solve_args))
            if trial_cost < cost:
                z, damping = trial, max(damping / 3.0, 1e-7)
                break
            damping *= 4.0
        if damping >= _MAX_DAMPING or cost - trial_cost <= tol * cost:
            break
    return z


def object_centre(dataset: Dataset):
    """[3] float64 world centre of the mesh's bounding box (the pivot of the turn w)."""
    vertices = np.asarray(dataset.mesh.vertices, np.float64)
    centre = 0.5 * (vertices.min(0) + vertices.max(0))
    return dataset.model[:3, :3] @ centre + dataset.model[:3, 3]


def _check_positive(name, value):
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
            0 < value < np.inf):
        raise ValueError(f"{name}: got {value!r}; expected a positive finite number")


def _view_problem(dataset, index, material, centre, scales, image_noise):
    """The data of one view's refinement: (scene, pose, centre, target, weight, scales)."""
    view = dataset.views[index]
    scene = view_scene(dataset, index, material)
    dtype = scene.camera.eye.dtype
    weight = np.ones(view.target.shape[:2]) if view.mask is None else view.mask
    return (scene, opencv_pose(view.camera), jnp.asarray(centre, dtype),
            jnp.asarray(view.target, dtype), jnp.asarray(weight / image_noise, dtype),
            jnp.asarray(scales, dtype))


def refine_poses(dataset: Dataset, material, *, rotation_prior_deg=1.0,
                 translation_prior=0.05, image_noise=0.05, steps=8, tol=1e-6,
                 blurs=BLURS, sigma=SIGMA, gamma=GAMMA) -> PoseRefinement:
    """Refine every view's pose (module docstring) with `material` and the views' lights
    held. rotation_prior_deg: the prior's standard deviation of the turn w, in degrees;
    translation_prior: that of the translation u, as a fraction of the camera's distance
    to the object's centre; image_noise: the scale of the residual the pose need not
    explain (noise, and the soft edges' and the material's mismatch with the photo: with
    0.01 the data outweigh the prior in the weakly seen turn and the turn drifts);
    steps: Levenberg-Marquardt steps per blur level; blurs: the levels, coarse to fine
    (pixels). Renders with the dataset's settings, soft-rasterized."""
    for name, value in (("rotation_prior_deg", rotation_prior_deg),
                        ("translation_prior", translation_prior), ("image_noise", image_noise)):
        _check_positive(name, value)
    # a closed mesh's back faces share its outline: their coverage would widen it
    settings = dataclasses.replace(dataset.settings, raster="soft", sigma=sigma,
                                   gamma=gamma, cull_backfaces=not dataset.two_sided)
    reach = int(np.ceil(_REACH * max(blurs)))
    centre = object_centre(dataset)
    views, corrections, costs = [], [], []
    for index, view in enumerate(dataset.views):
        distance = float(np.linalg.norm(centre - np.asarray(view.camera.eye, np.float64)))
        scales = [np.deg2rad(rotation_prior_deg)] * 3 + [translation_prior * distance] * 3
        problem = _view_problem(dataset, index, material, centre, scales, image_noise)
        z = jnp.zeros(6, problem[3].dtype)
        before = float(_cost(z, problem, blurs[-1], settings, reach))
        for width in blurs:
            z = _levenberg_marquardt(z, (problem, width, settings, reach), steps, tol)
        costs.append((before, float(_cost(z, problem, blurs[-1], settings, reach))))
        correction = z * problem[5]
        camera = with_pose(view.camera, *corrected(problem[1], problem[2], correction))
        views.append(dataclasses.replace(view, camera=camera))
        corrections.append(np.asarray(correction, np.float64))
    corrections = np.array(corrections)
    return PoseRefinement(dataclasses.replace(dataset, views=tuple(views)), corrections,
                          np.rad2deg(np.linalg.norm(corrections[:, :3], axis=1)),
                          np.array(costs))

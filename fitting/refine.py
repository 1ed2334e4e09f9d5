"""fit_with_poses: the material and every view's pose, alternating.

    result, poses = fit_with_poses(dataset, FitSpec(), rounds=2)
    poses.dataset.views[i].camera, poses.corrections, pose_records(poses.dataset)

A material fit holds the cameras (its pixel cache is rasterized once), and pose
refinement (fitting.solve.pose) holds the material; `fit_with_poses` alternates them:
fit the material with the calibrated cameras, refine the poses with it, fit again on the
refined cameras, `rounds` times. Lights (colours, positions) are fitted with the
material when the FitSpec asks, as in `fit`. `pose_records` gives each view's camera in
OpenCV form for result.json (docs/calibrated-cameras.md, "Pose refinement").
"""

import numpy as np

from diffshade.scene import camera_to_opencv
from fitting.data.views import Dataset
from fitting.driver import FitResult, fit
from fitting.solve.pose import PoseRefinement, refine_poses


def _check_rounds(rounds):
    if isinstance(rounds, bool) or not isinstance(rounds, int) or rounds < 1:
        raise ValueError(f"rounds: got {rounds!r}; expected an integer >= 1")


def refined_poses(dataset: Dataset, spec=None, init=None, *, rounds=2, pose=None,
                  **fit_options) -> PoseRefinement:
    """The poses after `rounds` alternations of a material fit (no uncertainty) and a pose
    refinement with its material. pose: keywords of refine_poses (rotation_prior_deg,
    translation_prior, image_noise, ...); fit_options: fit's keywords (options=...)."""
    _check_rounds(rounds)
    material = fit(dataset, spec, init, with_uncertainty=False, **fit_options).material
    for round_ in range(rounds):
        # each round refines from the calibration: the prior stays centred on it
        refined = refine_poses(dataset, material, **(pose or {}))
        if round_ < rounds - 1:
            material = fit(refined.dataset, spec, init, with_uncertainty=False,
                           **fit_options).material
    return refined


def fit_with_poses(dataset: Dataset, spec=None, init=None, *, rounds=2, pose=None,
                   **fit_options) -> tuple[FitResult, PoseRefinement]:
    """(the FitResult on the refined cameras, with its uncertainty; the PoseRefinement:
    the refined dataset and each view's correction of its calibration). Keywords as
    refined_poses'."""
    refined = refined_poses(dataset, spec, init, rounds=rounds, pose=pose, **fit_options)
    return fit(refined.dataset, spec, init, **fit_options), refined


def pose_records(refined: PoseRefinement) -> list:
    """Per view, JSON-ready: the refined camera in OpenCV form (K, R, t, width, height,
    dist), the turn (degrees) and translation (world units) applied to the calibration."""
    records = []
    for view, correction, angle in zip(refined.dataset.views, refined.corrections,
                                       refined.rotations_deg, strict=True):
        camera = {k: v.tolist() if isinstance(v, np.ndarray) else v
                  for k, v in camera_to_opencv(view.camera).items()}
        records.append({"camera": camera, "rotation_deg": float(angle),
                        "rotation_vector": correction[:3].tolist(),
                        "translation": correction[3:].tolist()})
    return records

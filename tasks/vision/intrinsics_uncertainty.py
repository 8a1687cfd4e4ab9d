"""How uncertain a camera's self-calibrated intrinsics are, and how each measured pose moves with them.

SYNOPSIS
    >>> cov = intrinsics_covariance(views, camera)            # (8, 8) of INTRINSIC_PARAMETERS
    >>> covs = intrinsics_covariances(dots, images, cameras, targets, plates)   # {camera: (8, 8)}
    >>> S = pose_sensitivities(dots, image_ids, T, cameras, plates)   # (N, 6, 8)
    >>> T_shifted = T @ se3.exp(S @ d_theta)                  # the poses under other intrinsics

The pose covariance of :mod:`tasks.vision.poses` is conditional on the intrinsics. Their error is common
to every image of a camera, so it does not average out over a campaign: a focal length 100 ppm
too long puts every plate 30 µm too far away at 300 mm, and a principal point 0.2 px off shifts
every plate sideways by tens of µm. This module gives the two pieces needed to carry that into
the identified parameters (:mod:`tasks.identification.uncertainty`):

* the full covariance of the intrinsics θ = (f, cx, cy, k1, k2, p1, p2, k3) of the joint
  self-calibration (one focal length: the fit holds the aspect ratio). OpenCV reports only their
  standard deviations; the correlations (f with k1, cx with p1, …) matter when the poses
  move with several at once. With S = Σ_views J_θᵀ J_θ − J_θᵀ J_g (J_gᵀ J_g)⁻¹ J_gᵀ J_θ, the Schur
  complement that eliminates each view's pose g: σ² S⁻¹ (σ² the residual variance with 2N − 8 − 6V
  degrees of freedom; its diagonal reproduces OpenCV's ``stdDeviationsIntrinsics``) when every
  dot centre errs independently, and by default the views-as-clusters sandwich, because the
  detector's errors are shared within a view (:func:`intrinsics_covariance`).
* the first-order change of each PnP pose with θ: the pose minimises the reprojection error,
  so dδ = −(J_gᵀ J_g)⁻¹ J_gᵀ J_θ dθ, δ the plate-frame twist of :mod:`tasks.vision.poses`.

Units: f, cx, cy in px; the distortion coefficients dimensionless; δ = (v mm, ω rad).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import cv2
import numpy as np
import pandas as pd

from tasks.machine.camera_model import CameraModel
from tasks.machine.plate import DotPlate
from tasks.vision.camera_calibration import machine_views, trial_views
from tasks.vision.poses import estimate_pose, pose_jacobian

INTRINSIC_PARAMETERS = ("f_px", "cx_px", "cy_px", "k1", "k2", "p1", "p2", "k3")


def intrinsics_vector(camera: CameraModel) -> np.ndarray:
    """(8,) θ of ``camera`` in the order of INTRINSIC_PARAMETERS (f, cx, cy in px)."""
    return np.r_[camera.focal_length_mm / camera.pixel_size_mm, camera.cx_px, camera.cy_px,
                 np.ravel(camera.dist_coeffs)[:5]]


def intrinsics_jacobian(object_points_mm: np.ndarray, T_cam_plate: np.ndarray, camera: CameraModel) -> np.ndarray:
    """∂(u, v)/∂θ (2K, 8), rows interleaving u_k, v_k, of the projections of the plate points
    (K, 3) at pose T_cam_plate; θ in the order of INTRINSIC_PARAMETERS (fx = fy = f)."""
    rvec, _ = cv2.Rodrigues(T_cam_plate[:3, :3])
    _, jac = cv2.projectPoints(np.asarray(object_points_mm, float).reshape(-1, 1, 3), rvec,
                               T_cam_plate[:3, 3].copy(), camera.matrix, camera.dist_coeffs)
    # projectPoints' columns: rvec (3), tvec (3), fx, fy, cx, cy, k1, k2, p1, p2, k3
    return np.column_stack([jac[:, 6] + jac[:, 7], jac[:, 8:15]])


def reduced_view(object_points_mm: np.ndarray, image_points_px: np.ndarray, camera: CameraModel
                 ) -> tuple[np.ndarray, np.ndarray] | None:
    """One view's intrinsics Jacobian with its own pose eliminated, J̃ = J_θ − J_g (J_gᵀ J_g)⁻¹ J_gᵀ J_θ
    (2K, 8; θ in the order of INTRINSIC_PARAMETERS), and its residuals r (2K,) observed − projected
    (px), both at the view's PnP pose with ``camera`` over its K finite dot centres; None when no
    pose is found. A change dθ of the intrinsics, the pose re-fitted, moves the residuals by −J̃ dθ."""
    obj, img = np.asarray(object_points_mm, float), np.asarray(image_points_px, float)
    ok = np.isfinite(img).all(axis=1)
    pose = estimate_pose(obj[ok], img[ok], camera)
    if not pose.ok:
        return None
    J_g = pose_jacobian(obj[ok], pose.T_cam_plate, camera).reshape(-1, 6)
    J_t = intrinsics_jacobian(obj[ok], pose.T_cam_plate, camera)
    reduced = J_t - J_g @ np.linalg.solve(J_g.T @ J_g, J_g.T @ J_t)
    residuals = np.nan_to_num(np.asarray(pose.residuals_px, float).reshape(-1))  # NaN: a point the pose skipped
    return reduced, residuals


def intrinsics_covariance(views: Sequence[tuple[np.ndarray, np.ndarray]], camera: CameraModel,
                          robust: bool = True) -> np.ndarray:
    """(8, 8) covariance of θ (INTRINSIC_PARAMETERS) of a self-calibration from its ``views``.

    views: (object points (K, 3) mm, image points (K, 2) px; NaN rows skipped) of every image the
    calibration used. camera: the calibration's intrinsics. Each view's pose is re-estimated with
    them (the calibration's own extrinsics, to the tolerance of its optimiser).

    robust=False: σ² S⁻¹, which assumes every dot centre errs independently; its diagonal is
    OpenCV's ``stdDeviationsIntrinsics``. The detector's centre errors are not independent within
    a view: blur, the pixel phase of the rims and the lighting bend a whole view's centres
    together. robust=True (the default) therefore takes the views as the independent units: the
    cluster-robust sandwich S⁻¹ (Σ_v g_v g_vᵀ) S⁻¹ · V / (V − 1), g_v = J̃_vᵀ r_v the view's pull
    on θ (J̃_v: its intrinsics Jacobian with its own pose eliminated, r_v its residuals, px). With
    independent centre errors it agrees with σ² S⁻¹ within its sampling error (≈ √(2/V))."""
    normal = np.zeros((8, 8))
    pulls = []
    sum_sq, n_obs = 0.0, 0
    for obj, img in views:
        view = reduced_view(obj, img, camera)
        if view is None:
            continue
        reduced, residuals = view
        normal += reduced.T @ reduced
        pulls.append(reduced.T @ residuals)
        sum_sq += float(residuals @ residuals)
        n_obs += residuals.size
    n_views = len(pulls)
    dof = n_obs - 8 - 6 * n_views
    if n_views < (2 if robust else 1) or dof <= 0:  # the views' scatter needs two of them
        return np.full((8, 8), np.nan)
    inverse = np.linalg.inv(normal)
    if not robust:
        return sum_sq / dof * inverse
    pulls = np.array(pulls)
    pulls -= pulls.mean(axis=0)  # zero at the exact optimum; what the optimiser's tolerance leaves
    return inverse @ (pulls.T @ pulls) @ inverse * n_views / (n_views - 1)


def intrinsics_covariances(dots: pd.DataFrame, images: pd.DataFrame, cameras: Mapping[str, CameraModel],
                           targets: Mapping[str, DotPlate], measured: Mapping[str, DotPlate] | None = None,
                           sweeps: Sequence[str] = ()) -> dict[str, np.ndarray]:
    """{camera: (8, 8) :func:`intrinsics_covariance`} of each camera's joint self-calibration from
    its ``camera_calibration`` images of its target (``targets``) and, with ``measured`` ({camera:
    the plate it measures}), the machine's images of that plate in the sweeps of the axes ``sweeps``
    and the five-axis poses, which refine it (:func:`tasks.vision.camera_calibration.machine_views`;
    the ``dots`` and ``images`` lake tables)."""
    out = {}
    for cam, model in cameras.items():
        views = [(o, m) for objs, imgs, _ in trial_views(dots, images, cam, targets[cam]).values()
                 for o, m in zip(objs, imgs, strict=True)]
        if measured is not None and cam in measured:
            views += machine_views(dots, images, cam, measured[cam], sweeps)
        out[cam] = intrinsics_covariance(views, model)
    return out


def pose_sensitivity(object_points_mm: np.ndarray, T_cam_plate: np.ndarray, camera: CameraModel) -> np.ndarray:
    """(6, 8) ∂δ/∂θ of a PnP pose: how the plate-frame twist (v mm, ω rad) of the pose found from
    these plate points (K, 3) moves per unit of each intrinsic."""
    J_g = pose_jacobian(object_points_mm, T_cam_plate, camera).reshape(-1, 6)
    J_t = intrinsics_jacobian(object_points_mm, T_cam_plate, camera)
    return -np.linalg.solve(J_g.T @ J_g, J_g.T @ J_t)


def pose_sensitivities(dots: pd.DataFrame, image_ids: Sequence[str], T_cam_plate: np.ndarray,
                       cameras: Mapping[str, CameraModel], plates: Mapping[str, DotPlate],
                       camera_of: Sequence[str]) -> np.ndarray:
    """(N, 6, 8) :func:`pose_sensitivity` of N measured poses.

    dots: the ``dots`` lake table (image_id, row, col, u_px, v_px). image_ids, camera_of: (N,) the
    images and their cameras. T_cam_plate: (N, 4, 4) their poses. The dots used are those found
    (finite centres), as in the pose estimate."""
    found = dots[np.isfinite(dots["u_px"]) & np.isfinite(dots["v_px"])]
    by_image = {k: g for k, g in found.groupby("image_id", sort=False)}
    out = np.zeros((len(image_ids), 6, 8))
    for i, (image_id, cam) in enumerate(zip(image_ids, camera_of, strict=True)):
        g = by_image.get(image_id)
        if g is None:
            raise ValueError(f"image {image_id!r} has a pose but no dot centres in the dots table")
        plate = plates[cam]
        obj = plate.dot_centres_mm()[g["row"].to_numpy() * plate.cols + g["col"].to_numpy()]
        out[i] = pose_sensitivity(obj, T_cam_plate[i], cameras[cam])
    return out

"""A camera's self-calibrated intrinsics refined on more views: its calibration views and the
machine's own images of the plate it measures.

The self-calibration views (:mod:`tasks.vision.camera_calibration`) are drawn over the whole field,
but the distortion that matters is where the machine puts the measured plate: the X and Y sweeps
carry plate a to the field's edges, where an error of k1, k2 tilts every pose camera 1 reads by an
amount that grows with the distance from the image centre, and so puts a trend into X's εy and Y's
εx. The sweeps' and five-axis poses' images show the plate there hundreds of times. Adding them to
the fit, each with its own free pose, assumes nothing of the machine's geometry (a view's tilt is
its own parameter), yet a radial distortion error bends a view's dot grid unlike a tilt does (it
stretches the grid along the radius three times as fast as across it), so these views pin the
distortion where they were taken.

Method: Gauss–Newton on the intrinsics θ with every view's pose eliminated (variable projection):
each iteration re-poses every view by PnP with the current θ and solves
(Σ_v J̃_vᵀ J̃_v) Δθ = Σ_v J̃_vᵀ r_v, J̃_v the view's intrinsics Jacobian with its pose projected out
(:func:`tasks.vision.intrinsics_uncertainty.reduced_view`). It minimises the same reprojection
error as OpenCV's ``calibrateCamera`` (one focal length, k3 optionally held), at a cost linear in
the number of views: OpenCV's solver carries every view's pose in one dense normal matrix and takes
minutes for the 650 views of a demo-size campaign's calibration and X/Y sweeps.

Units: f, cx, cy in px; distortion coefficients dimensionless (OpenCV's, normalised coordinates).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from tasks.machine.camera_model import CameraModel
from tasks.vision.camera_calibration import TrialResult
from tasks.vision.intrinsics_uncertainty import intrinsics_vector, reduced_view

MAX_ITERATIONS = 20
STEP_TOLERANCE = 1e-2
"""Converged when no intrinsic moves by more than this many of its standard deviations."""
OVERSHOOT = 1e-6
"""A step overshot when it raises Σ|r|² by more than this fraction (below it: PnP's own tolerance)."""
OUTLIER_FACTOR, OUTLIER_FLOOR_PX = 10.0, 0.5
"""A view whose PnP leaves an RMS above both OUTLIER_FACTOR × the views' median and OUTLIER_FLOOR_PX
(a pose on the wrong branch of a planar target's two-fold ambiguity) is left out of the step."""


def with_intrinsics(camera: CameraModel, theta: np.ndarray) -> CameraModel:
    """``camera`` with θ = (f px, cx px, cy px, k1, k2, p1, p2, k3) (INTRINSIC_PARAMETERS' order)."""
    return replace(camera, focal_length_mm=float(theta[0]) * camera.pixel_size_mm, cx_px=float(theta[1]),
                   cy_px=float(theta[2]), distortion=tuple(float(t) for t in theta[3:8]))


def _linearised(views: Sequence[tuple[np.ndarray, np.ndarray]], camera: CameraModel):
    """(reduced normal matrix (8, 8), pull (8,), Σ|r|², observations, views) over the views that
    PnP poses without an outlying RMS."""
    reduced = [v for v in (reduced_view(o, m, camera) for o, m in views) if v is not None]
    rms = np.array([np.sqrt(np.mean(r**2)) for _, r in reduced])
    keep = rms <= max(OUTLIER_FACTOR * float(np.median(rms)), OUTLIER_FLOOR_PX) if len(rms) else rms > 0
    kept = [v for v, k in zip(reduced, keep, strict=True) if k]
    normal = sum((J.T @ J for J, _ in kept), np.zeros((8, 8)))
    pull = sum((J.T @ r for J, r in kept), np.zeros(8))
    return normal, pull, float(sum(r @ r for _, r in kept)), sum(r.size for _, r in kept), len(kept)


def refine_intrinsics(views: Sequence[tuple[np.ndarray, np.ndarray]], camera: CameraModel, *,
                      fix_k3: bool = False, trial: str = "joint") -> TrialResult:
    """The intrinsics that minimise the reprojection error of all ``views``, started from ``camera``.

    views: [(object points (K, 3) mm, image points (K, 2) px; NaN rows skipped)], each with its own
    free pose. camera: the start (a self-calibration's best estimate; sensor, pitch and name are kept).
    fix_k3: hold k3 at the start's value. A step that raises the reprojection error is halved. Returns
    a :class:`TrialResult` as a joint OpenCV fit gives it (one focal length; per-image extrinsics not
    kept), with status ``failed`` when the views do not determine the intrinsics; std_intrinsics are
    σ̂² × the inverse reduced normal matrix (OpenCV's convention), σ̂² = Σ|r|²/(2N − p), p = free
    intrinsics + 6 per view.
    """
    size = (camera.width_px, camera.height_px)
    free = np.arange(7 if fix_k3 else 8)
    theta = intrinsics_vector(camera).astype(float)
    step, best = np.zeros(len(free)), np.inf
    for _ in range(MAX_ITERATIONS):
        normal, pull, sum_sq, n_obs, n_views = _linearised(views, with_intrinsics(camera, theta))
        N = normal[np.ix_(free, free)]
        if n_views < 2 or not np.all(np.isfinite(N)) or np.linalg.cond(N) > 1e14:
            return TrialResult(camera.name, trial, "failed", f"{n_views} views do not determine the intrinsics", size,
                               n_images=n_views)
        if sum_sq > best * (1 + OVERSHOOT):  # the last step overshot: go back half of it
            step /= 2
            theta[free] -= step
            continue
        best = sum_sq
        step = np.linalg.solve(N, pull[free])
        theta[free] += step
        unit_sd = np.sqrt(np.diag(np.linalg.inv(N)) * sum_sq / max(n_obs - len(free) - 6 * n_views, 1))
        if np.all(np.abs(step) <= STEP_TOLERANCE * unit_sd):
            break
    n_params = len(free) + 6 * n_views
    sigma2 = sum_sq / max(n_obs - n_params, 1)
    sd = np.zeros(8)
    sd[free] = np.sqrt(np.diag(np.linalg.inv(N)) * sigma2)
    model = with_intrinsics(camera, theta)
    return TrialResult(camera.name, trial, "ok", f"{n_views} views, the machine's images included", size,
                       n_images=n_views, n_points=n_obs // 2, rms_px=float(np.sqrt(sum_sq / (n_obs // 2))),
                       sigma_px=float(np.sqrt(sigma2)), camera_matrix=np.asarray(model.matrix, float),
                       dist_coeffs=np.asarray(model.dist_coeffs, float).ravel()[:5],
                       std_intrinsics=np.r_[sd[0], sd[0], sd[1:]], n_params=n_params)

"""The bias the lens leaves in the detector's dot centres, and the dot centres without it.

SYNOPSIS
    >>> b = rim_centre_bias(camera, plate, T_cam_plate)        # (rows*cols, 2) px
    >>> dots = unbiased_dots(dots, plate_of, cameras, plates)   # the dots table, centres corrected

The detector (:mod:`tasks.vision.detection`) fits an ellipse to each dot's rim and subtracts the
perspective bias of its centre computed from plate homographies, one per neighbourhood of dots
when the lens bends the grid (:func:`tasks.vision.detection.perspective.corrected_centres`). The
detector knows no intrinsics, so the lens's share is left: distortion bends each rim's image,
which is then no ellipse, and the local homographies take up the distortion's first-order
(affine) part across a dot, not the change of that part across it. What remains is a shift of
every centre that depends on where the dot lies in the image and how large it is there: on camera
1 at full size 0.0005–0.0009 px RMS (``bench/detection_bias.py``), against 0.004 px of noise per
centre, but the same in every view at the same place, so it does not average out over a campaign:
the self-calibration reads it as distortion and focal length, the poses as tilt.

With the intrinsics and a view's pose, the shift follows from the detector's geometry applied to
the exact rims (:func:`rim_centre_bias`): each dot's circle, sampled at ``points_per_rim`` points,
is projected through the camera with its distortion, an ellipse is fitted to the projected points
(Sampson-weighted least squares, as the detector's rim fits) and corrected as the detector
corrects it; the bias is that centre minus the projection of the dot's centre. It changes with the
intrinsics only at second order, so the self-calibration's first estimate and a view's PnP pose
give it (:func:`unbiased_dots`).

Units: px; plate points mm.
"""

from __future__ import annotations

from collections.abc import Mapping

import cv2
import numpy as np
import pandas as pd

from tasks.machine.camera_model import CameraModel
from tasks.machine.plate import DotPlate
from tasks.vision.detection.conics import ellipse_params, fit_conic_lsq
from tasks.vision.detection.framework import FrameworkParams
from tasks.vision.detection.perspective import corrected_centres
from tasks.vision.poses import estimate_pose

POINTS_PER_RIM = 16
"""Points per rim: a projected rim is smooth, and 16 give the biases of 96 to 1e-9 px."""


def _project(points_mm: np.ndarray, T_cam_plate: np.ndarray, camera: CameraModel) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(np.asarray(T_cam_plate[:3, :3], float))
    uv, _ = cv2.projectPoints(np.asarray(points_mm, float).reshape(-1, 1, 3), rvec,
                              np.asarray(T_cam_plate[:3, 3], float).copy(), camera.matrix, camera.dist_coeffs)
    return uv.reshape(-1, 2)


def rim_centre_bias(camera: CameraModel, plate: DotPlate, T_cam_plate: np.ndarray, found: np.ndarray | None = None,
                    points_per_rim: int = POINTS_PER_RIM) -> np.ndarray:
    """(rows*cols, 2) px: the detector's centre of each dot (ellipse fitted to its projected rim,
    perspective-corrected from the dots ``found`` (rows*cols,) bool, default all, as the detector
    corrects the dots it found) minus the projection of its centre, for ``plate`` at T_cam_plate
    (4×4, plate → camera, mm) seen by ``camera``. NaN for the dots not found."""
    n = plate.rows * plate.cols
    found = np.ones(n, bool) if found is None else np.asarray(found, bool)
    out = np.full((n, 2), np.nan)
    if found.sum() < 4:
        return out
    radius = plate.dot_diameter_mm / 2.0
    centres = plate.dot_centres_mm()[found]
    angle = np.linspace(0.0, 2.0 * np.pi, points_per_rim, endpoint=False)
    circle = radius * np.stack([np.cos(angle), np.sin(angle), np.zeros_like(angle)], axis=1)
    rims = _project((centres[:, None, :] + circle[None]).reshape(-1, 3), T_cam_plate, camera)
    rims = rims.reshape(len(centres), points_per_rim, 2)
    origin = rims.mean(axis=1)
    scale = np.maximum(np.ptp(rims, axis=1).max(axis=1) / 2.0, 1e-6)
    x = (rims[..., 0] - origin[:, :1]) / scale[:, None]
    y = (rims[..., 1] - origin[:, 1:]) / scale[:, None]
    ellipse_centres, _, _ = ellipse_params(fit_conic_lsq(x, y, np.ones_like(x)), origin, scale)
    p = FrameworkParams()
    detected, _ = corrected_centres(ellipse_centres, centres[:, :2], radius, plate.row_col()[found],
                                    p.bias_iterations, p.distorted_misfit_px)
    out[found] = detected - _project(centres, T_cam_plate, camera)
    return out


def unbiased_view(image_points_px: np.ndarray, camera: CameraModel, plate: DotPlate) -> np.ndarray:
    """One view's dot centres (rows*cols, 2) px in plate order (NaN: not found) without
    :func:`rim_centre_bias`, at the view's PnP pose with ``camera``; unchanged when PnP fails."""
    img = np.asarray(image_points_px, float)
    found = np.isfinite(img).all(axis=1)
    pose = estimate_pose(plate.dot_centres_mm()[found], img[found], camera)
    if not pose.ok:
        return img
    return img - np.nan_to_num(rim_centre_bias(camera, plate, pose.T_cam_plate, found))


def unbiased_dots(dots: pd.DataFrame, plate_of: pd.Series, cameras: Mapping[str, CameraModel],
                  plates: Mapping[str, DotPlate]) -> pd.DataFrame:
    """The ``dots`` table (image_id, camera, row, col, u_px, v_px, …) with every image's centres
    made :func:`unbiased_view` by its camera's intrinsics (``cameras``); plate_of: image_id →
    the name of the plate it shows (a key of ``plates``). Images of a camera or plate not given,
    and dots not found (NaN), are left as they are."""
    out = dots.copy()
    uv = out[["u_px", "v_px"]].to_numpy(float, copy=True)
    for (image_id, cam), rows in out.groupby(["image_id", "camera"], sort=False).indices.items():
        plate = plates.get(plate_of.get(image_id))
        if cam not in cameras or plate is None:
            continue
        k = out["row"].to_numpy()[rows] * plate.cols + out["col"].to_numpy()[rows]
        view = np.full((plate.rows * plate.cols, 2), np.nan)
        view[k] = uv[rows]
        uv[rows] = unbiased_view(view, cameras[cam], plate)[k]
    out["u_px"], out["v_px"] = uv[:, 0], uv[:, 1]
    return out

"""Plate pose from one image (Perspective-n-Point) with a calibrated pose covariance.

The measured pose g_a of §4.2 is the plate pose in the camera frame, found by PnP from the
detected dot centres and the camera's self-calibrated intrinsics. This module returns it with
its reprojection RMS and a 6×6 covariance, so that the kinematic identification (eq. 20 and the
LM step of eq. 21) can weight or check each image.

Frames and units
----------------
* Plate frame (mm): :mod:`tasks.machine.plate` (origin at the grid centre, z out of the printed face).
* Camera frame (mm): OpenCV (+z along the optical axis, +x towards increasing u, +y down).
* ``T_cam_plate`` (4×4): plate-frame points to camera-frame points, ``p_cam = T @ [X, 1]``.
* Pixels: (u, v), origin at the centre of the top-left pixel.

Pose uncertainty parameterisation
---------------------------------
A right (body-frame) perturbation on SE(3)::

    T_measured = T_true · exp(δ̂),   δ = (v, ω) ∈ se(3), v in mm, ω in rad,

δ expressed in the **plate frame**, twist order (v, ω) as in :mod:`tasks.core.se3`. This is the
convention of the pose residual of eq. (20), e = log(T_nominal⁻¹ · T_measured)
(:func:`tasks.machine.kinematics.pose_error`): with T_nominal = T_true, e = δ exactly. The covariance
is Σ = σ² (JᵀJ)⁻¹, J = ∂(u, v)/∂δ at δ = 0 (2K×6, px per mm and px per rad) and σ² the
per-coordinate pixel noise variance, estimated from the residuals as Σ r² / (2K − 6) unless
given. For the same uncertainty as a left perturbation in the camera frame,
T_measured = exp(δ̂_c) T_true, use :func:`covariance_in_camera_frame` (δ_c = Ad_T δ).
The covariance is conditional on the intrinsics: errors of the camera calibration, which
are common to all images of a camera, are not in it.

J is analytic: a plate point X moves by ∂(exp(δ̂) X)/∂δ = [I, −[X]×] in the plate frame, i.e.
by R [I, −[X]×] in the camera frame; ∂(u, v)/∂p_cam (pinhole + the 5-parameter distortion)
comes from ``cv2.projectPoints`` evaluated at rvec = tvec = 0 on the camera-frame points
(its translation Jacobian is then exactly ∂(u, v)/∂p_cam), for all points at once.

No Prefect import here: numpy, pandas and OpenCV only.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import cv2
import numpy as np
import pandas as pd

from tasks.core import se3
from tasks.core.units import RAD_TO_ARCSEC
from tasks.machine.camera_model import CameraModel
from tasks.machine.plate import DotPlate

MIN_POINTS = 6
"""Fewest valid (finite) points for a pose: IPPE needs 4, and 2K − 6 > 0 degrees of freedom are
needed to estimate σ from the residuals; 6 leaves 6."""

_REFINE_CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
POSE_COLUMNS = tuple(f"T{i}{j}" for i in range(3) for j in range(4))
STD_COLUMNS = ("std_vx_mm", "std_vy_mm", "std_vz_mm", "std_wx_arcsec", "std_wy_arcsec", "std_wz_arcsec")
COV_COLUMNS = tuple(f"cov{i}{j}" for i in range(6) for j in range(6))
STATUS_CODES = {
    "ok": "pose estimated",
    "too_few_points": f"fewer than the minimum (default {MIN_POINTS}) finite dot centres",
    "pnp_failed": "OpenCV found no pose, or the pose is behind the camera / not finite",
    "bad_input": "point arrays of the wrong shape, or rows/cols outside the plate",
}


@dataclass
class PoseResult:
    """Result of :func:`estimate_pose`. Arrays are NaN when ``status != "ok"``.

    T_cam_plate: (4, 4) plate → camera (mm).
    rms_px: RMS reprojection error over the points, sqrt(Σ|r_k|² / K) (px; OpenCV's convention,
        the norm of the 2-D residual — √2 × the per-coordinate noise for isotropic noise).
    sigma_px: per-coordinate noise estimate sqrt(Σ|r_k|² / (2K − 6)) (px), or the σ given.
    covariance: (6, 6) of the body-frame twist δ = (v [mm], ω [rad]) in the plate frame (see
        the module docstring).
    residuals_px: (K, 2) observed − projected (px), NaN at the points that were skipped.
    n_points: number of finite points used.
    """

    status: str
    message: str
    T_cam_plate: np.ndarray
    rms_px: float
    sigma_px: float
    covariance: np.ndarray
    residuals_px: np.ndarray
    n_points: int

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def std(self) -> np.ndarray:
        """(6,) standard deviations of δ: v in mm, ω in rad (plate frame)."""
        return np.sqrt(np.diag(self.covariance))

    @property
    def std_mm_arcsec(self) -> np.ndarray:
        """(6,) standard deviations: vx, vy, vz in mm, ωx, ωy, ωz in arcsec (plate frame)."""
        s = self.std.copy()
        s[3:] *= RAD_TO_ARCSEC
        return s

    @classmethod
    def failure(cls, status: str, message: str, n_rows: int, n_points: int = 0) -> PoseResult:
        return cls(status, message, np.full((4, 4), np.nan), float("nan"), float("nan"),
                   np.full((6, 6), np.nan), np.full((n_rows, 2), np.nan), n_points)


def pose_jacobian(object_points_mm: np.ndarray, T_cam_plate: np.ndarray, camera: CameraModel) -> np.ndarray:
    """∂(u, v)/∂δ (K, 2, 6) of the projections for the body-frame perturbation T · exp(δ̂).

    object_points_mm: (K, 3) plate frame. δ = (v [mm], ω [rad]) in the plate frame.
    Units: px/mm for the first three columns, px/rad for the last three.
    """
    X = np.asarray(object_points_mm, dtype=float)
    R, t = T_cam_plate[:3, :3], T_cam_plate[:3, 3]
    p_cam = X @ R.T + t
    zero = np.zeros(3)
    _, jac = cv2.projectPoints(p_cam.reshape(-1, 1, 3), zero, zero, camera.matrix, camera.dist_coeffs)
    duv_dp = jac[:, 3:6].reshape(-1, 2, 3)  # rows interleave u_k, v_k; tvec columns = ∂/∂p_cam
    dp_dd = np.empty((X.shape[0], 3, 6))  # R · [I, −[X]×]
    dp_dd[:, :, :3] = R
    dp_dd[:, :, 3:] = -R @ se3.skew(X)
    return duv_dp @ dp_dd


def _project(object_points_mm: np.ndarray, T: np.ndarray, camera: CameraModel) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(T[:3, :3])
    uv, _ = cv2.projectPoints(object_points_mm.reshape(-1, 1, 3), rvec, T[:3, 3].copy(), camera.matrix,
                              camera.dist_coeffs)
    return uv.reshape(-1, 2)


def estimate_pose(object_points_mm: np.ndarray, image_points_px: np.ndarray, camera: CameraModel, *,
                  sigma_px: float | None = None, min_points: int = MIN_POINTS) -> PoseResult:
    """Plate pose in the camera frame from K dot centres.

    object_points_mm: (K, 3) plate frame (z = 0 for a plate). image_points_px: (K, 2) (u, v) px;
    rows with a NaN/inf coordinate are skipped (partial detections). camera: intrinsics used as
    exact (5-parameter OpenCV model).
    sigma_px: a-priori per-coordinate noise (px); None estimates it from the residuals.

    Method: SOLVEPNP_IPPE (planar targets; the better of its two solutions) as the initial
    guess, then ``cv2.solvePnPRefineLM`` (Levenberg–Marquardt on the reprojection error).
    Never raises on data; failures come back with a ``status`` (:data:`STATUS_CODES`).
    """
    obj = np.asarray(object_points_mm, dtype=float)
    img = np.asarray(image_points_px, dtype=float)
    if obj.ndim != 2 or obj.shape[1] != 3 or img.shape != (obj.shape[0], 2):
        return PoseResult.failure("bad_input", f"object points {obj.shape} and image points {img.shape} "
                                  "must be (K, 3) and (K, 2)", img.shape[0] if img.ndim == 2 else 0)
    n_rows = obj.shape[0]
    valid = np.all(np.isfinite(img), axis=1) & np.all(np.isfinite(obj), axis=1)
    k = int(valid.sum())
    if k < max(min_points, 4):
        return PoseResult.failure("too_few_points", f"{k} finite dot centres of {n_rows} (need {min_points})",
                                  n_rows, k)
    o, m = obj[valid], img[valid]
    K, dist = camera.matrix, camera.dist_coeffs
    planar = bool(np.ptp(o[:, 2]) < 1e-9 * max(1.0, float(np.ptp(o[:, :2]))))
    try:
        ok, rvec, tvec = cv2.solvePnP(o, m, K, dist, flags=cv2.SOLVEPNP_IPPE if planar else cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            return PoseResult.failure("pnp_failed", "solvePnP found no solution", n_rows, k)
        rvec, tvec = cv2.solvePnPRefineLM(o, m, K, dist, rvec, tvec, criteria=_REFINE_CRITERIA)
    except cv2.error as exc:
        return PoseResult.failure("pnp_failed", f"OpenCV: {str(exc).strip().splitlines()[-1]}", n_rows, k)
    R, _ = cv2.Rodrigues(rvec)
    T = se3.from_rotation_translation(R, tvec.ravel())
    p_cam_z = o @ R[2] + T[2, 3]
    if not np.all(np.isfinite(T)) or np.any(p_cam_z <= 0):
        return PoseResult.failure("pnp_failed", "pose not finite or points behind the camera", n_rows, k)

    r = m - _project(o, T, camera)
    J = pose_jacobian(o, T, camera).reshape(-1, 6)
    dof = 2 * k - 6
    sum_sq = float(np.sum(r * r))
    if sigma_px is None:
        sigma = np.sqrt(sum_sq / dof) if dof > 0 else float("nan")
    else:
        sigma = float(sigma_px)
    try:
        cov = sigma**2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        cov = np.full((6, 6), np.nan)
    residuals = np.full((n_rows, 2), np.nan)
    residuals[valid] = r
    msg = "" if k == n_rows else f"{n_rows - k} of {n_rows} points skipped (not finite)"
    return PoseResult("ok", msg, T, float(np.sqrt(sum_sq / k)), float(sigma), cov, residuals, k)


def covariance_in_camera_frame(T_cam_plate: np.ndarray, covariance: np.ndarray) -> np.ndarray:
    """The body-frame (plate) twist covariance as a left perturbation in the camera frame:
    T_measured = exp(δ̂_c) T_true with δ_c = Ad_T δ, so Σ_c = Ad_T Σ Ad_Tᵀ. (v mm, ω rad)."""
    A = se3.adjoint(T_cam_plate)
    return A @ covariance @ A.T


def _pose_row(result: PoseResult) -> dict:
    row: dict = {"status": result.status, "message": result.message, "n_points": result.n_points}
    row.update(zip(POSE_COLUMNS, result.T_cam_plate[:3, :].ravel(), strict=True))
    row["rms_px"] = result.rms_px
    row["sigma_px"] = result.sigma_px
    row.update(zip(STD_COLUMNS, result.std_mm_arcsec, strict=True))
    row.update(zip(COV_COLUMNS, result.covariance.ravel(), strict=True))
    return row


def estimate_poses(dots: pd.DataFrame, cameras: Mapping[str, CameraModel] | CameraModel,
                   plates: Mapping[str, DotPlate] | DotPlate, *, sigma_px: float | None = None,
                   min_points: int = MIN_POINTS) -> pd.DataFrame:
    """Poses of many images from a long table of dot centres.

    dots: one row per dot with ``image_id``, ``row``, ``col`` (plate indices), ``u_px``, ``v_px``
        (NaN for a dot not found), and ``camera`` unless ``cameras`` is a single CameraModel.
        The layout of ``truth/dots.parquet`` (docs/campaign-format.md).
    cameras: {camera: intrinsics}, or one CameraModel for every image.
    plates: {camera: the plate that camera views}, or one DotPlate for every image.

    Returns one row per image, in order of first appearance: image_id, camera, status, message,
    n_points, T00…T23 (rows 0–2 of T_cam_plate, mm), rms_px, sigma_px, the six standard
    deviations ``std_v*_mm`` / ``std_w*_arcsec`` (plate frame), and the covariance of
    δ = (v mm, ω rad) flattened row-major as cov00…cov55 (see the module docstring).
    """
    need = {"image_id", "row", "col", "u_px", "v_px"}
    if not isinstance(cameras, CameraModel):
        need.add("camera")
    missing = need - set(dots.columns)
    if missing:
        raise ValueError(f"dots table lacks columns {sorted(missing)}")
    rows = []
    for image_id, g in dots.groupby("image_id", sort=False):
        cam_name = str(g["camera"].iloc[0]) if "camera" in g.columns else ""
        try:
            camera = cameras if isinstance(cameras, CameraModel) else cameras[cam_name]
            plate = plates if isinstance(plates, DotPlate) else plates[cam_name]
        except KeyError:
            res = PoseResult.failure("bad_input", f"no intrinsics or plate for camera {cam_name!r}", len(g))
            rows.append({"image_id": image_id, "camera": cam_name, **_pose_row(res)})
            continue
        r = g["row"].to_numpy()
        c = g["col"].to_numpy()
        if np.any((r < 0) | (r >= plate.rows) | (c < 0) | (c >= plate.cols)):
            res = PoseResult.failure("bad_input", "row/col outside the plate's grid", len(g))
        else:
            obj = plate.dot_centres_mm()[r * plate.cols + c]
            uv = g[["u_px", "v_px"]].to_numpy(dtype=float)
            res = estimate_pose(obj, uv, camera, sigma_px=sigma_px, min_points=min_points)
        rows.append({"image_id": image_id, "camera": cam_name, **_pose_row(res)})
    columns = ["image_id", "camera", "status", "message", "n_points", *POSE_COLUMNS, "rms_px", "sigma_px",
               *STD_COLUMNS, *COV_COLUMNS]
    return pd.DataFrame(rows, columns=columns)


def poses_from_table(table: pd.DataFrame) -> np.ndarray:
    """(N, 4, 4) T_cam_plate from the T00…T23 columns of :func:`estimate_poses` (NaN rows kept)."""
    n = len(table)
    out = np.zeros((n, 4, 4))
    out[:, :3, :] = table[list(POSE_COLUMNS)].to_numpy(dtype=float).reshape(n, 3, 4)
    out[:, 3, 3] = 1.0
    return out


def covariances_from_table(table: pd.DataFrame) -> np.ndarray:
    """(N, 6, 6) covariances of δ = (v mm, ω rad) from the cov00…cov55 columns."""
    return table[list(COV_COLUMNS)].to_numpy(dtype=float).reshape(-1, 6, 6)


def mean_poses(T_cam_plate: np.ndarray, covariances: np.ndarray, group: np.ndarray,
               n_groups: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mean plate pose of each group of repeated images and its covariance.

    T_cam_plate: (N, 4, 4) plate → camera (mm); covariances: (N, 6, 6) of the plate-frame twist
    (v mm, ω rad); group: (N,) group index in [0, n_groups). The mean is the first image's pose
    moved by the mean plate-frame twist log(T_first⁻¹ T_k) of the group: one Gauss–Newton step
    of the Riemannian mean, exact to far below the noise for repeats micrometres and arcseconds
    apart. Its covariance is Σ C_k / n² (independent repeats). Returns (n_groups, 4, 4),
    (n_groups, 6, 6) and the count per group (n_groups,); a group with no image is NaN.
    """
    group = np.asarray(group, dtype=int)
    count = np.bincount(group, minlength=n_groups)
    present, first = np.unique(group, return_index=True)  # the first image of each group
    ref = np.full((n_groups, 4, 4), np.nan)
    ref[present] = T_cam_plate[first]
    twists = se3.log(se3.inverse(ref[group]) @ T_cam_plate)
    mean_twist = np.zeros((n_groups, 6))
    np.add.at(mean_twist, group, twists)
    cov = np.zeros((n_groups, 6, 6))
    np.add.at(cov, group, covariances)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_twist /= count[:, None]
        cov /= (count ** 2)[:, None, None]
    return ref @ se3.exp(mean_twist), cov, count

"""Camera self-calibration from views of a dot plate (§5.2, Table 3 of the calibration paper).

Per camera the paper runs ten independent trials of 15 images each and reports the
reprojection error of every trial and their mean (Table 3), noting that the five distortion
parameters stay below 0.4 in magnitude. This module does the same with OpenCV:

* :func:`calibrate_trial`: one trial, ``cv2.calibrateCameraExtended`` on the 5-parameter
  Brown–Conrady model (k1, k2, p1, p2, k3; OpenCV conventions, see :mod:`tasks.machine.camera_model`),
  started from the nominal intrinsics (``CALIB_USE_INTRINSIC_GUESS``).
* :func:`calibrate_camera`: all trials of a camera → one row per trial, the Table 3 summary,
  and a best estimate (a joint fit on every valid image of the camera; see there why).
* :func:`table3`: the paper's Table 3 layout (trials × cameras, reprojection RMS, mean).
* :func:`compare_to_truth`: errors against the simulator's true intrinsics — for reports only,
  never used by a fit.

Units and frames: pixels (u right, v down, origin at the centre of the top-left pixel), plate
points in mm in the plate frame (:mod:`tasks.machine.plate`), distortion coefficients dimensionless on
normalised coordinates. Reprojection RMS follows OpenCV: sqrt(Σ_k |r_k|² / N) over the N points
(the norm of the 2-D residual), i.e. √2·σ·sqrt((2N − p)/(2N)) for isotropic per-coordinate
noise σ and p fitted parameters. ``sigma_px`` = sqrt(Σ|r|² / (2N − p)) estimates σ itself.

No Prefect import here: numpy, pandas and OpenCV only.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
import pandas as pd

from tasks.core import se3
from tasks.machine.camera_model import CameraModel, distort_normalised
from tasks.machine.description import CALIBRATION_STAGE
from tasks.machine.plate import DotPlate

INTRINSIC_NAMES = ("fx_px", "fy_px", "cx_px", "cy_px", "k1", "k2", "p1", "p2", "k3")
STD_NAMES = tuple(f"std_{n}" for n in INTRINSIC_NAMES)
MIN_POINTS_PER_IMAGE = 8
"""An image enters a calibration with at least this many finite dot centres (partial views allowed)."""
MIN_IMAGES = 4
"""Fewest valid images for a trial; below it the trial gets status ``too_few_images``."""
MACHINE_STAGES = ("pdge", "pige")
"""Stages whose images of a camera's measured plate may also refine its intrinsics (:func:`machine_views`)."""
DISTORTION_LIMIT = 0.4
"""The seed's bound on |k1|…|k3| (§5.2), checked in the summary."""
CRITERIA = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
STATUS_CODES = {
    "ok": "calibrated",
    "too_few_images": f"fewer than {MIN_IMAGES} images with ≥ {MIN_POINTS_PER_IMAGE} finite dot centres",
    "failed": "OpenCV raised or returned a non-finite result",
    "bad_input": "object/image point lists of different lengths or shapes",
}
TRIAL_COLUMNS = ("camera", "trial", "status", "message", "n_images", "n_points", "rms_px", "sigma_px",
                 *INTRINSIC_NAMES, *STD_NAMES)


@dataclass
class TrialResult:
    """One self-calibration (a trial, or the joint fit).

    camera_matrix: (3, 3) K (px). dist_coeffs: (5,) k1, k2, p1, p2, k3.
    std_intrinsics: (9,) standard deviations of fx, fy, cx, cy (px), k1…k3 from OpenCV's
        ``stdDeviationsIntrinsics`` (σ² from the residuals × the inverse normal matrix). With the
        aspect ratio fixed, fx = fy and fx gets fy's standard deviation.
    rms_px: OpenCV's RMS reprojection error sqrt(Σ|r|²/N) (px). sigma_px: sqrt(Σ|r|²/(2N − p)).
    per_image_rms_px: (n_images,) the same RMS per image used.
    image_ids: identifiers of the images used (input order), ``dropped``: those left out and why.
    T_cam_plate: (n_images, 4, 4) extrinsics of the images used (plate → camera, mm).
    n_params: p = free intrinsics + 6 per image.
    """

    camera: str
    trial: str
    status: str
    message: str
    image_size: tuple[int, int]
    n_images: int = 0
    n_points: int = 0
    rms_px: float = float("nan")
    sigma_px: float = float("nan")
    camera_matrix: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    dist_coeffs: np.ndarray = field(default_factory=lambda: np.full(5, np.nan))
    std_intrinsics: np.ndarray = field(default_factory=lambda: np.full(9, np.nan))
    per_image_rms_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    image_ids: list = field(default_factory=list)
    dropped: dict = field(default_factory=dict)
    T_cam_plate: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    n_params: int = 0

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def intrinsics(self) -> np.ndarray:
        """(9,) fx, fy, cx, cy (px), k1, k2, p1, p2, k3."""
        K = self.camera_matrix
        return np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *self.dist_coeffs])

    def to_row(self) -> dict:
        """One row of the trials table (:data:`TRIAL_COLUMNS`)."""
        row = {"camera": self.camera, "trial": self.trial, "status": self.status, "message": self.message,
               "n_images": self.n_images, "n_points": self.n_points, "rms_px": self.rms_px,
               "sigma_px": self.sigma_px}
        row.update(zip(INTRINSIC_NAMES, self.intrinsics, strict=True))
        row.update(zip(STD_NAMES, self.std_intrinsics, strict=True))
        return row

    def camera_model(self, nominal: CameraModel) -> CameraModel:
        """These intrinsics as a :class:`CameraModel` (lens optics, sensor pitch and name from
        ``nominal``). CameraModel has one focal length: fx_px = fy_px = sqrt(fx·fy), in mm
        through the nominal pixel pitch (exact when the fit had a fixed aspect ratio)."""
        K = self.camera_matrix
        f_px = float(np.sqrt(K[0, 0] * K[1, 1]))
        return replace(nominal, width_px=self.image_size[0], height_px=self.image_size[1],
                       focal_length_mm=f_px * nominal.pixel_size_mm, cx_px=float(K[0, 2]), cy_px=float(K[1, 2]),
                       distortion=tuple(float(d) for d in self.dist_coeffs))


def nominal_camera(spec: Mapping, name: str = "camera") -> CameraModel:
    """Nominal intrinsics from a ``campaign.json`` camera entry (width_px, height_px,
    pixel_size_mm, focal_length_mm, focus_distance_mm): principal point at the image centre
    ((W − 1)/2, (H − 1)/2 px), no distortion. The starting point of self-calibration."""
    w, h = int(spec["width_px"]), int(spec["height_px"])
    return CameraModel(w, h, float(spec["pixel_size_mm"]), float(spec["focal_length_mm"]), (w - 1) / 2.0,
                       (h - 1) / 2.0, focus_distance_mm=float(spec.get("focus_distance_mm", 100.0)),
                       f_number=float(spec.get("f_number", 8.0)), name=name)


def _initial_guess(initial: CameraModel | None, image_size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, int]:
    if initial is None:  # OpenCV's own start: principal point at the centre, focal from homographies
        return np.eye(3), np.zeros(5), 0
    return initial.matrix.copy(), initial.dist_coeffs.copy(), cv2.CALIB_USE_INTRINSIC_GUESS


def calibrate_trial(object_points_mm: Sequence[np.ndarray], image_points_px: Sequence[np.ndarray],
                    image_size: tuple[int, int], initial: CameraModel | None = None, *, camera: str = "camera",
                    trial: str = "trial", image_ids: Sequence | None = None, fix_aspect_ratio: bool = False,
                    fix_k3: bool = False, min_points: int = MIN_POINTS_PER_IMAGE,
                    min_images: int = MIN_IMAGES) -> TrialResult:
    """Self-calibrate one camera from the images of one trial.

    object_points_mm: per image (K, 3) plate-frame dot centres (mm), e.g. ``plate.dot_centres_mm()``.
    image_points_px: per image (K, 2) detected centres (u, v px), same order; rows with NaN are
        skipped, and images with fewer than ``min_points`` finite rows are dropped.
    image_size: (width, height) px.
    initial: nominal intrinsics (e.g. :func:`nominal_camera`): fx = fy = focal / pixel pitch, its
        principal point and distortion are the start of the fit (``CALIB_USE_INTRINSIC_GUESS``);
        None lets OpenCV initialise from the plate homographies.
    fix_aspect_ratio: fit one focal length (fx/fy kept at the initial ratio, 1 for square pixels).
    fix_k3: keep k3 at its initial value (4-parameter distortion). Default: the 5-parameter model.

    Never raises on data: a trial that cannot be calibrated comes back with a ``status`` other
    than "ok" (:data:`STATUS_CODES`) and a ``message``.
    """
    size = (int(image_size[0]), int(image_size[1]))
    ids = list(image_ids) if image_ids is not None else list(range(len(image_points_px)))
    if len(object_points_mm) != len(image_points_px) or len(ids) != len(image_points_px):
        return TrialResult(camera, trial, "bad_input", f"{len(object_points_mm)} object point sets, "
                           f"{len(image_points_px)} image point sets, {len(ids)} image ids", size)
    objs, imgs, used, dropped = [], [], [], {}
    for oid, o, m in zip(ids, object_points_mm, image_points_px, strict=True):
        o = np.asarray(o, dtype=float)
        m = np.asarray(m, dtype=float)
        if o.ndim != 2 or o.shape[1] != 3 or m.shape != (o.shape[0], 2):
            dropped[oid] = f"shapes {o.shape} / {m.shape}"
            continue
        valid = np.all(np.isfinite(m), axis=1) & np.all(np.isfinite(o), axis=1)
        if valid.sum() < min_points:
            dropped[oid] = f"{int(valid.sum())} finite centres"
            continue
        objs.append(o[valid].astype(np.float32))
        imgs.append(m[valid].astype(np.float32))
        used.append(oid)
    drop_msg = "; ".join(f"dropped {k}: {v}" for k, v in dropped.items())
    if len(objs) < min_images:
        msg = f"{len(objs)} valid images (need {min_images})" + (f"; {drop_msg}" if drop_msg else "")
        return TrialResult(camera, trial, "too_few_images", msg, size, n_images=len(objs), image_ids=used,
                           dropped=dropped)

    K0, d0, flags = _initial_guess(initial, size)
    if fix_aspect_ratio:
        flags |= cv2.CALIB_FIX_ASPECT_RATIO
    if fix_k3:
        flags |= cv2.CALIB_FIX_K3
    try:
        _, K, dist, rvecs, tvecs, std_i, _, _ = cv2.calibrateCameraExtended(
            objs, imgs, size, K0, d0, flags=flags, criteria=CRITERIA)
    except cv2.error as exc:
        return TrialResult(camera, trial, "failed", f"OpenCV: {str(exc).strip().splitlines()[-1]}", size,
                           n_images=len(objs), image_ids=used, dropped=dropped)
    dist = np.asarray(dist, dtype=float).ravel()[:5]
    std_i = np.asarray(std_i, dtype=float).ravel()[:9]
    if fix_aspect_ratio:
        std_i[0] = std_i[1] * K[0, 0] / K[1, 1]
    # residuals recomputed here (per image and overall, OpenCV's convention)
    sq, per_image, poses = 0.0, [], []
    n_points = 0
    for o, m, rv, tv in zip(objs, imgs, rvecs, tvecs, strict=True):
        uv, _ = cv2.projectPoints(o, rv, tv, K, dist)
        r = m.astype(float) - uv.reshape(-1, 2)
        s = float(np.sum(r * r))
        sq += s
        n_points += len(o)
        per_image.append(np.sqrt(s / len(o)))
        poses.append(se3.from_rotation_translation(cv2.Rodrigues(rv)[0], np.asarray(tv, float).ravel()))
    n_free = 9 - int(fix_aspect_ratio) - int(fix_k3)
    n_params = n_free + 6 * len(objs)
    if not (np.all(np.isfinite(K)) and np.all(np.isfinite(dist)) and np.isfinite(sq)):
        return TrialResult(camera, trial, "failed", "non-finite calibration result", size, n_images=len(objs),
                           image_ids=used, dropped=dropped)
    return TrialResult(camera, trial, "ok", drop_msg, size, n_images=len(objs), n_points=n_points,
                       rms_px=float(np.sqrt(sq / n_points)),
                       sigma_px=float(np.sqrt(sq / max(2 * n_points - n_params, 1))),
                       camera_matrix=np.asarray(K, float), dist_coeffs=dist, std_intrinsics=std_i,
                       per_image_rms_px=np.array(per_image), image_ids=used, dropped=dropped,
                       T_cam_plate=np.array(poses), n_params=n_params)


@dataclass
class CameraCalibration:
    """Result of :func:`calibrate_camera` for one camera.

    trials: one row per trial (:data:`TRIAL_COLUMNS`), with status/message for failed trials.
    summary: Table 3 statistics over the ok trials (:func:`summarise_trials`).
    joint: the joint fit on every valid image of the ok trials (trial = "joint").
    best_estimate: the intrinsics to use downstream (from ``joint``), or None if it failed.
    results: the per-trial :class:`TrialResult` objects, by trial id.
    """

    camera: str
    trials: pd.DataFrame
    summary: pd.DataFrame
    joint: TrialResult
    best_estimate: CameraModel | None
    results: dict[str, TrialResult]


def summarise_trials(trials: pd.DataFrame) -> pd.DataFrame:
    """Mean and spread over the ok trials (the statistics of Table 3).

    Rows: rms_px, sigma_px and every intrinsic; columns: n_trials, mean, std (sample, ddof=1),
    min, max, max_abs. ``max_abs`` of k1…k3 is what the seed bounds by 0.4.
    """
    ok = trials[trials["status"] == "ok"]
    qty = ["rms_px", "sigma_px", *INTRINSIC_NAMES]
    vals = ok[qty].astype(float)
    out = pd.DataFrame({"n_trials": len(ok), "mean": vals.mean(), "std": vals.std(ddof=1), "min": vals.min(),
                        "max": vals.max(), "max_abs": vals.abs().max()})
    out.index.name = "quantity"
    return out


def _split_views(views) -> tuple[list, list, list | None]:
    if len(views) == 3:
        return list(views[0]), list(views[1]), list(views[2])
    return list(views[0]), list(views[1]), None


def calibrate_camera(trials: Mapping[str, tuple], nominal: CameraModel, *, camera: str | None = None,
                     fix_k3: bool = False, joint: bool = True, min_points: int = MIN_POINTS_PER_IMAGE,
                     min_images: int = MIN_IMAGES) -> CameraCalibration:
    """All self-calibration trials of one camera.

    trials: {trial_id: (object_points_mm list, image_points_px list[, image_ids])} as for
        :func:`calibrate_trial`. nominal: the nominal intrinsics (start of every fit, sensor
        size, pixel pitch). camera: name in the tables (default ``nominal.name``).

    Each trial is fitted independently with free fx, fy (the Table 3 repeatability). The best
    estimate is a **joint** fit of all valid images of the ok trials, with one focal length
    (square pixels, as :class:`CameraModel` has one focal length): it is the maximum-likelihood
    estimate when the intrinsics are constant over the campaign — the assumption under which the
    trials are compared at all — it has ~√(number of trials) smaller standard deviations, and it
    fits the distortion field on the union of all views, which covers the image far better than
    any one trial. The mean of the trials' coefficients is not a good substitute: k2 and k3 are
    strongly correlated and individually poorly determined, so averaging them does not average
    the distortion fields. ``joint=False`` skips it (best_estimate None).
    """
    name = camera or nominal.name
    size = (nominal.width_px, nominal.height_px)
    results: dict[str, TrialResult] = {}
    all_obj, all_img, all_ids = [], [], []
    for trial_id, views in trials.items():
        obj, img, ids = _split_views(views)
        res = calibrate_trial(obj, img, size, nominal, camera=name, trial=str(trial_id), image_ids=ids,
                              fix_k3=fix_k3, min_points=min_points, min_images=min_images)
        results[str(trial_id)] = res
        if res.ok:
            ids = ids if ids is not None else [f"{trial_id}/{i}" for i in range(len(img))]
            all_obj += obj
            all_img += img
            all_ids += ids
    table = pd.DataFrame([r.to_row() for r in results.values()], columns=list(TRIAL_COLUMNS))
    if joint and all_obj:
        joint_res = calibrate_trial(all_obj, all_img, size, nominal, camera=name, trial="joint", image_ids=all_ids,
                                    fix_aspect_ratio=True, fix_k3=fix_k3, min_points=min_points,
                                    min_images=min_images)
    else:
        joint_res = TrialResult(name, "joint", "too_few_images", "no ok trial" if joint else "not requested", size)
    best = joint_res.camera_model(replace(nominal, name=name)) if joint_res.ok else None
    return CameraCalibration(name, table, summarise_trials(table), joint_res, best, results)


def table3(calibrations: Sequence[CameraCalibration] | pd.DataFrame) -> pd.DataFrame:
    """The seed's Table 3: reprojection RMS (px) of every trial (rows) per camera (columns), then
    the rows ``mean`` and ``std`` over the ok trials. Failed trials show NaN."""
    df = calibrations if isinstance(calibrations, pd.DataFrame) else pd.concat([c.trials for c in calibrations])
    wide = df.pivot(index="trial", columns="camera", values="rms_px").astype(float)
    ok = df[df["status"] == "ok"].pivot(index="trial", columns="camera", values="rms_px").astype(float)
    wide.loc["mean"] = ok.mean()
    wide.loc["std"] = ok.std(ddof=1)
    wide.columns.name = None
    return wide


def trial_views(dots: pd.DataFrame, manifest: pd.DataFrame, camera: str, plate: DotPlate,
                stage: str = CALIBRATION_STAGE) -> dict[str, tuple]:
    """Calibration inputs of one camera from a long table of dot centres.

    dots: image_id, row, col, u_px, v_px (NaN for missing dots). manifest: image_id, camera,
    stage, group (docs/campaign-format.md). Returns {trial (group): (object points, image
    points, image ids)} for the camera's images of ``stage`` (its ``camera_calibration`` views by
    default), dots in plate order.
    """
    sel = manifest[(manifest["camera"] == camera) & (manifest["stage"] == stage)].reset_index(drop=True)
    centres = plate.dot_centres_mm()
    d = dots[dots["image_id"].isin(sel["image_id"])]
    uv = np.full((len(sel), plate.rows * plate.cols, 2), np.nan)
    uv[pd.Index(sel["image_id"]).get_indexer(d["image_id"]),
       d["row"].to_numpy() * plate.cols + d["col"].to_numpy()] = d[["u_px", "v_px"]].to_numpy(dtype=float)
    ids = sel["image_id"].to_numpy()
    return {str(group): ([centres] * len(rows), list(uv[rows]), ids[rows].tolist())
            for group, rows in sorted(sel.groupby("group").indices.items())}


def machine_views(dots: pd.DataFrame, manifest: pd.DataFrame, camera: str, plate: DotPlate,
                  sweeps: Sequence[str]) -> list[tuple[np.ndarray, np.ndarray]]:
    """[(object points (K, 3) mm, image points (K, 2) px; NaN where a dot was not found)] of the
    camera's images of the plate it measures (``plate``) in the PDGE sweeps of the axes ``sweeps``
    and in the five-axis poses (the validation poses are kept out), from the long dots table."""
    sweep_views = trial_views(dots, manifest, camera, plate, "pdge")
    groups = [sweep_views[a] for a in sweeps if a in sweep_views]
    groups += list(trial_views(dots, manifest, camera, plate, "pige").values())
    return [(o, m) for objs, imgs, _ in groups for o, m in zip(objs, imgs, strict=True)]


# --------------------------------------------------------------------------------------------
# Comparison with the truth (reports only)
# --------------------------------------------------------------------------------------------


def _as_arrays(model) -> tuple[np.ndarray, np.ndarray]:
    """(9,) intrinsics fx, fy, cx, cy, k1..k3 of a CameraModel / TrialResult / CameraCalibration."""
    if isinstance(model, CameraCalibration):
        model = model.best_estimate
    if isinstance(model, TrialResult):
        return model.intrinsics, model.camera_matrix
    if isinstance(model, CameraModel):
        return np.array([model.fx_px, model.fy_px, model.cx_px, model.cy_px, *model.distortion]), model.matrix
    raise TypeError(f"cannot compare a {type(model).__name__}")


def _field_grid(true_camera: CameraModel, step_px: float = 32.0) -> np.ndarray:
    """Rays (normalised, undistorted) of a pixel grid over the whole image (every ``step_px``)."""
    u = np.append(np.arange(0.0, true_camera.width_px - 1, step_px), true_camera.width_px - 1.0)
    v = np.append(np.arange(0.0, true_camera.height_px - 1, step_px), true_camera.height_px - 1.0)
    uu, vv = np.meshgrid(u, v)
    return _rays(np.stack([uu.ravel(), vv.ravel()], -1), true_camera)


def compare_to_truth(result, true_camera: CameraModel, points_px: np.ndarray | None = None) -> dict | pd.DataFrame:
    """Errors of estimated intrinsics against the true ones (simulation reports; never a fit input).

    result: a :class:`TrialResult`, :class:`CameraModel`, :class:`CameraCalibration` (its best
    estimate) or a trials DataFrame (one output row per trial). Returns:

    - fx_error_pct, fy_error_pct, focal_error_pct: (estimate / true − 1)·100; focal uses sqrt(fx·fy);
    - cx_error_px, cy_error_px, pp_error_px: principal-point errors and their norm (px);
    - dk1 … dk3: coefficient differences (estimate − true);
    - distortion_max_px / distortion_rms_px: |f_true · (D_est(x) − D_true(x))| over the whole
      image (rays x of a 32-px pixel grid, D the distortion map of normalised coordinates): the
      distortion-field difference, the meaningful figure when k2 and k3 trade off;
    - projection_max_px / projection_rms_px: the whole model's difference for the same rays
      (focal length, principal point and distortion together; a principal-point shift moves
      every ray alike and is largely absorbed by the plate poses);
    - with ``points_px`` ((M, 2) pixel positions, e.g. every observed dot centre): the same four
      figures evaluated only there, suffixed ``_seen`` (the field inside the calibrated region,
      against the extrapolation to the image corners above).
    """
    seen = None if points_px is None else _rays(np.asarray(points_px, dtype=float).reshape(-1, 2), true_camera)
    if isinstance(result, pd.DataFrame):
        rows = []
        for _, r in result.iterrows():
            est = r[list(INTRINSIC_NAMES)].to_numpy(dtype=float)
            base = {"camera": r.get("camera", ""), "trial": r.get("trial", ""), "status": r.get("status", "ok")}
            rows.append({**base, **_compare(est, true_camera, seen)})
        return pd.DataFrame(rows)
    est, _ = _as_arrays(result)
    return _compare(est, true_camera, seen)


def _rays(uv: np.ndarray, true_camera: CameraModel) -> np.ndarray:
    from tasks.machine.distortion import undistort_pixels  # exact Newton inverse of the 5-parameter model

    return undistort_pixels(uv[np.all(np.isfinite(uv), axis=1)], true_camera)


def _field_differences(est: np.ndarray, true_camera: CameraModel, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """|distortion difference| and |projection difference| (px) for normalised rays x (M, 2)."""
    fx, fy, cx, cy = est[:4]
    dt = distort_normalised(x, true_camera.distortion)
    de = distort_normalised(x, tuple(est[4:9]))
    dist_px = np.linalg.norm(true_camera.fx_px * (de - dt), axis=1)
    tc = true_camera
    uv_t = np.stack([tc.fx_px * dt[:, 0] + tc.cx_px, tc.fy_px * dt[:, 1] + tc.cy_px], -1)
    uv_e = np.stack([fx * de[:, 0] + cx, fy * de[:, 1] + cy], -1)
    return dist_px, np.linalg.norm(uv_e - uv_t, axis=1)


def _compare(est: np.ndarray, true_camera: CameraModel, seen: np.ndarray | None = None) -> dict:
    fx, fy, cx, cy = est[:4]
    d_est = est[4:9]
    tf = true_camera.fx_px
    out = {
        "fx_error_pct": (fx / true_camera.fx_px - 1.0) * 100.0,
        "fy_error_pct": (fy / true_camera.fy_px - 1.0) * 100.0,
        "focal_error_pct": (np.sqrt(fx * fy) / tf - 1.0) * 100.0,
        "cx_error_px": cx - true_camera.cx_px,
        "cy_error_px": cy - true_camera.cy_px,
    }
    out["pp_error_px"] = float(np.hypot(out["cx_error_px"], out["cy_error_px"]))
    for name, a, b in zip(("dk1", "dk2", "dp1", "dp2", "dk3"), d_est, true_camera.distortion, strict=True):
        out[name] = a - b
    regions = [("", _field_grid(true_camera))] + ([("_seen", seen)] if seen is not None else [])
    for suffix, x in regions:
        keys = [f"{k}{suffix}" for k in ("distortion_max_px", "distortion_rms_px", "projection_max_px",
                                          "projection_rms_px")]
        if np.all(np.isfinite(est)) and len(x):
            dist_px, proj_px = _field_differences(est, true_camera, x)
            vals = [dist_px.max(), np.sqrt(np.mean(dist_px**2)), proj_px.max(), np.sqrt(np.mean(proj_px**2))]
        else:
            vals = [np.nan] * 4
        out.update(zip(keys, (float(v) for v in vals), strict=True))
    return out

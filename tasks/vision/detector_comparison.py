"""Table 4 of the seed paper: the RRHT, blob and Hough dot-grid detectors with PnP, side by side.

The seed (§5.2, Table 4) compares its RRHT-based target recognition framework (§4.1) with a
blob-based and a Hough-based one on runtime, recognition accuracy, reprojection error and pose
accuracy. This module measures the same on a campaign folder (docs/campaign-format.md):

* :func:`detector_runs`: every detector on the same deterministic sample of images — one row per
  (image, detector): wall time, whole grid found or not, centre error against the truth, PnP
  reprojection RMS with the given (calibrated) intrinsics, pose error against the truth.
* :func:`summarise_runs`: one row per (detector, camera) and an overall row (camera ``"all"``)
  per detector. :func:`compare_detectors` = both.
* :func:`format_table4`: the summary as a Markdown table.
* :func:`run_comparison`: intrinsics from the ``camera_calibration`` result table (or a quick
  self-calibration from the campaign's calibration views), the comparison, and the
  ``detector_comparison`` partition of the results lake with provenance.

Fairness rules (see docs/detector-comparison.md)
------------------------------------------------
* Same images, read and decoded **once** (decoding is not timed), held in memory and handed to
  every detector in the same process; per image the detectors run interleaved, the starting
  detector rotating from image to image, so that background load hits all of them alike. Each
  detector first runs once, untimed, on the first image (warm-up: lazy initialisation, caches).
* Runtime = wall time (``time.perf_counter``) of :func:`tasks.vision.detection.detect_grid`, i.e.
  including its input check and preprocessing, for one call on one image (median over
  ``repeats`` calls when repeats > 1). No scale hint (``px_per_mm_hint``), as in the pipeline.
* Orientation prior: a 7 × 7 grid is symmetric under 90° turns, so the labelling of the dots
  needs the expected in-plane angle of the plate. In the pipeline it comes from the commanded
  axes through the nominal kinematics (calibration views on the fixture get none). Here every
  detector gets the **same** prior, ``prior="truth"`` (default): the angle of the plate's +X axis
  measured on the true projected centres of dots (0, 0) → (0, 1) — the one place where truth
  reaches a detector, and only as a coarse angle. ``prior="none"`` gives no prior. Scoring then
  also matches labels to the truth within the grid's symmetry group (rotations and flips that
  map the lattice onto itself): a detection whose labelling is a symmetric relabelling of the
  true one is scored after undoing it and counted in ``n_relabelled`` (with the true prior this
  stays 0; it would matter with ``prior="none"``).
* The truth (``truth/``) is otherwise read only to score; without a truth folder the centre and
  pose errors are NaN and runtime, detection rate and reprojection RMS are still measured.

Units: px (image frame of :mod:`tasks.vision.detection.result`), ms, µm, arcsec. No Prefect import.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import statistics
import time
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pandas as pd

from tasks.core.units import RAD_TO_ARCSEC
from tasks.machine.camera_model import CameraModel
from tasks.machine.description import CALIBRATION_STAGE
from tasks.machine.kinematics import position_orientation_error
from tasks.machine.plate import DotPlate
from tasks.vision.pipeline import campaign_plates, plate_names, plates_by_camera
from tasks.vision.poses import estimate_pose

CODE_VERSION = "detector-comparison-1"
TABLE_NAME = "detector_comparison"
ALL_CAMERAS = "all"
DEFAULT_DETECTORS = ("rrht", "blob", "hough")
STAGE_ORDER = (CALIBRATION_STAGE, "pdge", "pige", "validation")
PRIORS = ("truth", "none")
RUN_COLUMNS = ("image_id", "camera", "stage", "detector", "in_view", "prior_deg", "ok", "reason", "runtime_ms",
               "rotation_deg", "relabelled", "n_dots", "centre_rms_px", "centre_max_px", "pnp_status",
               "reproj_rms_px", "trans_err_um", "rot_err_arcsec", "trans_err_truecam_um",
               "rot_err_truecam_arcsec")
SUMMARY_COLUMNS = ("detector", "camera", "n_images", "n_in_view", "n_found", "detection_rate_pct",
                   "detection_rate_in_view_pct", "n_relabelled", "runtime_mean_ms", "runtime_median_ms",
                   "n_dots", "centre_rms_px", "centre_max_px", "n_poses", "reproj_rms_px", "trans_err_mean_um",
                   "trans_err_max_um", "rot_err_mean_arcsec", "rot_err_max_arcsec", "trans_err_truecam_mean_um",
                   "rot_err_truecam_mean_arcsec")
"""Summary table columns (one row per detector and camera, plus camera ``"all"``):

n_images: images in the sample; n_in_view: of them, with the whole plate in view (truth; NaN
without truth); n_found: whole grid found (``GridDetection.ok``); detection_rate_pct =
100·n_found/n_images; detection_rate_in_view_pct: the same over the in-view images only;
n_relabelled: found grids whose labelling was a symmetric relabelling of the truth (undone for
scoring); runtime_mean_ms / runtime_median_ms: wall time of ``detect_grid`` per image (ms, over
every sampled image that could be read, found or not); n_dots: dot centres scored; centre_rms_px
/ centre_max_px: RMS and max distance (px) of the found centres to the true projected dot
centres, pooled over dots; n_poses: PnP poses obtained; reproj_rms_px: PnP reprojection RMS (px,
OpenCV's convention sqrt(Σ|r|²/K)) pooled over the dots of those images, with the given
intrinsics; trans_err_*_um: ‖t_est − t_true‖ of T_cam_plate (µm), rot_err_*_arcsec: angle of
R_estᵀ R_true (arcsec), mean / max over images (the seed's Δt, ΔR); *_truecam_*: the same with the
true intrinsics of each exposure (the detector's share, without the calibration's common error).
"""


# --------------------------------------------------------------------------------------------
# Campaign access
# --------------------------------------------------------------------------------------------


def _metadata(folder: Path) -> dict:
    return json.loads((folder / "campaign.json").read_text(encoding="utf-8"))


def sample_images(manifest: pd.DataFrame, max_images_per_camera: int = 20) -> list[str]:
    """A deterministic sample of image ids across stages and cameras.

    Per camera (in manifest order of first appearance), the quota ``max_images_per_camera`` is
    shared as evenly as possible over the stages the camera has (order of :data:`STAGE_ORDER`,
    unknown stages after), a stage's unused share passing on to the others; inside a stage the
    images are evenly spaced over its manifest order (first and last included). Returns ids in
    manifest order.
    """
    chosen: list[str] = []
    for _, cam in manifest.groupby("camera", sort=False):
        stages = sorted(cam["stage"].unique(), key=lambda s: (STAGE_ORDER.index(s) if s in STAGE_ORDER else 99, s))
        sizes = {s: int((cam["stage"] == s).sum()) for s in stages}
        quota = dict.fromkeys(stages, 0)
        left = max(0, int(max_images_per_camera))
        while left > 0 and any(quota[s] < sizes[s] for s in stages):
            for s in stages:
                if left > 0 and quota[s] < sizes[s]:
                    quota[s] += 1
                    left -= 1
        for s in stages:
            ids = cam.loc[cam["stage"] == s, "image_id"].to_numpy()
            if quota[s]:
                idx = np.unique(np.round(np.linspace(0, len(ids) - 1, quota[s])).astype(int))
                chosen.extend(map(str, ids[idx]))
    order = {i: k for k, i in enumerate(manifest["image_id"].astype(str))}
    return sorted(chosen, key=order.__getitem__)


def read_truth(folder: Path) -> tuple[pd.DataFrame | None, pd.DataFrame | None, dict[str, CameraModel]]:
    """(truth images table indexed by image_id, truth dots, true cameras) or Nones without truth/."""
    tdir = Path(folder) / "truth"
    if not (tdir / "images.parquet").is_file() or not (tdir / "dots.parquet").is_file():
        return None, None, {}
    images = pd.read_parquet(tdir / "images.parquet").set_index("image_id")
    dots = pd.read_parquet(tdir / "dots.parquet")
    cams: dict[str, CameraModel] = {}
    if (tdir / "truth.json").is_file():
        doc = json.loads((tdir / "truth.json").read_text(encoding="utf-8"))
        cams = {n: CameraModel.from_dict(c) for n, c in doc.get("cameras", {}).items()}
    return images, dots, cams


def prior_from_centres(uv: np.ndarray, plate: DotPlate) -> float:
    """In-plane angle (deg, counter-clockwise on screen from +u) of the plate's +X axis, from
    row-major centres (rows*cols, 2) px: the direction from dot (0, 0) to dot (0, 1)."""
    d = uv[1] - uv[0] if plate.cols > 1 else uv[plate.cols] - uv[0]
    angle = float(np.degrees(np.arctan2(-d[1], d[0])))
    return angle if plate.cols > 1 else angle + 90.0


def symmetric_labellings(plate: DotPlate) -> list[np.ndarray]:
    """Index arrays A (rows*cols,) such that ``centres[A]`` relabels a row-major grid by one of the
    lattice symmetries (the dihedral group: 4 rotations × flip, those keeping rows × cols and,
    on a rectangular lattice, the row and column pitches)."""
    idx = np.arange(plate.rows * plate.cols).reshape(plate.rows, plate.cols)
    out: list[np.ndarray] = []
    for base in (idx, np.fliplr(idx)):
        for k in range(4) if plate.is_square_lattice else (0, 2):
            a = np.rot90(base, k)
            if a.shape == idx.shape and not any(np.array_equal(a.ravel(), b) for b in out):
                out.append(a.ravel().copy())
    return out


def match_labels(centres: np.ndarray, truth: np.ndarray, labellings: Sequence[np.ndarray]) -> tuple[np.ndarray, bool]:
    """(relabelled centres closest to the truth in the RMS sense, whether a relabelling was needed)."""
    best, best_err, identity = centres, np.inf, True
    for a in labellings:
        err = float(np.nansum((centres[a] - truth) ** 2))
        if err < best_err - 1e-9:
            best, best_err, identity = centres[a], err, bool(np.array_equal(a, np.arange(a.size)))
    return best, not identity


# --------------------------------------------------------------------------------------------
# The comparison
# --------------------------------------------------------------------------------------------


def _time_detector(image: np.ndarray, plate: DotPlate, detector: str, prior: float | None, repeats: int):
    from tasks.vision.detection import detect_grid

    times, det = [], None
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        det = detect_grid(image, plate, detector, expected_rotation_deg=prior)
        times.append(1e3 * (time.perf_counter() - t0))
    return det, statistics.median(times)


def _pose_errors(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    dt, dr = position_orientation_error(T_est[None], T_true[None])
    return float(dt[0] * 1e3), float(dr[0] * RAD_TO_ARCSEC)


def detector_runs(campaign_folder: str | Path, cameras: Mapping[str, CameraModel],
                  detectors: Sequence[str] = DEFAULT_DETECTORS, images: Sequence[str] | None = None,
                  max_images_per_camera: int = 20, *, prior: str = "truth", repeats: int = 1,
                  warm_up: bool = True) -> pd.DataFrame:
    """Run every detector on the same images; one row per (image, detector) (:data:`RUN_COLUMNS`).

    campaign_folder: a campaign (docs/campaign-format.md). cameras: {camera: intrinsics} used for
    PnP (the pipeline's calibrated ones). detectors: names in ``tasks.vision.detection.DETECTORS``.
    images: image ids to use (default :func:`sample_images` with ``max_images_per_camera``).
    prior: "truth" (the same true-pose orientation prior for every detector) or "none".
    repeats: detector calls per image; the median time is kept (ms).

    Per row: ok (whole grid found), reason, runtime_ms, rotation_deg (found in-plane angle, deg),
    relabelled, n_dots scored, centre_rms_px / centre_max_px (px, against truth), pnp_status,
    reproj_rms_px (px), trans_err_um (µm) and rot_err_arcsec (arcsec) of T_cam_plate against the
    truth with ``cameras``, and the same with the true intrinsics (``*_truecam_*``). Accuracy
    fields are NaN where not available (no grid, no pose, no truth).
    """
    from tasks.vision.detection import DETECTORS

    if prior not in PRIORS:
        raise ValueError(f"prior must be one of {PRIORS}, not {prior!r}")
    unknown = [d for d in detectors if d not in DETECTORS]
    if unknown or not detectors:
        raise ValueError(f"unknown detector(s) {unknown}; choose from {sorted(DETECTORS)}")
    folder = Path(campaign_folder)
    meta = _metadata(folder)
    plates = campaign_plates(meta)
    manifest = pd.read_csv(folder / "manifest.csv", dtype={"image_id": str})
    manifest["plate"] = plate_names(meta, manifest)
    ids = list(images) if images is not None else sample_images(manifest, max_images_per_camera)
    rows_by_id = manifest.set_index("image_id")
    missing = [i for i in ids if i not in rows_by_id.index]
    if missing:
        raise ValueError(f"image ids not in the manifest: {missing[:5]}")
    t_images, t_dots, true_cams = read_truth(folder)
    truth_uv: dict[str, np.ndarray] = {}
    if t_dots is not None:
        for image_id, g in t_dots[t_dots["image_id"].isin(ids)].groupby("image_id"):
            plate = plates[rows_by_id.loc[image_id, "plate"]]
            uv = np.full((plate.rows * plate.cols, 2), np.nan)
            uv[g["row"].to_numpy() * plate.cols + g["col"].to_numpy()] = g[["u_px", "v_px"]].to_numpy(float)
            truth_uv[image_id] = uv

    # read and decode every image once (not timed)
    pixels: dict[str, np.ndarray | None] = {}
    for image_id in ids:
        pixels[image_id] = cv2.imread(str(folder / rows_by_id.loc[image_id, "path"]), cv2.IMREAD_GRAYSCALE)

    if warm_up:  # one untimed call per camera: lazy imports, and compiled code that only sharp dots reach
        firsts = {}
        for i in ids:
            if pixels[i] is not None:
                firsts.setdefault(rows_by_id.loc[i, "camera"], i)
        for first in firsts.values():
            for d in detectors:
                _time_detector(pixels[first], plates[rows_by_id.loc[first, "plate"]], d, None, 1)

    labellings = {name: symmetric_labellings(p) for name, p in plates.items()}
    out: list[dict[str, Any]] = []
    for k, image_id in enumerate(ids):
        m = rows_by_id.loc[image_id]
        cam, plate = str(m["camera"]), plates[str(m["plate"])]
        truth = truth_uv.get(image_id)
        T_true = None
        in_view = np.nan
        if t_images is not None and image_id in t_images.index:
            t = t_images.loc[image_id]
            T_true = np.vstack([t[[f"T{i}{j}" for i in range(3) for j in range(4)]].to_numpy(float).reshape(3, 4),
                                [0.0, 0.0, 0.0, 1.0]])
            in_view = bool(t["in_view"])
        p = prior_from_centres(truth, plate) if prior == "truth" and truth is not None else None
        true_cam = None
        if cam in true_cams and t_images is not None and image_id in t_images.index:
            scale = float(t_images.loc[image_id].get("focal_scale", 1.0))
            true_cam = true_cams[cam] if scale == 1.0 else replace(true_cams[cam], focal_length_mm=true_cams[cam]
                                                                   .focal_length_mm * scale)
        order = list(detectors[k % len(detectors):]) + list(detectors[:k % len(detectors)])
        results = {}
        for d in order:
            if pixels[image_id] is None:
                results[d] = (None, np.nan)
            else:
                results[d] = _time_detector(pixels[image_id], plate, d, p, repeats)
        for d in detectors:
            det, ms = results[d]
            row: dict[str, Any] = {
                "image_id": image_id, "camera": cam, "stage": str(m["stage"]), "detector": d, "in_view": in_view,
                "prior_deg": np.nan if p is None else p, "ok": bool(det is not None and det.ok),
                "reason": "image could not be read" if det is None else det.reason, "runtime_ms": ms,
                "rotation_deg": np.nan if det is None else det.rotation_deg, "relabelled": False, "n_dots": 0,
                "centre_rms_px": np.nan, "centre_max_px": np.nan, "pnp_status": "no_grid",
                "reproj_rms_px": np.nan, "trans_err_um": np.nan, "rot_err_arcsec": np.nan,
                "trans_err_truecam_um": np.nan, "rot_err_truecam_arcsec": np.nan,
            }
            if det is not None and det.ok:
                uv = np.asarray(det.centres, dtype=float)
                if truth is not None:
                    uv, row["relabelled"] = match_labels(uv, truth, labellings[str(m["plate"])])
                    err = np.linalg.norm(uv - truth, axis=1)
                    err = err[np.isfinite(err)]
                    row["n_dots"] = int(err.size)
                    if err.size:
                        row["centre_rms_px"] = float(np.sqrt(np.mean(err**2)))
                        row["centre_max_px"] = float(err.max())
                obj = plate.dot_centres_mm()
                if cam in cameras:
                    pose = estimate_pose(obj, uv, cameras[cam])
                    row["pnp_status"] = pose.status
                    if pose.ok:
                        row["reproj_rms_px"] = pose.rms_px
                        if T_true is not None and truth is not None:
                            row["trans_err_um"], row["rot_err_arcsec"] = _pose_errors(pose.T_cam_plate, T_true)
                else:
                    row["pnp_status"] = "no_intrinsics"
                if true_cam is not None and T_true is not None and truth is not None:
                    pose_t = estimate_pose(obj, uv, true_cam)
                    if pose_t.ok:
                        row["trans_err_truecam_um"], row["rot_err_truecam_arcsec"] = _pose_errors(
                            pose_t.T_cam_plate, T_true)
            out.append(row)
    return pd.DataFrame(out, columns=list(RUN_COLUMNS))


def _summary_row(detector: str, camera: str, g: pd.DataFrame) -> dict[str, Any]:
    n = len(g)
    found = g["ok"].astype(bool)
    known = g["in_view"].notna()
    in_view = g["in_view"].where(known, False).astype(bool) & known
    rt = g["runtime_ms"].astype(float).dropna()
    scored = g[found & g["centre_rms_px"].notna()]
    n_dots = int(scored["n_dots"].sum())
    centre_rms = (float(np.sqrt(np.sum(scored["centre_rms_px"] ** 2 * scored["n_dots"]) / n_dots))
                  if n_dots else np.nan)
    posed = g[g["reproj_rms_px"].notna()]
    # pooled over dots: every image contributes its n_points; detections are whole grids (same K)
    reproj = float(np.sqrt(np.mean(posed["reproj_rms_px"] ** 2))) if len(posed) else np.nan

    def stat(col: str, fn) -> float:
        v = g[col].astype(float).dropna()
        return float(fn(v)) if len(v) else np.nan

    return {
        "detector": detector, "camera": camera, "n_images": n,
        "n_in_view": int(in_view.sum()) if known.any() else np.nan, "n_found": int(found.sum()),
        "detection_rate_pct": 100.0 * found.sum() / n if n else np.nan,
        "detection_rate_in_view_pct": (100.0 * (found & in_view).sum() / in_view.sum()) if in_view.sum() else np.nan,
        "n_relabelled": int((found & g["relabelled"].astype(bool)).sum()),
        "runtime_mean_ms": float(rt.mean()) if len(rt) else np.nan,
        "runtime_median_ms": float(rt.median()) if len(rt) else np.nan,
        "n_dots": n_dots, "centre_rms_px": centre_rms,
        "centre_max_px": float(scored["centre_max_px"].max()) if len(scored) else np.nan,
        "n_poses": len(posed), "reproj_rms_px": reproj,
        "trans_err_mean_um": stat("trans_err_um", np.mean), "trans_err_max_um": stat("trans_err_um", np.max),
        "rot_err_mean_arcsec": stat("rot_err_arcsec", np.mean), "rot_err_max_arcsec": stat("rot_err_arcsec", np.max),
        "trans_err_truecam_mean_um": stat("trans_err_truecam_um", np.mean),
        "rot_err_truecam_mean_arcsec": stat("rot_err_truecam_arcsec", np.mean),
    }


def summarise_runs(runs: pd.DataFrame) -> pd.DataFrame:
    """The tidy summary (:data:`SUMMARY_COLUMNS`) of :func:`detector_runs`: per detector (in order
    of first appearance) one row per camera (sorted) and one row with camera ``"all"``."""
    rows = []
    for det, g in runs.groupby("detector", sort=False):
        for cam, gc in g.groupby("camera", sort=True):
            rows.append(_summary_row(str(det), str(cam), gc))
        rows.append(_summary_row(str(det), ALL_CAMERAS, g))
    return pd.DataFrame(rows, columns=list(SUMMARY_COLUMNS))


def compare_detectors(campaign_folder: str | Path, cameras: Mapping[str, CameraModel],
                      detectors: Sequence[str] = DEFAULT_DETECTORS, images: list[str] | None = None,
                      max_images_per_camera: int = 20, *, prior: str = "truth", repeats: int = 1) -> pd.DataFrame:
    """Table 4 on a campaign: :func:`summarise_runs` of :func:`detector_runs` (same arguments).

    Returns one row per (detector, camera) plus one ``camera == "all"`` row per detector, with the
    columns of :data:`SUMMARY_COLUMNS` (ms, %, px, µm, arcsec).
    """
    runs = detector_runs(campaign_folder, cameras, detectors, images, max_images_per_camera, prior=prior,
                         repeats=repeats)
    return summarise_runs(runs)


def _fmt(v: Any, digits: int) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)) or pd.isna(v):
        return "–"
    return f"{float(v):.{digits}f}"


def format_table4(df: pd.DataFrame, per_camera: bool = True) -> str:
    """The summary as a Markdown table in the spirit of the seed's Table 4 (overall rows in bold
    detector names; ``per_camera=False`` keeps only them)."""
    head = ("| Detector | Camera | Images | Found (%) | Runtime mean / median (ms) | Centre RMS (px) "
            "| Reproj. RMS (px) | Translation error mean (µm) | Rotation error mean (″) "
            "| Transl. / rot. error, true intrinsics (µm / ″) |")
    lines = [head, "|" + "---|" * 10]
    for r in df.itertuples(index=False):
        if not per_camera and r.camera != ALL_CAMERAS:
            continue
        name = f"**{r.detector}**" if r.camera == ALL_CAMERAS else r.detector
        lines.append(
            f"| {name} | {r.camera} | {r.n_images} | {_fmt(r.detection_rate_pct, 1)} "
            f"| {_fmt(r.runtime_mean_ms, 0)} / {_fmt(r.runtime_median_ms, 0)} | {_fmt(r.centre_rms_px, 3)} "
            f"| {_fmt(r.reproj_rms_px, 3)} | {_fmt(r.trans_err_mean_um, 1)} | {_fmt(r.rot_err_mean_arcsec, 1)} "
            f"| {_fmt(r.trans_err_truecam_mean_um, 1)} / {_fmt(r.rot_err_truecam_mean_arcsec, 1)} |")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------
# Intrinsics and the results-lake entry point
# --------------------------------------------------------------------------------------------


def _nominal(metadata: dict, name: str) -> CameraModel:
    from tasks.vision.camera_calibration import nominal_camera

    return nominal_camera(metadata["cameras"][name], name)


def intrinsics_from_table(table: pd.DataFrame, metadata: dict) -> dict[str, CameraModel]:
    """{camera: CameraModel} from ``camera_calibration`` rows with trial "joint" and status "ok"
    (fx_px, fy_px, cx_px, cy_px in px; k1, k2, p1, p2, k3). One focal length sqrt(fx·fy) (px;
    fy missing → fx), converted to mm with the nominal pixel pitch of campaign.json."""
    out: dict[str, CameraModel] = {}
    if table.empty or not {"trial", "status", "camera"} <= set(table.columns):
        return out
    ok = table[(table["trial"] == "joint") & (table["status"] == "ok")]
    for r in ok.to_dict("records"):
        name = str(r["camera"])
        if name not in metadata["cameras"]:
            continue
        fx = float(r["fx_px"])
        fy = float(r["fy_px"]) if r.get("fy_px") is not None and not pd.isna(r.get("fy_px")) else fx
        nom = _nominal(metadata, name)
        dist = tuple(float(r[k]) for k in ("k1", "k2", "p1", "p2", "k3"))
        model = replace(nom, focal_length_mm=float(np.sqrt(fx * fy)) * nom.pixel_size_mm, cx_px=float(r["cx_px"]),
                        cy_px=float(r["cy_px"]), distortion=dist)
        if np.all(np.isfinite(model.matrix)) and np.all(np.isfinite(model.dist_coeffs)):
            out[name] = model
    return out


def self_calibrate(campaign_folder: str | Path, cameras: Sequence[str] | None = None,
                   max_images_per_camera: int = 12) -> tuple[dict[str, CameraModel], dict[str, str]]:
    """Quick self-calibration from the campaign's ``camera_calibration`` views (RRHT centres).

    Per camera at most ``max_images_per_camera`` views, evenly spaced over the manifest order,
    detected without orientation prior (a symmetric relabelling of a view is an equally valid
    view for calibration), then one OpenCV fit (one focal length, 5 distortion parameters,
    started from the nominal intrinsics of campaign.json). Returns ({camera: model}, {camera:
    how it was obtained}); a camera whose fit fails keeps its nominal intrinsics (said so).
    """
    from tasks.vision.camera_calibration import calibrate_trial
    from tasks.vision.detection import detect_grid

    folder = Path(campaign_folder)
    meta = _metadata(folder)
    plates = plates_by_camera(meta, CALIBRATION_STAGE)
    manifest = pd.read_csv(folder / "manifest.csv", dtype={"image_id": str})
    models: dict[str, CameraModel] = {}
    sources: dict[str, str] = {}
    for name in cameras or list(meta["cameras"]):
        nominal = _nominal(meta, name)
        sel = manifest[(manifest["camera"] == name) & (manifest["stage"] == CALIBRATION_STAGE)]
        if len(sel) > max_images_per_camera:
            sel = sel.iloc[np.unique(np.round(np.linspace(0, len(sel) - 1, max_images_per_camera)).astype(int))]
        obj, img, ids = [], [], []
        plate = plates[name]
        for r in sel.itertuples(index=False):
            image = cv2.imread(str(folder / r.path), cv2.IMREAD_GRAYSCALE)
            if image is None:
                continue
            det = detect_grid(image, plate, "rrht")
            if det.ok:
                obj.append(plate.dot_centres_mm())
                img.append(det.centres)
                ids.append(r.image_id)
        res = calibrate_trial(obj, img, (nominal.width_px, nominal.height_px), nominal, camera=name, trial="joint",
                              image_ids=ids, fix_aspect_ratio=True)
        if res.ok:
            models[name] = res.camera_model(nominal)
            sources[name] = f"self-calibrated ({res.n_images} views, rrht, rms {res.rms_px:.4f} px)"
        else:
            models[name] = nominal
            sources[name] = f"nominal (self-calibration failed: {res.status}: {res.message})"
    return models, sources


def _input_hash(folder: Path, manifest: pd.DataFrame, ids: Sequence[str]) -> str:
    from tasks.campaign.ingest import file_sha256

    paths = manifest.set_index("image_id").loc[list(ids), "path"]
    h = hashlib.sha256()
    for image_id, rel in paths.items():
        p = folder / rel
        h.update(f"{image_id}:{file_sha256(p) if p.is_file() else 'missing'}\n".encode())
    return h.hexdigest()


def run_comparison(campaign: str | Path, results_root: str | Path | None = None, *,
                   detectors: Sequence[str] = DEFAULT_DETECTORS, max_images_per_camera: int = 20,
                   images: list[str] | None = None, prior: str = "truth", repeats: int = 1,
                   calibration_images_per_camera: int = 12) -> tuple[pd.DataFrame, Path]:
    """Compare the detectors on a campaign folder and write the ``detector_comparison`` partition.

    Intrinsics: the ``camera_calibration`` result table of this campaign in ``results_root``
    (rows trial == "joint", status == "ok"); cameras missing there are self-calibrated here
    (:func:`self_calibrate`, at most ``calibration_images_per_camera`` views each). The summary
    (:data:`SUMMARY_COLUMNS`) gets the column ``intrinsics_source``; the partition's provenance
    holds the fivecal version, a hash of the sampled image files, the image ids, the parameters,
    the intrinsics used and the host (CPU count, OpenCV threads) — runtimes depend on it.
    Returns (summary table, path of the written Parquet file).
    """
    from tasks.core.version import FIVECAL_VERSION
    from tasks.lake.store import read_table, write_partition

    folder = Path(campaign)
    meta = _metadata(folder)
    campaign_id = str(meta["campaign_id"])
    cameras = intrinsics_from_table(read_table("camera_calibration", results_root, campaign_id), meta)
    sources = dict.fromkeys(cameras, "camera_calibration table (joint)")
    missing = [c for c in meta["cameras"] if c not in cameras]
    if missing:
        more, more_src = self_calibrate(folder, missing, calibration_images_per_camera)
        cameras.update(more)
        sources.update(more_src)
    manifest = pd.read_csv(folder / "manifest.csv", dtype={"image_id": str})
    ids = list(images) if images is not None else sample_images(manifest, max_images_per_camera)
    summary = compare_detectors(folder, cameras, detectors, ids, max_images_per_camera, prior=prior,
                                repeats=repeats)
    summary["intrinsics_source"] = [
        sources.get(c, "") if c != ALL_CAMERAS else "; ".join(f"{n}: {sources[n]}" for n in sorted(sources))
        for c in summary["camera"]]
    provenance = {
        "fivecal_version": FIVECAL_VERSION, "input_sha256": _input_hash(folder, manifest, ids),
        "parameters": {"code_version": CODE_VERSION, "detectors": list(detectors), "prior": prior,
                       "repeats": repeats, "max_images_per_camera": max_images_per_camera,
                       "calibration_images_per_camera": calibration_images_per_camera, "image_ids": ids},
        "intrinsics": {n: {"source": sources[n], **c.to_dict()} for n, c in cameras.items()},
        "host": {"cpu_count": os.cpu_count(), "opencv": cv2.__version__, "opencv_threads": cv2.getNumThreads(),
                 "machine": platform.machine(), "python": platform.python_version()},
    }
    path = write_partition(TABLE_NAME, campaign_id, summary, provenance, results_root)
    return summary, path


def _main(argv: Sequence[str] | None = None) -> None:
    """``python -m tasks.vision.detector_comparison CAMPAIGN [--results DIR] ...``: print Table 4, write the table."""
    import argparse

    p = argparse.ArgumentParser(description="Table 4: the dot-grid detectors with PnP on a campaign folder.")
    p.add_argument("campaign", help="campaign folder")
    p.add_argument("--results", default=None, help="results root (default data/results or $FIVECAL_RESULTS_DIR)")
    p.add_argument("--detector", action="append", help="detector (repeatable; default rrht, blob, hough)")
    p.add_argument("--max-images-per-camera", type=int, default=20)
    p.add_argument("--repeats", type=int, default=1, help="timed calls per image and detector (median kept)")
    p.add_argument("--prior", choices=PRIORS, default="truth")
    p.add_argument("--calibration-images", type=int, default=12,
                   help="views per camera for the fallback self-calibration")
    a = p.parse_args(argv)
    summary, path = run_comparison(a.campaign, a.results, detectors=tuple(a.detector or DEFAULT_DETECTORS),
                                   max_images_per_camera=a.max_images_per_camera, prior=a.prior, repeats=a.repeats,
                                   calibration_images_per_camera=a.calibration_images)
    print(format_table4(summary))
    print(f"\nintrinsics: {summary['intrinsics_source'].iloc[-1]}")
    print(f"detector_comparison table: {path}")


if __name__ == "__main__":
    _main()

"""From ingested images to plate poses: dot detection, camera self-calibration, PnP (§4.1, §5.2).

No Prefect here. The flow ``flows/measure.py`` runs these steps as cached tasks; a notebook can
call them directly.

- :func:`plate_names`, :func:`campaign_plates`, :func:`plates_by_camera`: which plate each image
  shows — a camera's calibration target in its camera_calibration views, the plate it measures
  otherwise (``Machine.plate_seen``) — and the plates themselves.
- :func:`with_detection_inputs`: the images table with each image's plate and expected rotation.
- :func:`expected_rotations`: the in-plane angle at which each plate should appear, from the
  *nominal* kinematics at the commanded axes. It resolves the 90°/180° symmetry of a square grid;
  calibration views (plate on a fixture, any rotation) get none, and any symmetric labelling is
  equally valid for self-calibration.
- :func:`detect_images`: dot centres of a chunk of images (the ``dots`` table).
- :func:`calibrate_cameras`: per camera, the trials of Table 3 and a joint best estimate
  (the ``camera_calibration`` table).
- :func:`plate_poses`: PnP with the calibrated intrinsics (the ``poses`` table).
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Mapping
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from tasks.camera_calibration import calibrate_camera, nominal_camera, trial_views
from tasks.camera_model import CameraModel, project_points
from tasks.detection import detect_grid
from tasks.kinematics import forward
from tasks.machine import CALIBRATION_STAGE, Machine, machine_from_dict, plate_seen
from tasks.plate import DotPlate
from tasks.poses import estimate_poses

# Bump when a change in detection, calibration or pose code changes their results: it is part of
# every cache key of the measure flow.
VISION_CODE_VERSION = "vision-6"
COMMANDS = ("X_mm", "Y_mm", "Z_mm", "A_deg", "C_deg")  # in AXIS_ORDER
DOT_COLUMNS = ("image_id", "camera", "row", "col", "u_px", "v_px", "residual_rms_px", "support_ratio", "detector")
DETECTION_COLUMNS = ("image_id", "camera", "plate", "detection_status", "detection_message", "rotation_deg",
                     "elapsed_ms")


def content_key(*parts) -> str:
    """sha256 of JSON-serialisable parts and DataFrames (by their values), for cache keys."""
    h = hashlib.sha256(VISION_CODE_VERSION.encode())
    for p in parts:
        if isinstance(p, pd.DataFrame):
            h.update(pd.util.hash_pandas_object(p, index=False).to_numpy().tobytes())
            h.update(json.dumps(list(map(str, p.columns))).encode())
        else:
            h.update(json.dumps(p, sort_keys=True, default=str).encode())
    return h.hexdigest()


def campaign_plates(metadata: dict) -> dict[str, DotPlate]:
    """{plate name: DotPlate} of every plate in campaign.json (measured plates and calibration targets)."""
    return {name: DotPlate.from_dict({**spec, "name": name}) for name, spec in metadata["plates"].items()}


def _plate_name(metadata: dict, camera: str, stage: str) -> str:
    return plate_seen(metadata["views"], metadata.get("calibration_targets", {}), camera, stage)


def plates_by_camera(metadata: dict, stage: str = "pige") -> dict[str, DotPlate]:
    """{camera: the plate it sees in images of ``stage``} from campaign.json: its calibration
    target in the camera_calibration stage (campaigns without ``calibration_targets`` calibrate
    on the measured plate), the plate it measures otherwise."""
    plates = campaign_plates(metadata)
    return {cam: plates[_plate_name(metadata, cam, stage)] for cam in metadata["views"]}


def plate_names(metadata: dict, images: pd.DataFrame) -> pd.Series:
    """Name of the plate each image shows (index of ``images``: rows with camera and stage)."""
    names = [_plate_name(metadata, c, s) if c in metadata["views"] else ""
             for c, s in zip(images["camera"], images["stage"], strict=True)]
    return pd.Series(names, index=images.index, dtype=object)


def nominal_cameras(metadata: dict) -> dict[str, CameraModel]:
    """{camera: nominal intrinsics} (centred principal point, no distortion) from campaign.json."""
    return {name: nominal_camera(spec, name) for name, spec in metadata["cameras"].items()}


def nominal_machine(metadata: dict) -> Machine:
    """The machine of campaign.json with nominal cameras (what the analysis may know)."""
    cams = {n: {k: v for k, v in c.to_dict().items() if k != "name"} for n, c in nominal_cameras(metadata).items()}
    return machine_from_dict({**metadata["machine"], "cameras": cams, "plates": metadata["plates"],
                              "views": metadata["views"],
                              "calibration_targets": metadata.get("calibration_targets", {})})


def expected_rotations(metadata: dict, images: pd.DataFrame) -> pd.Series:
    """Expected in-plane angle (deg, counter-clockwise on screen from +u) of each plate's +X axis.

    From the nominal kinematics at the commanded axes; NaN for camera_calibration views.
    images: rows of the images table (camera, stage, X_mm ... C_deg).
    """
    out = pd.Series(np.nan, index=images.index, dtype=float)
    machine = nominal_machine(metadata)
    for camera, g in images[images["stage"] != CALIBRATION_STAGE].groupby("camera"):
        if camera not in machine.cameras:
            continue
        T = forward(machine, g[list(COMMANDS)].to_numpy(float)).camera_view(camera)  # (N, 4, 4)
        pitch = machine.plates[machine.views[camera]].pitch_mm
        pts = np.stack([T[:, :3, 3], T[:, :3, 3] + pitch * T[:, :3, 0]], axis=1)  # origin, +X, camera frame
        uv = project_points(pts, machine.cameras[camera])
        d = uv[:, 1] - uv[:, 0]
        out.loc[g.index] = np.degrees(np.arctan2(-d[:, 1], d[:, 0]))
    return out


def with_detection_inputs(metadata: dict, images: pd.DataFrame) -> pd.DataFrame:
    """``images`` with what detection needs beside each image: ``rotation_deg``
    (:func:`expected_rotations`) and ``plate`` (:func:`plate_names`)."""
    return images.assign(rotation_deg=expected_rotations(metadata, images), plate=plate_names(metadata, images))


def detection_chunks(images: pd.DataFrame, chunk_size: int) -> list[pd.DataFrame]:
    """The ingested images fit for detection (status ok), in chunks of ``chunk_size`` rows."""
    ok = images[images["status"] == "ok"]
    return [ok.iloc[i:i + chunk_size] for i in range(0, len(ok), chunk_size)]


def detect_images(folder: Path, rows: pd.DataFrame, plates: Mapping[str, DotPlate],
                  detector: str = "rrht") -> tuple[pd.DataFrame, pd.DataFrame]:
    """Detect the dot grid in each image of ``rows``.

    rows: images-table rows with image_id, camera, path, ``plate`` (the name of the plate the image
    shows, :func:`plate_names`) and ``rotation_deg`` (expected, NaN = none). plates: {plate name:
    DotPlate} (:func:`campaign_plates`).
    Returns (dots, detections): dots has one row per found dot (DOT_COLUMNS, px); detections one
    row per image with its status ("ok" or "no_grid"), message naming the file, and timing.
    """
    dots, detections = [], []
    for r in rows.itertuples(index=False):
        plate = plates.get(r.plate)
        path = Path(folder) / r.path
        t0 = time.perf_counter()
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if plate is None:
            status, message, res = "no_grid", f"{r.path}: camera {r.camera!r} has no plate in campaign.json", None
        elif image is None:  # changed since ingest
            status, message, res = "no_grid", f"{r.path}: could not be read", None
        else:
            prior = None if np.isnan(r.rotation_deg) else float(r.rotation_deg)
            res = detect_grid(image, plate, detector, expected_rotation_deg=prior)
            status = "ok" if res.ok else "no_grid"
            message = "" if res.ok else f"{r.path}: {res.reason}"
        elapsed = 1e3 * (time.perf_counter() - t0)
        detections.append((r.image_id, r.camera, r.plate, status, message,
                           float("nan") if res is None else res.rotation_deg, elapsed))
        if res is not None and res.ok:
            rc = plate.row_col()
            dots.append(pd.DataFrame({
                "image_id": r.image_id, "camera": r.camera, "row": rc[:, 0], "col": rc[:, 1],
                "u_px": res.centres[:, 0], "v_px": res.centres[:, 1],
                "residual_rms_px": res.residual_rms_px, "support_ratio": res.support_ratio, "detector": detector,
            }))
    dots_df = pd.concat(dots, ignore_index=True) if dots else pd.DataFrame(columns=list(DOT_COLUMNS))
    return dots_df, pd.DataFrame(detections, columns=list(DETECTION_COLUMNS))


def calibrate_cameras(dots: pd.DataFrame, images: pd.DataFrame, metadata: dict
                      ) -> tuple[pd.DataFrame, dict[str, CameraModel]]:
    """Self-calibration of every camera from its camera_calibration views (§5.2, Table 3).

    Returns the camera_calibration table (one row per trial and a "joint" row per camera: the
    best estimate, fitted on every valid view) and {camera: calibrated intrinsics}.
    """
    plates = plates_by_camera(metadata, CALIBRATION_STAGE)
    tables, models = [], {}
    for camera, nominal in nominal_cameras(metadata).items():
        views = trial_views(dots, images, camera, plates[camera])
        if not views:
            continue
        cal = calibrate_camera(views, nominal, camera=camera)
        joint = pd.DataFrame([cal.joint.to_row()], columns=cal.trials.columns)
        tables.append(pd.concat([cal.trials, joint], ignore_index=True))
        if cal.best_estimate is not None:
            models[camera] = cal.best_estimate
    table = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame()
    return table, models


def plate_poses(dots: pd.DataFrame, detections: pd.DataFrame, cameras: dict[str, CameraModel],
                plates: Mapping[str, DotPlate]) -> pd.DataFrame:
    """PnP pose of every image with a detected grid; images without one keep their status.

    detections: :func:`detect_images`' per-image table (its ``plate`` names the plate each image
    shows). plates: {plate name: DotPlate}. Poses are T_cam_plate of that plate (mm).
    """
    plate_of = detections.set_index("image_id")["plate"]
    if len(dots):
        parts = [estimate_poses(g, cameras, plates[name])
                 for name, g in dots.groupby(dots["image_id"].map(plate_of), sort=False)]
        poses = pd.concat(parts, ignore_index=True)
    else:
        poses = pd.DataFrame(columns=["image_id"])
    failed = detections[detections["detection_status"] != "ok"]
    missing = pd.DataFrame({"image_id": failed["image_id"], "camera": failed["camera"],
                            "status": failed["detection_status"], "message": failed["detection_message"]})
    return pd.concat([poses, missing], ignore_index=True)

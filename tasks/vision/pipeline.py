"""From ingested images to plate poses: dot detection, camera self-calibration, PnP (§4.1, §5.2).

No Prefect here. The flow ``flows/measure.py`` runs these steps as cached tasks; a notebook can
call them directly.

- :func:`plate_names`, :func:`campaign_plates`, :func:`plates_by_camera`: which plate each image
  shows — a camera's calibration target in its camera_calibration views, the plate it measures
  otherwise (``Machine.plate_seen``) — and the plates themselves.
- :func:`with_detection_inputs`: the images table with each image's plate and expected rotation.
- :func:`expected_homographies`, :func:`expected_rotations`: where each plate's dots should appear
  and at what in-plane angle, from the *nominal* kinematics at the commanded axes. The angle
  resolves the 90°/180° symmetry of a square grid; the dots' positions let a plate partly out of
  the image be measured on the dots inside it. Calibration views (plate on a fixture, any
  rotation) get neither, and any symmetric labelling is equally valid for self-calibration.
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

from tasks.campaign.ingest import MAX_FAULT_FRACTION, CampaignError
from tasks.machine.camera_model import CameraModel
from tasks.machine.description import CALIBRATION_STAGE, COMMAND_COLUMNS, Machine, machine_from_dict, plate_seen
from tasks.machine.kinematics import forward
from tasks.machine.plate import DotPlate
from tasks.vision.camera_calibration import (
    MACHINE_STAGES,
    calibrate_camera,
    machine_views,
    nominal_camera,
    trial_views,
)
from tasks.vision.centre_bias import unbiased_dots
from tasks.vision.detection import detect_grid
from tasks.vision.detection.grid_order import rotation_deg
from tasks.vision.detection.perspective import project
from tasks.vision.intrinsics_refinement import refine_intrinsics
from tasks.vision.poses import estimate_poses

# Bump when a change in detection, calibration or pose code changes their results: it is part of
# every cache key of the measure flow.
VISION_CODE_VERSION = "vision-9"
FIX_K3 = True
"""Camera self-calibration keeps k3 at 0 (four distortion coefficients). The calibration targets'
views stay off the field's edges, so k3 is barely determined there (with it free, camera 1's k3 came
out between −2.8 and +1.4 on the 10-seed panel against a true −0.041, k2 trading off against it) and
the r⁶ term extrapolates into the part of the field that the X sweep's ends use: the plate's tilt
about y read there by PnP was off by up to 64″ at X = ±25 mm, which became X's εy profile (and a
true −0.041 is 1.8·10⁻⁵ of the radius at the field's corner: 0.008 px at the demo size, 0.03 px at
full size). ``bench/x_sweep_tilt.py`` measures it."""
POSES_VERSION = "poses-2"
"""Part of the poses' cache key (with VISION_CODE_VERSION): bump when :func:`plate_poses` would
return something else for the same dots and intrinsics."""
SELF_CALIBRATION_STAGES = (CALIBRATION_STAGE, *MACHINE_STAGES)
"""The stages whose images :func:`calibrate_cameras` reads."""
SELF_CALIBRATION_VERSION = "self-calibration-3"
"""Part of the self-calibration's cache key (with VISION_CODE_VERSION, which also keys detection):
bump when :func:`calibrate_cameras` would return something else for the same dots."""
DOT_COLUMNS = ("image_id", "camera", "row", "col", "u_px", "v_px", "residual_rms_px", "support_ratio", "detector")
PRIOR_COLUMNS = tuple(f"prior_h{i}{j}" for i in range(3) for j in range(3))
"""Columns of the predicted plate → image homography that detection takes (:func:`with_detection_inputs`)."""
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


def expected_homographies(metadata: dict, images: pd.DataFrame) -> np.ndarray:
    """(N, 3, 3) plate (x, y) mm → image px homography of each image's plate, predicted from the
    commanded axes through the *nominal* kinematics and the nominal camera (pinhole, no
    distortion: H = K [r₁ r₂ t]); NaN for camera_calibration views and unknown cameras.
    images: rows of the images table (camera, stage, X_mm ... C_deg).

    The machine's geometric errors and the lens move the real dots by a small part of the pitch;
    detection only needs each dot's prediction to fall nearer its own dot than any other.
    """
    out = np.full((len(images), 3, 3), np.nan)
    machine = nominal_machine(metadata)
    measured = np.flatnonzero((images["stage"] != CALIBRATION_STAGE).to_numpy())
    for camera, g in images.iloc[measured].groupby("camera"):
        if camera not in machine.cameras:
            continue
        T = forward(machine, g[list(COMMAND_COLUMNS)].to_numpy(float)).camera_view(camera)  # (N, 4, 4) T_cam_plate
        H = machine.cameras[camera].matrix @ T[:, :3][:, :, [0, 1, 3]]
        out[images.index.get_indexer(g.index)] = H / H[:, 2:, 2:]
    return out


def homography_rotations(H: np.ndarray) -> np.ndarray:
    """(N,) in-plane angle (deg, counter-clockwise on screen from +u) of the plate's +X axis at the
    plate's centre under the plate → image homographies ``H`` (N, 3, 3); NaN where H is."""
    origin = H[:, :2, 2] / H[:, 2:, 2]
    along_x = (H[:, :2, 0] + H[:, :2, 2]) / (H[:, 2:, 0] + H[:, 2:, 2])  # the plate point (1 mm, 0)
    return rotation_deg(along_x - origin)


def expected_rotations(metadata: dict, images: pd.DataFrame) -> pd.Series:
    """Expected in-plane angle (deg) of each plate's +X axis (:func:`homography_rotations` of
    :func:`expected_homographies`); NaN for camera_calibration views.
    images: rows of the images table (camera, stage, X_mm ... C_deg).
    """
    return pd.Series(homography_rotations(expected_homographies(metadata, images)), index=images.index, dtype=float)


def with_detection_inputs(metadata: dict, images: pd.DataFrame) -> pd.DataFrame:
    """``images`` with what detection needs beside each image: ``rotation_deg``
    (:func:`expected_rotations`), ``plate`` (:func:`plate_names`) and the predicted homography in
    :data:`PRIOR_COLUMNS` (:func:`expected_homographies`, row-major, scaled to h22 = 1)."""
    H = expected_homographies(metadata, images)
    flat = H.reshape(len(images), 9)
    return images.assign(rotation_deg=homography_rotations(H), plate=plate_names(metadata, images),
                         **{c: flat[:, k] for k, c in enumerate(PRIOR_COLUMNS)})


def detection_chunks(images: pd.DataFrame, chunk_size: int) -> list[pd.DataFrame]:
    """The ingested images fit for detection (status ok), in chunks of ``chunk_size`` rows."""
    ok = images[images["status"] == "ok"]
    return [ok.iloc[i:i + chunk_size] for i in range(0, len(ok), chunk_size)]


def detect_images(folder: Path, rows: pd.DataFrame, plates: Mapping[str, DotPlate],
                  detector: str = "rrht") -> tuple[pd.DataFrame, pd.DataFrame]:
    """Detect the dot grid in each image of ``rows``.

    rows: images-table rows with image_id, camera, path, ``plate`` (the name of the plate the image
    shows, :func:`plate_names`), ``rotation_deg`` (expected, NaN = none) and, optionally, the
    predicted homography (:data:`PRIOR_COLUMNS`, NaN = none), with which a plate partly out of the
    image is measured on the dots wholly inside it. plates: {plate name: DotPlate}
    (:func:`campaign_plates`).
    Returns (dots, detections): dots has one row per measured dot (DOT_COLUMNS, px); detections one
    row per image with its status ("ok" or "no_grid"), message naming the file (for an ok
    partial view: how many dots were measured), and timing.
    """
    dots, detections = [], []
    priors = (rows[list(PRIOR_COLUMNS)].to_numpy(float).reshape(-1, 3, 3) if set(PRIOR_COLUMNS) <= set(rows.columns)
              else np.full((len(rows), 3, 3), np.nan))
    for r, H in zip(rows.itertuples(index=False), priors, strict=True):
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
            expected = project(H, plate.dot_centres_mm()[:, :2]) if np.isfinite(H).all() else None
            res = detect_grid(image, plate, detector, expected_rotation_deg=prior, expected_centres_px=expected)
            status = "ok" if res.ok else "no_grid"
            n_found, n_dots = int(res.found.sum()), plate.rows * plate.cols
            message = (f"{r.path}: {res.reason}" if not res.ok else "" if n_found == n_dots
                       else f"{r.path}: partial view, {n_found} of {n_dots} dots wholly in the image")
        elapsed = 1e3 * (time.perf_counter() - t0)
        detections.append((r.image_id, r.camera, r.plate, status, message,
                           float("nan") if res is None else res.rotation_deg, elapsed))
        if res is not None and res.ok:
            k = res.found
            rc = plate.row_col()[k]
            dots.append(pd.DataFrame({
                "image_id": r.image_id, "camera": r.camera, "row": rc[:, 0], "col": rc[:, 1],
                "u_px": res.centres[k, 0], "v_px": res.centres[k, 1],
                "residual_rms_px": res.residual_rms_px[k], "support_ratio": res.support_ratio[k], "detector": detector,
            }))
    dots_df = pd.concat(dots, ignore_index=True) if dots else pd.DataFrame(columns=list(DOT_COLUMNS))
    return dots_df, pd.DataFrame(detections, columns=list(DETECTION_COLUMNS))


def calibrate_cameras(dots: pd.DataFrame, images: pd.DataFrame, metadata: dict
                      ) -> tuple[pd.DataFrame, dict[str, CameraModel]]:
    """Self-calibration of every camera from its camera_calibration views (§5.2, Table 3), its best
    estimate refined on the machine's images of the plate the camera measures.

    The trials are fitted on the calibration views alone (Table 3); the joint best estimate is then
    refined on those views and the camera's images of its measured plate in the linear axes' sweeps
    and the five-axis poses (:func:`tasks.vision.camera_calibration.machine_views`, each view with a
    free pose; :mod:`tasks.vision.intrinsics_refinement` says why). A camera without such images
    (camera 2: the A sweep turns plate b about the field's centre) keeps the joint fit. All of it
    runs twice: the second time on the dot centres without the lens's share of their bias
    (:func:`tasks.vision.centre_bias.unbiased_dots`, computed with the first estimate). Returns the
    camera_calibration table (one row per trial and a "joint" row per camera: the best estimate and
    the views it was fitted on) and {camera: calibrated intrinsics}. dots: the campaign's dots
    table (the images the fit does not read may be left out).
    """
    _, first = _self_calibration(dots, images, metadata)
    used = images[images["stage"].isin(SELF_CALIBRATION_STAGES)]
    plate_of = pd.Series(plate_names(metadata, used).to_numpy(), index=used["image_id"].to_numpy())
    unbiased = unbiased_dots(dots[dots["image_id"].isin(used["image_id"])], plate_of, first, campaign_plates(metadata))
    return _self_calibration(unbiased, images, metadata)


def _self_calibration(dots: pd.DataFrame, images: pd.DataFrame, metadata: dict
                      ) -> tuple[pd.DataFrame, dict[str, CameraModel]]:
    """One pass of :func:`calibrate_cameras` on these dot centres."""
    targets = plates_by_camera(metadata, CALIBRATION_STAGE)
    measured = plates_by_camera(metadata)
    sweeps = nominal_machine(metadata).linear_axes
    tables, models = [], {}
    for camera, nominal in nominal_cameras(metadata).items():
        views = trial_views(dots, images, camera, targets[camera])
        if not views:
            continue
        cal = calibrate_camera(views, nominal, camera=camera, fix_k3=FIX_K3)
        joint = cal.joint
        if cal.best_estimate is not None:
            models[camera] = cal.best_estimate
            extra = machine_views(dots, images, camera, measured[camera], sweeps) if camera in measured else []
            if extra:
                used = set(joint.image_ids)
                calibration = [(o, m) for objs, imgs, ids in views.values()
                               for o, m, i in zip(objs, imgs, ids, strict=True) if i in used]
                refined = refine_intrinsics(calibration + extra, cal.best_estimate, fix_k3=FIX_K3)
                if refined.ok:
                    joint = refined
                    models[camera] = refined.camera_model(cal.best_estimate)
        row = pd.DataFrame([joint.to_row()], columns=cal.trials.columns)
        tables.append(pd.concat([cal.trials, row], ignore_index=True))
    table = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame()
    return table, models


def check_detections(campaign: str | Path, detections: pd.DataFrame, plates: Mapping[str, DotPlate]) -> None:
    """Raise :class:`tasks.campaign.ingest.CampaignError` when no grid was found in more than
    :data:`tasks.campaign.ingest.MAX_FAULT_FRACTION` of the images (then the plates campaign.json describes
    are most likely not the plates photographed) detection ran on (``detections``: one row per
    image, :data:`DETECTION_COLUMNS`), saying per plate how many were found with the geometry
    campaign.json gives it, and the first image's reason."""
    missed = detections["detection_status"] != "ok"
    if not len(detections) or missed.sum() <= MAX_FAULT_FRACTION * len(detections):
        return
    per_plate = []
    for name, g in detections.groupby("plate", sort=True):
        p = plates.get(name)
        shape = f" ({p.rows}×{p.cols} dots at {p.pitch_mm:g} mm)" if p is not None else ""
        per_plate.append(f"{name}{shape}: {int((g['detection_status'] == 'ok').sum())} of {len(g)}")
    first = detections[missed].iloc[0]
    raise CampaignError(
        f"{campaign}: no dot grid found in {int(missed.sum())} of {len(detections)} images, more than the "
        f"{MAX_FAULT_FRACTION:.0%} a campaign may miss (MAX_FAULT_FRACTION): check each plate's rows, "
        f"cols, pitch_mm and dark_dots in campaign.json against the plates photographed; refused before the dots, "
        f"camera_calibration and poses tables are written. Grids found per plate: {'; '.join(per_plate)}. "
        f"First: image {first['image_id']}: {first['detection_status']}: {first['detection_message']}")


def plate_poses(dots: pd.DataFrame, detections: pd.DataFrame, cameras: dict[str, CameraModel],
                plates: Mapping[str, DotPlate]) -> pd.DataFrame:
    """PnP pose of every image with a detected grid; images without one keep their status.

    detections: :func:`detect_images`' per-image table (its ``plate`` names the plate each image
    shows). plates: {plate name: DotPlate}. Poses are T_cam_plate of that plate (mm), from the dot
    centres without the lens's share of their bias (:func:`tasks.vision.centre_bias.unbiased_dots`).
    """
    plate_of = detections.set_index("image_id")["plate"]
    dots = unbiased_dots(dots, plate_of, cameras, plates)
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

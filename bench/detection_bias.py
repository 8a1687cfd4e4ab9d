"""Camera 1's detected dot centres against the simulator's true projections, and what their error
does to the refined self-calibration, seed by seed.

For each campaign ``<campaigns>/s<seed>`` (its ``truth/`` beside it) and its detected dots (the
``dots`` table of the lake ``--results``, or with ``--detect`` the camera's images detected again
with the current detector, about 0.1 s an image at full size), printed per seed:

- per stage (camera_calibration, pdge, pige, validation): the RMS of detected − true (px) and the
  ``slope`` of its component along the image direction of increasing depth against the dot's depth
  offset from the plate's mean (mpx per mm of depth): a grid compressed along the depth gradient
  (slope < 0) is read by PnP and the self-calibration as a weaker perspective, a longer focal
  length;
- ``m2``: Δθᵀ Σ_θ⁻¹ Δθ over (f, cx, cy, k1, k2, p1, p2) of camera 1's self-calibration as the
  pipeline makes it (:func:`tasks.vision.pipeline.calibrate_cameras`: the calibration views' joint
  fit refined on the machine's images of plate a, k3 held) against the truth, Σ_θ its stated
  covariance (:func:`tasks.vision.intrinsics_uncertainty.intrinsics_covariances`), χ² on 7 degrees
  of freedom if Σ_θ is honest; ``df_ppm``: its focal length error;
- ``m2_white``, ``df_white_ppm``: the same with the detected centres replaced by what an exact
  ellipse fit and the detector's perspective correction give on the true image (the true
  projection plus the lens's share of the bias, :mod:`tasks.vision.centre_bias`, which the pipeline
  removes again) plus white Gaussian noise of the detections' own RMS (same dots, same views):
  what a detector with independent errors and no other bias would give.

Below: the pooled m2/7 of both.

    python bench/detection_bias.py --seeds 10 67 161 --campaigns /work/scratch/full42/campaigns \\
        --results /work/scratch/full42/results2 [--detect]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from tasks.lake.store import read_table
from tasks.machine.camera_model import CameraModel
from tasks.machine.description import CALIBRATION_STAGE
from tasks.vision.centre_bias import rim_centre_bias
from tasks.vision.intrinsics_uncertainty import INTRINSIC_PARAMETERS, intrinsics_covariances, intrinsics_vector
from tasks.vision.pipeline import (
    calibrate_cameras,
    campaign_plates,
    detect_images,
    nominal_machine,
    plates_by_camera,
    with_detection_inputs,
)

CAMERA = "camera1"
CHECKED = [INTRINSIC_PARAMETERS.index(n) for n in ("f_px", "cx_px", "cy_px", "k1", "k2", "p1", "p2")]
POSE_COLUMNS = [f"T{i}{j}" for i in range(3) for j in range(4)]


def detected_dots(campaign: Path, results: Path, detect: bool) -> pd.DataFrame:
    """Camera 1's dots: the lake's, or detected again from its ingested images."""
    images = read_table("images", results, campaign.name)
    if not detect:
        dots = read_table("dots", results, campaign.name)
        return dots[dots.camera == CAMERA]
    meta = json.loads((campaign / "campaign.json").read_text())
    ours = images[(images.camera == CAMERA) & (images.status == "ok")].reset_index(drop=True)
    rows = with_detection_inputs(meta, ours)
    return detect_images(campaign, rows, campaign_plates(meta))[0]


def matched_truth(campaign: Path, dots: pd.DataFrame) -> pd.DataFrame:
    """``dots`` (finite centres) with the true projection nearest each (u_true, v_true px) and its
    plate row and column in the truth's numbering (row_true, col_true). A symmetric plate's grid
    may be numbered from another corner than the truth numbers it (a rigid relabelling)."""
    truth = pd.read_parquet(campaign / "truth" / "dots.parquet")
    by_image = {k: g for k, g in truth.groupby("image_id")}
    dots = dots[np.isfinite(dots.u_px) & np.isfinite(dots.v_px)]
    parts = []
    for image_id, g in dots.groupby("image_id", sort=False):
        t = by_image[image_id]
        tuv = t[["u_px", "v_px"]].to_numpy(float)
        nearest = cKDTree(tuv).query(g[["u_px", "v_px"]].to_numpy(float))[1]
        parts.append(g.assign(u_true=tuv[nearest, 0], v_true=tuv[nearest, 1], row_true=t["row"].to_numpy()[nearest],
                              col_true=t["col"].to_numpy()[nearest]))
    return pd.concat(parts, ignore_index=True)


def centre_errors(campaign: Path, dots: pd.DataFrame, images: pd.DataFrame) -> pd.DataFrame:
    """Per dot: stage, detected − true (du, dv px), the component along the image direction of
    increasing depth (along px) and the dot's depth offset from its view's mean (dz mm)."""
    meta = json.loads((campaign / "campaign.json").read_text())
    plates = campaign_plates(meta)
    poses = pd.read_parquet(campaign / "truth" / "images.parquet").set_index("image_id")
    stage = images.set_index("image_id")["stage"]
    d = matched_truth(campaign, dots)
    out = []
    for image_id, g in d.groupby("image_id"):
        name = meta["calibration_targets"][CAMERA] if stage[image_id] == CALIBRATION_STAGE else meta["views"][CAMERA]
        plate = plates[name]
        T = poses.loc[image_id, POSE_COLUMNS].to_numpy(float).reshape(3, 4)
        k = g["row_true"].to_numpy() * plate.cols + g["col_true"].to_numpy()
        z = (plate.dot_centres_mm()[k] @ T[:, :3].T + T[:, 3])[:, 2]
        uv = g[["u_true", "v_true"]].to_numpy(float)
        err = g[["u_px", "v_px"]].to_numpy(float) - uv
        grad = np.linalg.lstsq(np.c_[uv - uv.mean(axis=0), np.ones(len(uv))], z, rcond=None)[0][:2]
        n = grad / max(float(np.linalg.norm(grad)), 1e-30)
        out.append(pd.DataFrame({"stage": stage[image_id], "du": err[:, 0], "dv": err[:, 1], "along": err @ n,
                                 "dz": z - z.mean()}))
    return pd.concat(out, ignore_index=True)


def intrinsics_check(campaign: Path, dots: pd.DataFrame, images: pd.DataFrame) -> tuple[float, float]:
    """(m2, focal error ppm) of camera 1's pipeline self-calibration from ``dots`` against the truth."""
    meta = json.loads((campaign / "campaign.json").read_text())
    truth = json.loads((campaign / "truth" / "truth.json").read_text())["cameras"][CAMERA]
    true = CameraModel(**{**truth, "distortion": tuple(truth["distortion"])})
    _, models = calibrate_cameras(dots, images, meta)
    cam = {CAMERA: models[CAMERA]}
    cov = intrinsics_covariances(dots, images, cam, plates_by_camera(meta, CALIBRATION_STAGE), plates_by_camera(meta),
                                 nominal_machine(meta).linear_axes)[CAMERA][np.ix_(CHECKED, CHECKED)]
    err = (intrinsics_vector(models[CAMERA]) - intrinsics_vector(true))[CHECKED]
    return float(err @ np.linalg.solve(cov, err)), float(err[0] / intrinsics_vector(true)[0] * 1e6)


def with_true_centres(campaign: Path, dots: pd.DataFrame, images: pd.DataFrame, sigma_px: float,
                      seed: int) -> pd.DataFrame:
    """``dots`` (their numbering kept) with each centre replaced by what an exact ellipse fit with
    the detector's perspective correction gives on the true image (the true projection plus
    :func:`tasks.vision.centre_bias.rim_centre_bias` at the true intrinsics and pose: the part the
    pipeline removes again) plus N(0, sigma_px²) noise."""
    meta = json.loads((campaign / "campaign.json").read_text())
    plates = campaign_plates(meta)
    truth = json.loads((campaign / "truth" / "truth.json").read_text())["cameras"][CAMERA]
    true = CameraModel(**{**truth, "distortion": tuple(truth["distortion"])})
    poses = pd.read_parquet(campaign / "truth" / "images.parquet").set_index("image_id")
    stage = images.set_index("image_id")["stage"]
    d = matched_truth(campaign, dots)
    bias = np.zeros((len(d), 2))
    for image_id, rows in d.groupby("image_id", sort=False).indices.items():
        name = meta["calibration_targets"][CAMERA] if stage[image_id] == CALIBRATION_STAGE else meta["views"][CAMERA]
        plate = plates[name]
        T = np.eye(4)
        T[:3] = poses.loc[image_id, POSE_COLUMNS].to_numpy(float).reshape(3, 4)
        k = d["row_true"].to_numpy()[rows] * plate.cols + d["col_true"].to_numpy()[rows]
        found = np.zeros(plate.rows * plate.cols, bool)
        found[k] = True
        bias[rows] = rim_centre_bias(true, plate, T, found)[k]
    noise = np.random.default_rng(seed).normal(0.0, sigma_px, (len(d), 2))
    return d.assign(u_px=d.u_true + bias[:, 0] + noise[:, 0], v_px=d.v_true + bias[:, 1] + noise[:, 1])


def seed_row(campaign: Path, results: Path, detect: bool, seed: int) -> dict:
    images = read_table("images", results, campaign.name)
    dots = detected_dots(campaign, results, detect)
    errors = centre_errors(campaign, dots, images)
    row: dict = {"seed": seed}
    for stage, g in errors.groupby("stage"):
        row[f"rms_{stage}"] = float(np.sqrt(np.mean(np.r_[g.du, g.dv] ** 2)))
        row[f"slope_{stage}"] = 1e3 * float(np.polyfit(g.dz, g.along, 1)[0]) if g.dz.std() > 0.1 else np.nan
    row["m2"], row["df_ppm"] = intrinsics_check(campaign, dots, images)
    sigma = float(np.sqrt(np.mean(np.r_[errors.du, errors.dv] ** 2)))
    white = with_true_centres(campaign, dots, images, sigma, seed)
    row["m2_white"], row["df_white_ppm"] = intrinsics_check(campaign, white, images)
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seeds", type=int, nargs="+", required=True)
    p.add_argument("--campaigns", type=Path, required=True)
    p.add_argument("--results", type=Path, required=True)
    p.add_argument("--detect", action="store_true", help="detect camera 1's images again with the current detector")
    a = p.parse_args()
    rows = [seed_row(a.campaigns / f"s{s}", a.results, a.detect, s) for s in a.seeds]
    table = pd.DataFrame(rows)
    pd.set_option("display.width", 250)
    print(table.to_string(index=False, float_format=lambda v: f"{v:.4g}"))
    n = 7 * len(table)
    print(f"pooled m2/7: {table.m2.sum() / n:.2f} detected, {table.m2_white.sum() / n:.2f} true + white noise")


if __name__ == "__main__":
    main()

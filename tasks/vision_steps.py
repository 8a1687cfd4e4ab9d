"""Prefect task wrappers of the vision steps (detection, camera calibration, poses).

Every step is cached by the content of its inputs plus VISION_CODE_VERSION: detection chunks by
the images' content hashes (from ingest), the detector, the plate and the orientation priors;
calibration by the calibration views' dots; poses by the dots and the intrinsics. Changing the
error model later re-runs none of these.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd
from prefect import task
from prefect.cache_policies import NO_CACHE
from prefect.context import TaskRunContext

from tasks.camera_model import CameraModel
from tasks.plate import DotPlate
from tasks.results_lake import read_table, write_partition
from tasks.vision import calibrate_cameras, content_key, detect_images, plate_poses


def _detect_key(context: TaskRunContext, p: dict[str, Any]) -> str:
    rows = p["rows"][["image_id", "camera", "content_sha256", "rotation_deg"]].round({"rotation_deg": 6})
    plates = {c: pl.to_dict() for c, pl in p["plates"].items()}
    return "detect-" + content_key(rows, plates, p["detector"])


def _calibrate_key(context: TaskRunContext, p: dict[str, Any]) -> str:
    cal_ids = p["images"].loc[p["images"]["stage"] == "camera_calibration", "image_id"]
    dots = p["dots"][p["dots"]["image_id"].isin(cal_ids)]
    groups = p["images"][["image_id", "camera", "stage", "group"]]
    return "calibrate-" + content_key(dots, groups, p["metadata"]["cameras"], p["metadata"]["plates"])


def _poses_key(context: TaskRunContext, p: dict[str, Any]) -> str:
    cams = {c: m.to_dict() for c, m in p["cameras"].items()}
    plates = {c: pl.to_dict() for c, pl in p["plates"].items()}
    return "poses-" + content_key(p["dots"], p["detections"], cams, plates)


@task(name="read-images-table", cache_policy=NO_CACHE, persist_result=False)
def read_images(campaign_id: str, results_root: Path | None) -> pd.DataFrame:
    return read_table("images", results_root, campaign_id)


@task(name="detect-dots", cache_key_fn=_detect_key, persist_result=True)
def detect_chunk(folder: Path, rows: pd.DataFrame, plates: dict[str, DotPlate], detector: str):
    """Dots and per-image detection status of one chunk of images."""
    return detect_images(folder, rows, plates, detector)


@task(name="calibrate-cameras", cache_key_fn=_calibrate_key, persist_result=True)
def calibrate(dots: pd.DataFrame, images: pd.DataFrame, metadata: dict):
    """Camera self-calibration: Table 3 rows and the best intrinsics per camera."""
    return calibrate_cameras(dots, images, metadata)


@task(name="estimate-poses", cache_key_fn=_poses_key, persist_result=True)
def poses(dots: pd.DataFrame, detections: pd.DataFrame, cameras: dict[str, CameraModel],
          plates: dict[str, DotPlate]) -> pd.DataFrame:
    """PnP pose with covariance of every image."""
    return plate_poses(dots, detections, cameras, plates)


@task(name="write-table", cache_policy=NO_CACHE, persist_result=False)
def write_table(name: str, campaign_id: str, df: pd.DataFrame, provenance: dict, results_root: Path | None) -> Path:
    """Replace the campaign's partition of one result table (atomic)."""
    return write_partition(name, campaign_id, df, provenance, results_root)

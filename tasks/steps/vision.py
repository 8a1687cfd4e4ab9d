"""Prefect task wrappers of the vision steps (detection, camera calibration, poses).

Every step is cached by the content of its inputs plus VISION_CODE_VERSION: detection chunks by
the images' content hashes (from ingest), the detector, the plate and the orientation priors;
calibration by the calibration views' dots; poses by the dots and the intrinsics. Changing the
error model later re-runs none of these.

Calibration and poses run OpenCV and BLAS on one thread (:func:`one_numeric_thread`). OpenCV's
multi-threaded reductions (calibrateCamera, the PnP refinement) add in a varying order, so with
more threads two runs on the same dots differ in the last bits (focal lengths by ~1e-8 relative);
and BLAS (OpenBLAS of numpy and of OpenCV) gives results that depend on its thread count, which
differs between this process (one per core) and a Dask worker (one: Dask sets OMP_NUM_THREADS=1).
On one thread the results are the same bit for bit in every run and on every task runner, and on
2 cores not measurably slower.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import cv2
import pandas as pd
from prefect import task
from prefect.cache_policies import NO_CACHE
from prefect.context import TaskRunContext
from threadpoolctl import threadpool_limits

from tasks.lake.store import read_table
from tasks.machine.camera_model import CameraModel
from tasks.machine.plate import DotPlate
from tasks.vision.pipeline import (
    FIX_K3,
    POSES_VERSION,
    PRIOR_COLUMNS,
    SELF_CALIBRATION_STAGES,
    SELF_CALIBRATION_VERSION,
    calibrate_cameras,
    content_key,
    detect_images,
    plate_poses,
)

_numeric_lock = threading.Lock()
_numeric_users = 0
_numeric_restore: list = []  # while pinned: [OpenCV threads before, threadpoolctl limiter]


@contextmanager
def one_numeric_thread() -> Iterator[None]:
    """Run the block with OpenCV and BLAS on one thread each, then restore the process's settings.

    Both settings are process-wide: tasks running meanwhile in other threads also get one thread
    (slower, same results). Nested and concurrent uses restore only when the last one ends.
    """
    global _numeric_users
    with _numeric_lock:
        if _numeric_users == 0:
            _numeric_restore[:] = [cv2.getNumThreads(), threadpool_limits(limits=1)]
            cv2.setNumThreads(1)
        _numeric_users += 1
    try:
        yield
    finally:
        with _numeric_lock:
            _numeric_users -= 1
            if _numeric_users == 0:
                opencv_threads, blas = _numeric_restore
                blas.restore_original_limits()
                cv2.setNumThreads(opencv_threads)


def _detect_key(context: TaskRunContext, p: dict[str, Any]) -> str:
    prior = [c for c in PRIOR_COLUMNS if c in p["rows"].columns]
    rows = p["rows"][["image_id", "camera", "plate", "content_sha256", "rotation_deg", *prior]].round(
        {"rotation_deg": 6, **dict.fromkeys(prior, 9)})
    plates = {c: pl.to_dict() for c, pl in p["plates"].items()}
    return "detect-" + content_key(rows, plates, p["detector"])


def _calibrate_key(context: TaskRunContext, p: dict[str, Any]) -> str:
    cal_ids = p["images"].loc[p["images"]["stage"].isin(SELF_CALIBRATION_STAGES), "image_id"]
    dots = p["dots"][p["dots"]["image_id"].isin(cal_ids)]
    groups = p["images"][["image_id", "camera", "stage", "group"]]
    return "calibrate-" + content_key(dots, groups, p["metadata"]["cameras"], p["metadata"]["plates"],
                                      p["metadata"]["views"], p["metadata"].get("calibration_targets", {}),
                                      {"fix_k3": FIX_K3, "version": SELF_CALIBRATION_VERSION})


def _poses_key(context: TaskRunContext, p: dict[str, Any]) -> str:
    cams = {c: m.to_dict() for c, m in p["cameras"].items()}
    plates = {c: pl.to_dict() for c, pl in p["plates"].items()}
    return "poses-" + content_key(p["dots"], p["detections"], cams, plates, POSES_VERSION)


@task(name="read-images-table", cache_policy=NO_CACHE, persist_result=False)
def read_images(campaign_id: str, results_root: Path | None) -> pd.DataFrame:
    return read_table("images", results_root, campaign_id)


@task(name="detect-dots", cache_key_fn=_detect_key, persist_result=True)
def detect_chunk(folder: Path, rows: pd.DataFrame, plates: dict[str, DotPlate], detector: str):
    """Dots and per-image detection status of one chunk of images (rows carry the name of the plate
    each image shows; plates: {plate name: DotPlate})."""
    return detect_images(folder, rows, plates, detector)


@task(name="calibrate-cameras", cache_key_fn=_calibrate_key, persist_result=True)
def calibrate(dots: pd.DataFrame, images: pd.DataFrame, metadata: dict):
    """Camera self-calibration: Table 3 rows and the best intrinsics per camera (OpenCV and BLAS on one thread)."""
    with one_numeric_thread():
        return calibrate_cameras(dots, images, metadata)


@task(name="estimate-poses", cache_key_fn=_poses_key, persist_result=True)
def poses(dots: pd.DataFrame, detections: pd.DataFrame, cameras: dict[str, CameraModel],
          plates: dict[str, DotPlate]) -> pd.DataFrame:
    """PnP pose with covariance of every image (OpenCV and BLAS on one thread); plates: {plate name: DotPlate}."""
    with one_numeric_thread():
        return plate_poses(dots, detections, cameras, plates)

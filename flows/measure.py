"""Measure a campaign: ingest it, find the dot grids, self-calibrate the cameras and estimate the
plate pose of every image (§4.1, §5.2). Writes the ``dots``, ``camera_calibration`` and
``poses`` tables; every step is cached by the content of its inputs."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd
from prefect import flow, get_run_logger

from flows.ingest import ingest_campaign
from flows.runners import image_task_runner, subflow_task_runner
from tasks.campaign.ingest import load_campaign_metadata
from tasks.core.version import FIVECAL_VERSION
from tasks.lake.store import write_partitions
from tasks.steps.vision import calibrate, detect_chunk, poses, read_images
from tasks.vision.pipeline import (
    SELF_CALIBRATION_STAGES,
    campaign_plates,
    check_detections,
    content_key,
    detection_chunks,
    with_detection_inputs,
)

CHUNK_SIZE = 32


@flow(name="measure-campaign", task_runner=image_task_runner())
def measure_campaign(campaign: str, results_root: str | None = None, detector: str = "rrht",
                     chunk_size: int = CHUNK_SIZE) -> dict[str, Any]:
    """Ingest, detect, calibrate and estimate poses for the campaign folder ``campaign``.

    Returns a summary: counts of images, detections and poses, cached steps, table paths.
    """
    logger = get_run_logger()
    folder = Path(campaign).resolve()
    root = None if results_root is None else Path(results_root)
    ingest_summary = ingest_campaign.with_options(task_runner=subflow_task_runner())(str(folder), results_root)
    metadata = load_campaign_metadata(folder)
    campaign_id = metadata["campaign_id"]
    images = with_detection_inputs(metadata, read_images(campaign_id, root))
    plates = campaign_plates(metadata)

    chunks = detection_chunks(images, chunk_size)
    logger.info(f"detecting dots ({detector}) in {sum(map(len, chunks))} images, {len(chunks)} chunks")
    futures = [detect_chunk.submit(folder, rows, plates, detector) for rows in chunks]
    results = [f.result() for f in futures]
    cached = {"detect": sum(f.state.name == "Cached" for f in futures)}
    dots = pd.concat([r[0] for r in results], ignore_index=True)
    detections = pd.concat([r[1] for r in results], ignore_index=True)
    check_detections(folder, detections, plates)  # plates that are not the ones imaged: refused here

    # only the dots of the images the fit reads (and hashes for its cache key)
    calibration_ids = images.loc[images["stage"].isin(SELF_CALIBRATION_STAGES), "image_id"]
    cal_future = calibrate.submit(dots[dots["image_id"].isin(calibration_ids)], images, metadata)
    calibration, cameras = cal_future.result()
    cached["calibrate"] = int(cal_future.state.name == "Cached")
    missing = sorted(set(metadata["views"]) - set(cameras))
    if missing:
        logger.warning(f"no calibrated intrinsics for {missing}: their images get no pose")
    pose_future = poses.submit(dots, detections, cameras, plates)
    pose_table = pose_future.result()
    cached["poses"] = int(pose_future.state.name == "Cached")

    provenance = {"fivecal_version": FIVECAL_VERSION, "detector": detector,
                  "images_content_sha256": content_key(images[["image_id", "content_sha256"]]),
                  "campaign": str(folder)}
    # the step's three tables together: all replaced, or (an error before the swaps) none
    written = write_partitions({"dots": dots, "camera_calibration": calibration, "poses": pose_table}, campaign_id,
                               provenance, root)
    tables = {name: str(path) for name, path in written.items()}
    summary = {
        "campaign_id": campaign_id, "n_images": len(images), "n_ingested_ok": ingest_summary["n_ok"],
        "n_detected": int((detections["detection_status"] == "ok").sum()),
        "n_poses": int((pose_table["status"] == "ok").sum()), "cached": cached, "tables": tables,
    }
    logger.info(f"measured {campaign_id}: {summary['n_detected']}/{len(detections)} grids found, "
                f"{summary['n_poses']} poses; cached steps {cached}")
    return summary


def run_measure(campaign: str | Path, results_root: str | Path | None = None, detector: str = "rrht",
                dask_address: str | None = None, dask_workers: int | None = None) -> dict[str, Any]:
    """Entry point for the CLI: measure a campaign folder and return the flow's summary.

    dask_address, dask_workers: where the image work of ingest and measure runs (see
    flows.runners.image_task_runner); the flows themselves run in this process.
    """
    runner = image_task_runner(dask_address, dask_workers)
    return measure_campaign.with_options(task_runner=runner)(
        str(campaign), None if results_root is None else str(results_root), detector)

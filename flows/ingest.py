"""Ingest a measurement campaign: check the folder against its contract, check every image, and
write the ``images`` table of the results lake.

A campaign-level fault (no manifest, metadata that breaks its schema, a missing column, no usable
image, more faulty rows than tasks.campaign.ingest.MAX_FAULT_FRACTION) stops the flow before anything is
written. Image-level faults are recorded in the table, one status and
message per manifest row, and the rest goes on. Re-ingesting an unchanged campaign decodes no
image: the per-chunk checks are cached by file content.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from prefect import flow, get_run_logger

from flows.runners import image_task_runner
from tasks.campaign.ingest import CHUNK_SIZE, check_usable, format_summary, image_chunks, summarise
from tasks.steps.ingest import assemble_images_table, check_image_chunk, read_campaign, write_images_table

MAX_LOGGED_FAULTS = 20


@flow(name="ingest-campaign", task_runner=image_task_runner())
def ingest_campaign(campaign: str, results_root: str | None = None, chunk_size: int = CHUNK_SIZE) -> dict[str, Any]:
    """Ingest the campaign folder ``campaign`` into ``<results_root>/images/campaign_id=<id>/``.

    results_root: the lake's root; None means $FIVECAL_RESULTS_DIR or data/results.
    chunk_size: images per cached image-check task (the table does not depend on it).
    Returns the summary: campaign_id, n_images, n_ok, n_faults, by_status {status: count},
    chunks, chunks_cached (chunks whose image checks came from the cache), table (Parquet path).
    Raises tasks.campaign.ingest.CampaignError on a campaign-level fault (nothing written).
    """
    logger = get_run_logger()
    folder = Path(campaign).resolve()
    metadata, typed, faults = read_campaign(folder)
    chunks = image_chunks(typed, faults, chunk_size)
    logger.info(f"campaign {metadata['campaign_id']}: {len(typed)} manifest rows, checking images in "
                f"{len(chunks)} chunks")
    futures = [check_image_chunk.with_options(
                   task_run_name=f"check-images-rows-{rows['manifest_row'].iloc[0]}-{rows['manifest_row'].iloc[-1]}"
               ).submit(folder, rows) for rows in chunks]
    file_facts = [f.result() for f in futures]
    n_cached = sum(f.state.name == "Cached" for f in futures)
    images = assemble_images_table(metadata, typed, faults, file_facts)
    check_usable(folder, images)  # a campaign of mostly faults is refused before anything is written
    table = write_images_table(folder, images, None if results_root is None else Path(results_root))

    summary = summarise(images) | {"chunks": len(chunks), "chunks_cached": n_cached, "table": str(table)}
    for message in images.loc[images["status"] != "ok", "message"].head(MAX_LOGGED_FAULTS):
        logger.warning(message)
    if summary["n_faults"] > MAX_LOGGED_FAULTS:
        logger.warning(f"... and {summary['n_faults'] - MAX_LOGGED_FAULTS} more faults: see the status and "
                       f"message columns of {table}")
    logger.info(f"{format_summary(summary)}; image checks cached for {n_cached}/{len(chunks)} chunks; "
                f"images table written to {table}")
    return summary


def run_ingest(campaign: str | Path, results_root: str | Path | None = None, dask_address: str | None = None,
               dask_workers: int | None = None) -> dict[str, Any]:
    """Entry point for the CLI: run the flow on a campaign folder and return its summary.

    dask_address, dask_workers: where the image checks run (see flows.runners.image_task_runner).
    Raises tasks.campaign.ingest.CampaignError (message names the file) on a campaign-level fault.
    """
    runner = image_task_runner(dask_address, dask_workers)
    return ingest_campaign.with_options(task_runner=runner)(str(campaign),
                                                            None if results_root is None else str(results_root))

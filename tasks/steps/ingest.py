"""Prefect task wrappers of ingest (the only Prefect-aware module of ingest).

Caching: only the per-image work is cached. :func:`check_image_chunk` is keyed by
:func:`tasks.campaign.ingest.chunk_content_key` — the chunk's manifest row numbers and paths, the sha256 of
each file's bytes, the ingest CODE_VERSION and the OpenCV version — and its small result (one
row of file facts per image) is persisted in Prefect's result storage, so re-ingesting an
unchanged campaign, in a new run or process, hashes the files but decodes none (the task runs
end in state Cached). The key is computed from file contents, not size or mtime: a file
rewritten with the same size and a restored mtime still invalidates its chunk.
The other steps are cheap (or write) and are not cached.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pandas as pd
from prefect import task
from prefect.cache_policies import NO_CACHE
from prefect.context import TaskRunContext

from tasks.campaign.ingest import (
    build_images_table,
    check_image_files,
    chunk_content_key,
    ingest_provenance,
    read_checked_manifest,
)
from tasks.lake.store import write_partition

IMAGES_TABLE = "images"


def _chunk_cache_key(context: TaskRunContext, parameters: dict[str, Any]) -> str:
    """Prefect cache_key_fn of check_image_chunk: the content key of (folder, rows)."""
    return "ingest-chunk-" + chunk_content_key(parameters["folder"], parameters["rows"])


@task(name="read-campaign", cache_policy=NO_CACHE, persist_result=False)
def read_campaign(folder: Path) -> tuple[dict, pd.DataFrame, pd.DataFrame]:
    """Campaign-level validation (raises CampaignError, also when the manifest alone is mostly
    faults) and the vectorised manifest checks.

    Returns (metadata, typed manifest, manifest faults); see tasks.campaign.ingest.check_manifest.
    """
    return read_checked_manifest(folder)


@task(name="check-image-chunk", cache_key_fn=_chunk_cache_key, persist_result=True)
def check_image_chunk(folder: Path, rows: pd.DataFrame) -> pd.DataFrame:
    """Read, hash and decode the files of one chunk (rows: manifest_row, path); cached by content."""
    return check_image_files(folder, rows)


@task(name="build-images-table", cache_policy=NO_CACHE, persist_result=False)
def assemble_images_table(metadata: dict, typed: pd.DataFrame, faults: pd.DataFrame,
                          file_facts: list[pd.DataFrame]) -> pd.DataFrame:
    """The images table: manifest and file checks joined, with one status and message per row."""
    return build_images_table(metadata["campaign_id"], typed, faults, file_facts, metadata)


@task(name="write-images-table", cache_policy=NO_CACHE, persist_result=False)
def write_images_table(folder: Path, images: pd.DataFrame, results_root: Path | None) -> Path:
    """Replace the campaign's partition of the images table (atomic) with provenance."""
    campaign_id = str(images["campaign_id"].iloc[0])
    return write_partition(IMAGES_TABLE, campaign_id, images, ingest_provenance(folder, images), results_root)

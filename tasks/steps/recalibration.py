"""Prefect task wrappers of scheduled recalibration: scan the watched directory, and build the
drift report (lake ``drift`` table + ``reports/drift/<run>/``). Never cached: both read state
that changes between runs (the folder, the lake)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from prefect import task
from prefect.cache_policies import NO_CACHE

from tasks.analysis.drift import DriftTolerance, drift_table, verdict, verification_summary
from tasks.campaign.watch import CampaignEntry, Skipped, scan_watch_dir
from tasks.core.version import FIVECAL_VERSION
from tasks.lake.store import read_table, write_partition
from tasks.report.drift_report import DriftReportData, write_drift_report
from tasks.vision.pipeline import content_key

DRIFT_CODE_VERSION = "drift-1"


@task(name="scan-watch-dir", cache_policy=NO_CACHE, persist_result=False)
def scan_task(watch_dir: str) -> tuple[list[CampaignEntry], list[Skipped]]:
    """The readable campaign folders below ``watch_dir`` and the skipped ones with their reasons."""
    return scan_watch_dir(Path(watch_dir))


@task(name="drift-report", cache_policy=NO_CACHE, persist_result=False)
def drift_report_task(results_root: str | None, out_dir: str, tolerance: DriftTolerance, reference: str | None,
                      run: str) -> dict[str, Any]:
    """Drift of every calibrated campaign in the lake against the reference: writes one ``drift``
    partition per campaign and the report in ``out_dir``; returns paths, verdict and counts."""
    root = None if results_root is None else Path(results_root)
    pige, pdge, images = read_table("pige", root), read_table("pdge", root), read_table("images", root)
    drift = drift_table(pige, pdge, images, tolerance, reference)
    summary = verification_summary(read_table("verification", root), read_table("compensation", root))
    words = verdict(drift, summary, tolerance)
    provenance = {"fivecal_version": FIVECAL_VERSION, "drift_code": DRIFT_CODE_VERSION, "run": run,
                  "reference_campaign_id": words.reference_campaign_id, "tolerance": tolerance.to_dict(),
                  "inputs_sha256": content_key(pige, pdge, images[["campaign_id", "timestamp"]] if len(images) else [])}
    tables = {c: str(write_partition("drift", c, g, provenance, root))
              for c, g in drift.groupby("campaign_id", sort=False)}
    paths = write_drift_report(Path(out_dir), DriftReportData(run, drift, summary, tolerance, words, provenance))
    return {"report": str(paths["html"]), "markdown": str(paths["markdown"]), "tables": tables,
            "campaigns": list(tables), "needs_recompensation": words.needs_recompensation, "verdict": words.text(),
            "flagged": int(drift["flagged"].sum()) if len(drift) else 0}

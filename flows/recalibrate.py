"""Scheduled recalibration (issue 6, item 3): calibrate every new campaign dropped under a watched
directory, exactly once, then write the drift report across all campaigns of the lake.

One run ("tick"): scan the watched directory; log and skip folders that are incomplete, malformed
or still changing (retried next tick); for each campaign input not in the ledger, claim it, run the
``calibrate-campaign`` subflow and record it done; then, when anything was calibrated (or
``always_report``), write the ``drift`` table and ``<reports_root>/drift/<run>/``. Serve it on a
cron schedule with ``fivecal serve-recalibration`` (docs/recalibration.md).
"""


from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from prefect import flow, get_run_logger
from prefect.runtime import flow_run

from flows.calibrate import calibrate_campaign
from tasks.analysis.compensation import check_objective
from tasks.analysis.drift import DriftTolerance
from tasks.campaign.recalibration_ledger import Ledger
from tasks.campaign.watch import capture_arrived
from tasks.steps.recalibration import drift_report_task, scan_task

DEFAULT_SETTLE_S = 120.0


@flow(name="recalibrate-new-campaigns")
def recalibrate_new_campaigns(watch_dir: str, results_root: str | None = None, reports_root: str = "reports",
                              tolerance: DriftTolerance = DriftTolerance(),  # noqa: B008 (frozen, JSON-able)
                              reference: str | None = None, settle_seconds: float = DEFAULT_SETTLE_S,
                              detector: str = "rrht", always_report: bool = False,
                              orientation: str = "full", verification_repeats: int = 1) -> dict[str, Any]:
    """Calibrate the new campaigns under ``watch_dir`` and write the drift report.

    results_root: the lake (default data/results or $FIVECAL_RESULTS_DIR); the ledger lives in
    ``<results_root>/.recalibration/``. reports_root: calibration reports go to
    ``<reports_root>/<campaign_id>/<run>/``, the drift report to ``<reports_root>/drift/<run>/``.
    tolerance: drift tolerances (µm, arcsec, coverage factor k) and recompensation thresholds.
    reference: campaign_id the drift is measured from (default: the earliest). settle_seconds: a
    folder changed more recently than this is taken to be still copying and left for the next tick.
    orientation: the compensation objective of every calibration ("full" or "tool-axis",
    tasks.analysis.compensation.ORIENTATION_OBJECTIVES); the drift verdict judges the orientation it aims at.
    verification_repeats: images per compensated pose in each simulated verification capture
    (calibrate_campaign).
    A campaign calibrated while its verification capture was only requested (a lab's campaign,
    tasks.campaign.capture_request) is calibrated again on the first tick after the lab has written that
    capture (and left it alone for settle_seconds): everything but the capture comes from the cache.
    Returns calibrated/failed/waiting/skipped/awaiting_capture campaign lists and the drift report
    summary (or None).
    """
    check_objective(orientation)  # before any campaign is claimed
    logger = get_run_logger()
    ledger = Ledger.under(results_root)
    found, skipped = scan_task(watch_dir)
    for s in skipped:
        logger.warning(f"skipped {s.folder}: {s.reason} (looked at again next run)")
    new = [e for e in found if not ledger.is_done(e.campaign_id, e.input_sha256)]

    def capture_pending(e) -> bool:  # calibrated, and the lab has since written the verification capture
        return capture_arrived(ledger.record(e.campaign_id, e.input_sha256), settle_seconds)

    def capture_requested(e) -> bool:  # calibrated, its verification capture asked of the lab
        return (ledger.record(e.campaign_id, e.input_sha256) or {}).get("capture_state") == "requested"

    captured = [e for e in found if e not in new and capture_pending(e)]
    awaiting = [e for e in found if e not in new and e not in captured and capture_requested(e)]
    waiting = [e for e in new if e.quiet_s < settle_seconds]
    for e in waiting:
        logger.info(f"waiting for {e.folder}: changed {e.quiet_s:.0f} s ago (settle time {settle_seconds:g} s; "
                    "still being copied?)")
    ready = [e for e in new if e.quiet_s >= settle_seconds] + captured
    logger.info(f"{len(found)} campaign(s) under {watch_dir}: {len(found) - len(new)} already calibrated "
                f"({len(captured)} of them with a verification capture to measure now, {len(awaiting)} waiting for "
                f"one), {len(ready) - len(captured)} to calibrate, {len(waiting)} still changing, "
                f"{len(skipped)} folder(s) skipped")

    calibrated, failed = [], []
    for e in ready:
        with ledger.claim(e.campaign_id) as mine:
            if not mine or (ledger.is_done(e.campaign_id, e.input_sha256) and not capture_pending(e)):
                logger.info(f"{e.campaign_id}: calibrated or being calibrated by another run; skipped")
                continue
            if e.missing_images:
                logger.warning(f"{e.campaign_id}: {e.missing_images} image(s) of its manifest are missing; "
                               "ingest records them as faults")
            state = calibrate_campaign(e.folder, results_root, detector, reports_root, orientation=orientation,
                                       verification_repeats=verification_repeats,
                                       return_state=True)
            if not state.is_completed():
                logger.error(f"{e.campaign_id} ({e.folder}): calibration {state.name}: {state.message}; "
                             "retried next run")
                failed.append(e.campaign_id)
                continue
            summary = state.result()
            ledger.mark_done(e.campaign_id, e.input_sha256, {
                "folder": e.folder, "report": summary["report"], "recalibration_flow_run_id": str(flow_run.id),
                "capture": summary.get("capture"), "capture_state": summary.get("capture_state")})
            if summary.get("capture_state") == "requested":
                logger.warning(f"{e.campaign_id}: verification capture requested in {summary['capture']} "
                               "(capture_plan.csv); measured on the first tick after the lab has written it")
            calibrated.append(e.campaign_id)

    drift = None
    if calibrated or always_report:
        run = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ") + "-" + str(flow_run.id or "local")[:8]
        drift = drift_report_task(results_root, str(Path(reports_root) / "drift" / run), tolerance, reference, run)
        logger.info(f"drift report {drift['report']}: {drift['flagged']} flagged; "
                    f"{'recompensate' if drift['needs_recompensation'] else 'no recompensation needed'}")
    if failed:
        raise RuntimeError(f"calibration failed for {', '.join(failed)} (see the logs); retried next run")
    return {"calibrated": calibrated, "failed": failed, "waiting": [e.folder for e in waiting],
            "skipped": [{"folder": s.folder, "reason": s.reason} for s in skipped],
            "already_calibrated": [e.campaign_id for e in found if e not in new and e not in captured],
            "awaiting_capture": [e.campaign_id for e in found if capture_requested(e)],
            "drift": drift}

"""Calibrate a campaign (§3.3, §4.2, §5.2): measure it, extract the PDGEs, identify the PIGEs,
compensate the validation poses, verify them on a second capture and write the report.

Writes the ``pdge``, ``pige``, ``compensation``, ``verification``, ``formulations``, ``residuals``,
``residual_trends`` and ``diagnosis`` tables
and ``reports/<campaign_id>/<run>/``. Every stage is a cached task: re-running on an unchanged
campaign re-uses all of them.
"""

from __future__ import annotations

import os
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pandas as pd
from prefect import flow, get_run_logger
from prefect.task_runners import ThreadPoolTaskRunner

from flows.ingest import ingest_campaign
from flows.measure import measure_campaign
from flows.runners import image_task_runner
from tasks.analysis.compensation import check_objective, compensation_table, desired_tip_poses
from tasks.analysis.diagnosis.verdict import residual_follows_sentence
from tasks.analysis.model_ladder import append_step, compensated_tip_errors, ladder_step
from tasks.analysis.residual_trends import shared_deviations, trend_tests
from tasks.analysis.residuals import dot_residual_table, plates_of, pose_residual_table
from tasks.analysis.verification import (
    capture_errors,
    predicted_by,
    vbm_errors,
    verification_table,
    with_phase_columns,
)
from tasks.campaign.capture_request import (
    capture_rows,
    check_capture_commands,
    check_repeats,
    has_capture,
    planned_capture_context,
    repeats_key,
    write_capture_request,
)
from tasks.campaign.ingest import CampaignError, load_campaign_metadata
from tasks.core.version import FIVECAL_VERSION
from tasks.identification.measurements import assemble_measurements, capture_context
from tasks.identification.pige_identification import null_space_sentences
from tasks.identification.uncertainty import expected_tip_errors
from tasks.lake.store import partition_path, read_table, write_partitions
from tasks.machine.description import CALIBRATION_STAGE
from tasks.machine.effects import load_effect_modules, parse_effect
from tasks.machine.error_model import ErrorModel
from tasks.report import ReportData
from tasks.report.residual_figures import residual_report
from tasks.simulation.simulate import read_truth
from tasks.simulation.verification_capture import is_simulated, true_campaign_errors, true_capture_errors
from tasks.steps.calibration import (
    IDENTIFICATION_CODE_VERSION,
    capture_task,
    compensate_task,
    cross_validate_task,
    diagnose_task,
    formulations_task,
    identify_task,
    propagate_task,
    report_task,
)
from tasks.steps.vision import detect_chunk, poses
from tasks.vision.detector_comparison import intrinsics_from_table
from tasks.vision.pipeline import campaign_plates, content_key, nominal_machine, with_detection_inputs

VALIDATION_CAMERA = "camera1"


def _read_optional(table: str, root: Path | None, campaign_id: str) -> pd.DataFrame | None:
    try:
        return read_table(table, root, campaign_id)
    except (FileNotFoundError, OSError, ValueError):
        return None


def _measure_capture(folder: Path, results_root: str | None, cameras: dict, detector: str) -> pd.DataFrame:
    """Ingest the capture folder, detect its grids and estimate its poses with the campaign's intrinsics:
    the capture's poses table."""
    ingest_campaign(str(folder), results_root)
    metadata = load_campaign_metadata(folder)
    root = None if results_root is None else Path(results_root)
    images = with_detection_inputs(metadata, read_table("images", root, metadata["campaign_id"]))
    plates = campaign_plates(metadata)
    ok = images[images["status"] == "ok"]
    dots, detections = detect_chunk(folder, ok, plates, detector)
    table = poses(dots, detections, cameras, plates)
    return table


@flow(name="calibrate-campaign", task_runner=ThreadPoolTaskRunner(max_workers=os.cpu_count() or 2))
def calibrate_campaign(campaign: str, results_root: str | None = None, detector: str = "rrht",
                       reports_root: str = "reports", run: str | None = None, effects: list[str] | None = None,
                       effect_modules: list[str] | None = None, dask_address: str | None = None,
                       dask_workers: int | None = None, orientation: str = "full",
                       verification_repeats: int = 1) -> dict[str, Any]:
    """The whole calibration of the campaign folder ``campaign``; returns a summary with the report path
    and the verification capture's folder: measured, or (a lab's campaign whose capture is not
    there yet) requested, its images listed in the folder's capture_plan.csv (tasks.campaign.capture_request).

    dask_address, dask_workers: where the campaign's image work (ingest, detection, camera
    calibration, poses) runs (flows.runners.image_task_runner); the fit and the simulated
    verification capture run in this process.

    effects: effect specs (``family:key=value,...``) added to the model, their amplitudes fitted with
    the constant parameters (``fivecal calibrate --add-effect``). effect_modules: dotted module paths
    imported first, so that user-written effect families register themselves. Adding an effect re-runs
    the fit, its followers and the report; the image work is served from the cache.

    orientation: the compensation's orientation objective (``tasks.analysis.compensation.ORIENTATION_OBJECTIVES``:
    "full", the seed's whole tip rotation, or "tool-axis", the tool direction exactly); changing it
    re-runs the compensation, the verification capture and the report.

    verification_repeats: images of each compensated pose in the verification capture (passes
    over all the poses in turn); the VBM's after figures average them, and their noise floor falls
    as 1/√n. Changing it re-renders and re-measures the capture only."""
    check_objective(orientation)  # before the image work and the fit, not after them
    verification_repeats = check_repeats(verification_repeats)
    logger = get_run_logger()
    load_effect_modules(effect_modules or [])
    base = ErrorModel(effects=[parse_effect(s) for s in effects or []])
    folder = Path(campaign).resolve()
    root = None if results_root is None else Path(results_root)
    measure = measure_campaign.with_options(task_runner=image_task_runner(dask_address, dask_workers))
    measured = measure(str(folder), results_root, detector)
    metadata = load_campaign_metadata(folder)
    campaign_id = metadata["campaign_id"]
    machine = nominal_machine(metadata)
    images = read_table("images", root, campaign_id)
    pose_table = read_table("poses", root, campaign_id)
    calibration = read_table("camera_calibration", root, campaign_id)
    cameras = intrinsics_from_table(calibration, metadata)
    simulated = is_simulated(folder)
    # the truth is read only to express it in the fit's gauge and to report errors against it; its
    # user effects come from the modules recorded with it, which the analysis below does not see
    truth = read_truth(folder)[1] if simulated else None

    measurements = assemble_measurements(images, pose_table)
    if not len(measurements.stage("validation", camera=VALIDATION_CAMERA)):  # before minutes of fitting
        raise CampaignError(f"{folder}: no validation image of {VALIDATION_CAMERA} gave a pose (see the status "
                            "columns of the images and poses tables): calibrate needs at least one to compensate "
                            "and verify")
    logger.info(f"identifying: {len(measurements)} poses ({(measurements.table.stage == 'pige').sum()} five-axis)")
    ident = identify_task.submit(machine, measurements, truth, base)
    result = ident.result()
    fit = result.pige.fit
    logger.info(f"PIGE fit: {fit.iterations} LM iterations, σ² = {fit.sigma2:.3g}, "
                f"{int(fit.identifiable.sum())}/{fit.identifiable.size} parameters identifiable")

    dots = read_table("dots", root, campaign_id)
    logger.info("propagating the camera self-calibration and the pose noise into the parameters' uncertainty")
    prop_future = propagate_task.submit(machine, measurements, result, calibration, dots, images, cameras,
                                        plates_of(machine), plates_of(machine, CALIBRATION_STAGE))
    # (it runs beside the compensation and the capture)

    validation = measurements.stage("validation", camera=VALIDATION_CAMERA)
    ids = validation.table.image_id.tolist()
    commands = validation.commands
    # the context each compensated move will have in the capture: approach, time, temperature
    campaign_context = capture_context(images)
    planned = planned_capture_context(commands, campaign_context["time_s"].to_numpy(float),
                                      campaign_context["temperature_c"].to_numpy(float), verification_repeats)
    comp = compensate_task.submit(machine, result.model, commands, orientation, planned)
    compensation = comp.result()
    compensated = compensation.commands
    desired = desired_tip_poses(machine, commands)
    parts = {("before", "vbm"): (ids, vbm_errors(machine, result.model, desired, commands, validation.T,
                                                 validation.cov, VALIDATION_CAMERA).assign(repeats=1))}
    cached = {"measure": measured["cached"], "identify": ident.state.name == "Cached",
              "compensate": comp.state.name == "Cached"}
    capture_id = "compensated-" + content_key(compensated.round(9).tolist(), *repeats_key(verification_repeats))[:12]
    capture_folder = folder / "captures" / capture_id
    requested = capture_rows(ids, compensated, VALIDATION_CAMERA, verification_repeats)
    if simulated:
        logger.info(f"simulator renders the verification capture of {len(ids)} compensated poses, "
                    f"{verification_repeats} image(s) each")
        cap = capture_task.submit(folder, capture_folder, ids, compensated, verification_repeats)
        capture_folder = Path(cap.result())
        cached["capture"] = cap.state.name == "Cached"
        parts[("before", "truth")] = (ids, true_campaign_errors(folder, ids, commands, desired))
        parts[("after", "truth")] = (ids, true_capture_errors(folder, ids, compensated, desired, VALIDATION_CAMERA,
                                                              verification_repeats))
    if has_capture(capture_folder):
        check_capture_commands(capture_folder, requested)
        after = _measure_capture(capture_folder, results_root, cameras, detector)
        parts[("after", "vbm")] = capture_errors(machine, result.model, desired, compensated, ids, after,
                                                 VALIDATION_CAMERA)
        capture_state = "measured"
    else:
        plan = write_capture_request(folder, capture_folder, requested)
        capture_state = "requested"
        logger.warning(f"no verification capture yet: take the {len(requested)} images listed in {plan} (the "
                       f"compensated commands of the {len(ids)} validation poses), write them and manifest.csv "
                       f"into {capture_folder} (docs/campaign-format.md, captures/), then run calibrate again")
    propagated = prop_future.result()
    cached["propagate_uncertainty"] = prop_future.state.name == "Cached"
    # how far the model's own uncertainty lets the tip miss, per phase
    phase_commands = {"before": commands, "after": compensated}
    parts = with_phase_columns(parts, ids, phase_commands,
                               lambda c: expected_tip_errors(machine, result.model, propagated, c), "model_uncertainty")
    # what the identified model itself predicts, to set beside what was measured
    parts = with_phase_columns(parts, ids, phase_commands,
                               predicted_by(machine, result.model, desired,
                                            [(commands, validation.context), (compensated, planned)]),
                               "model_predicted")
    verification = verification_table(parts)
    formulations = formulations_task.submit(machine, result.model,
                                            measurements.stage("pige").commands).result()

    provenance = {"fivecal_version": FIVECAL_VERSION, "detector": detector, "campaign": str(folder),
                  "images_content_sha256": content_key(images[["image_id", "content_sha256"]]),
                  "identification_code": IDENTIFICATION_CODE_VERSION, "effects": [e.spec() for e in base.effects],
                  "orientation_objective": orientation, "verification_repeats": verification_repeats,
                  "effect_modules": list(effect_modules or [])}
    pdge_table, pige_table = result.pdge.table, result.pige_table(propagated)
    compensation_rows = compensation_table(ids, commands, compensation)
    # The step's tables are written together once all of them are computed (write_partitions):
    # an error anywhere before leaves every table of the campaign as it was.
    pending = {"pdge": pdge_table, "pige": pige_table, "compensation": compensation_rows,
               "verification": verification, "formulations": formulations}

    # where the model fails: residuals against everything they could depend on, and the ladder
    residuals = pose_residual_table(machine, result.model, measurements, dots)
    dot_residuals = dot_residual_table(dots, measurements, cameras, plates_of(machine))
    pending |= {"residuals": residuals, "dot_residuals": dot_residuals}
    cv = cross_validate_task.submit(machine, result.model, result.pige.specs, measurements)
    cv_rms = cv.result()
    cached["cross_validate"] = cv.state.name == "Cached"
    trends = trend_tests(residuals, shared_deviations(machine, result.model, propagated, measurements))
    pending["residual_trends"] = trends
    logger.info("diagnosis: scoring every catalogue effect the model lacks")
    diag_future = diagnose_task.submit(machine, measurements, result)
    diagnosis = diag_future.result()
    cached["diagnose"] = diag_future.state.name == "Cached"
    pending["diagnosis"] = diagnosis.table
    tables = {name: str(path) for name, path in write_partitions(pending, campaign_id, provenance, root).items()}
    ladder = append_step(campaign_id, ladder_step(machine, result.model, fit, measurements, cv_rms=cv_rms,
                                                  tip=compensated_tip_errors(verification)),
                         provenance, root)
    tables["model_ladder"] = str(partition_path("model_ladder", campaign_id, root))
    sections, figures = residual_report(residuals, dot_residuals, ladder, cameras=cameras, trends=trends,
                                        accepted=diagnosis.accepted)
    sentences = list(diagnosis.sentences)
    if diagnosis.best is None:  # no family explains it: say what the residual follows
        sentences += [s for s in [residual_follows_sentence(trends, VALIDATION_CAMERA)] if s]
    sections = [("What the model lacks (diagnosis)", "\n\n".join(sentences)), *sections]
    logger.info("diagnosis:\n" + "\n".join(sentences))

    run = run or datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    out_dir = Path(reports_root) / campaign_id / run
    data = ReportData(campaign_id=campaign_id, run=run, pdge=pdge_table, pige=pige_table,
                      verification=verification, camera_calibration=calibration,
                      detector_comparison=_read_optional("detector_comparison", root, campaign_id),
                      formulations=formulations, identifiability=null_space_sentences(result.pige.specs, fit),
                      provenance={**provenance, "tables": tables}, simulated=simulated,
                      images=images, compensation=compensation_rows,
                      extra_sections=sections, extra_figures=figures)
    paths = report_task(out_dir, data)
    summary_rows = verification.groupby(["phase", "source"])[["position_um", "orientation_arcsec",
                                                              "tool_direction_arcsec"]].mean()
    logger.info(f"verification means:\n{summary_rows.round(2).to_string()}")
    return {"campaign_id": campaign_id, "report": str(paths["html"]), "markdown": str(paths["markdown"]),
            "cv_rms": cv_rms, "effects": [e.spec() for e in result.model.effects],
            "diagnosis": sentences, "diagnosis_best": diagnosis.best,
            "tables": tables, "cached": cached, "sigma2": fit.sigma2,
            "capture": str(capture_folder), "capture_state": capture_state,
            "verification_means": summary_rows.reset_index().to_dict("records")}  # unrounded: no double rounding

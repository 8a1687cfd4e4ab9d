"""Calibrate a campaign (§3.3, §4.2, §5.2): measure it, extract the PDGEs, identify the PIGEs,
compensate the validation poses, verify them on a second capture and write the report.

Writes the ``pdge``, ``pige``, ``compensation``, ``verification``, ``formulations``, ``residuals``,
``residual_trends`` and ``diagnosis`` tables
and ``reports/<campaign_id>/<run>/``. Every stage is a cached task: re-running on an unchanged
campaign re-uses all of them.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import pandas as pd
from prefect import flow, get_run_logger
from prefect.futures import PrefectFuture as Future
from prefect.task_runners import ThreadPoolTaskRunner

from flows.ingest import ingest_campaign
from flows.measure import measure_campaign
from flows.runners import image_task_runner
from tasks.analysis.compensation import check_objective, compensation_table, desired_tip_poses
from tasks.analysis.diagnosis.diagnose import Diagnosis
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
from tasks.identification.measurements import Measurements, assemble_measurements, capture_context
from tasks.identification.pige_identification import CalibrationResult
from tasks.identification.uncertainty import expected_tip_errors
from tasks.lake.store import partition_path, read_table, write_partitions
from tasks.machine.description import CALIBRATION_STAGE, Machine
from tasks.machine.effects import load_effect_modules, parse_effect
from tasks.machine.error_model import ErrorModel
from tasks.report.calibration_report import WhereTheModelFails, calibration_report_data, diagnosis_sentences
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


@dataclass
class MeasuredCampaign:
    """A measured campaign as the fit reads it: its folder, lake tables, machine and cameras."""

    folder: Path
    root: Path | None
    campaign_id: str
    machine: Machine
    images: pd.DataFrame
    calibration: pd.DataFrame          # the camera_calibration table
    cameras: dict                      # {camera: CameraModel} from that table
    dots: pd.DataFrame
    measurements: Measurements
    simulated: bool
    truth: ErrorModel | None           # the simulator's model (simulated campaigns only)


@dataclass
class Verification:
    """The compensation of the validation poses and its verification (before/after, VBM and truth)."""

    table: pd.DataFrame                # the verification table
    compensation: pd.DataFrame         # the compensation table
    capture_folder: Path
    capture_state: str                 # "measured" or "requested"


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
    return poses(dots, detections, cameras, plates)


def read_measured_campaign(folder: Path, results_root: str | None) -> MeasuredCampaign:
    """The lake tables measure wrote for ``folder``, assembled into the fit's measurements; refuses a
    campaign whose validation poses all failed (before minutes of fitting)."""
    root = None if results_root is None else Path(results_root)
    metadata = load_campaign_metadata(folder)
    campaign_id = metadata["campaign_id"]
    images = read_table("images", root, campaign_id)
    calibration = read_table("camera_calibration", root, campaign_id)
    simulated = is_simulated(folder)
    measurements = assemble_measurements(images, read_table("poses", root, campaign_id))
    if not len(measurements.stage("validation", camera=VALIDATION_CAMERA)):
        raise CampaignError(f"{folder}: no validation image of {VALIDATION_CAMERA} gave a pose (see the status "
                            "columns of the images and poses tables): calibrate needs at least one to compensate "
                            "and verify")
    # the truth is read only to express it in the fit's gauge and to report errors against it; its
    # user effects come from the modules recorded with it, which the analysis does not see
    return MeasuredCampaign(folder, root, campaign_id, nominal_machine(metadata), images, calibration,
                            intrinsics_from_table(calibration, metadata), read_table("dots", root, campaign_id),
                            measurements, simulated, read_truth(folder)[1] if simulated else None)


def verify_compensation(c: MeasuredCampaign, result: CalibrationResult, propagated: Future, orientation: str,
                        verification_repeats: int, results_root: str | None, detector: str,
                        cached: dict) -> Verification:
    """Compensate the validation poses, take (simulated) or request (a lab's) the verification capture
    and tabulate the tip errors before and after: VBM, truth, the model's uncertainty and prediction."""
    logger = get_run_logger()
    validation = c.measurements.stage("validation", camera=VALIDATION_CAMERA)
    ids, commands = validation.table.image_id.tolist(), validation.commands
    # the context each compensated move will have in the capture: approach, time, temperature
    context = capture_context(c.images)
    planned = planned_capture_context(commands, context["time_s"].to_numpy(float),
                                      context["temperature_c"].to_numpy(float), verification_repeats)
    comp = compensate_task.submit(c.machine, result.model, commands, orientation, planned)
    compensation = comp.result()
    cached["compensate"] = comp.state.name == "Cached"
    compensated = compensation.commands
    desired = desired_tip_poses(c.machine, commands)
    parts = {("before", "vbm"): (ids, vbm_errors(c.machine, result.model, desired, commands, validation.T,
                                                 validation.cov, VALIDATION_CAMERA).assign(repeats=1))}
    capture_id = "compensated-" + content_key(compensated.round(9).tolist(), *repeats_key(verification_repeats))[:12]
    capture_folder = c.folder / "captures" / capture_id
    requested = capture_rows(ids, compensated, VALIDATION_CAMERA, verification_repeats)
    if c.simulated:
        logger.info(f"simulator renders the verification capture of {len(ids)} compensated poses, "
                    f"{verification_repeats} image(s) each")
        cap = capture_task.submit(c.folder, capture_folder, ids, compensated, verification_repeats)
        capture_folder = Path(cap.result())
        cached["capture"] = cap.state.name == "Cached"
        parts[("before", "truth")] = (ids, true_campaign_errors(c.folder, ids, commands, desired))
        parts[("after", "truth")] = (ids, true_capture_errors(c.folder, ids, compensated, desired, VALIDATION_CAMERA,
                                                              verification_repeats))
    if has_capture(capture_folder):
        check_capture_commands(capture_folder, requested)
        after = _measure_capture(capture_folder, results_root, c.cameras, detector)
        parts[("after", "vbm")] = capture_errors(c.machine, result.model, desired, compensated, ids, after,
                                                 VALIDATION_CAMERA)
        capture_state = "measured"
    else:
        plan = write_capture_request(c.folder, capture_folder, requested)
        capture_state = "requested"
        logger.warning(f"no verification capture yet: take the {len(requested)} images listed in {plan} (the "
                       f"compensated commands of the {len(ids)} validation poses), write them and manifest.csv "
                       f"into {capture_folder} (docs/campaign-format.md, captures/), then run calibrate again")
    uncertainty = propagated.result()
    cached["propagate_uncertainty"] = propagated.state.name == "Cached"
    phase_commands = {"before": commands, "after": compensated}
    # how far the model's own uncertainty lets the tip miss, and what the model itself predicts
    parts = with_phase_columns(parts, ids, phase_commands,
                               lambda cmd: expected_tip_errors(c.machine, result.model, uncertainty, cmd),
                               "model_uncertainty")
    parts = with_phase_columns(parts, ids, phase_commands,
                               predicted_by(c.machine, result.model, desired,
                                            [(commands, validation.context), (compensated, planned)]),
                               "model_predicted")
    return Verification(verification_table(parts), compensation_table(ids, commands, compensation), capture_folder,
                        capture_state)


def where_the_model_fails(c: MeasuredCampaign, result: CalibrationResult, uncertainty,
                          cached: dict) -> tuple[dict[str, pd.DataFrame], Diagnosis, float]:
    """Residuals against everything they could depend on, their trend tests, the cross-validated
    RMS and the diagnosis: ({table: frame}, diagnosis, cv_rms)."""
    residuals = pose_residual_table(c.machine, result.model, c.measurements, c.dots)
    tables = {"residuals": residuals,
              "dot_residuals": dot_residual_table(c.dots, c.measurements, c.cameras, plates_of(c.machine)),
              "residual_trends": trend_tests(residuals, shared_deviations(c.machine, result.model, uncertainty,
                                                                          c.measurements))}
    cv = cross_validate_task.submit(c.machine, result.model, result.pige.specs, c.measurements)
    cv_rms = cv.result()  # before the diagnosis starts: each sets the BLAS threads for its own process
    cached["cross_validate"] = cv.state.name == "Cached"
    get_run_logger().info("diagnosis: scoring every catalogue effect the model lacks")
    diag = diagnose_task.submit(c.machine, c.measurements, result)
    diagnosis = diag.result()
    cached["diagnose"] = diag.state.name == "Cached"
    tables["diagnosis"] = diagnosis.table
    return tables, diagnosis, cv_rms


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
    measure = measure_campaign.with_options(task_runner=image_task_runner(dask_address, dask_workers))
    measured = measure(str(folder), results_root, detector)
    c = read_measured_campaign(folder, results_root)
    cached = {"measure": measured["cached"]}

    logger.info(f"identifying: {len(c.measurements)} poses ({(c.measurements.table.stage == 'pige').sum()} five-axis)")
    ident = identify_task.submit(c.machine, c.measurements, c.truth, base)
    result = ident.result()
    cached["identify"] = ident.state.name == "Cached"
    fit = result.pige.fit
    logger.info(f"PIGE fit: {fit.iterations} LM iterations, σ² = {fit.sigma2:.3g}, "
                f"{int(fit.identifiable.sum())}/{fit.identifiable.size} parameters identifiable")
    logger.info("propagating the camera self-calibration and the pose noise into the parameters' uncertainty")
    propagated = propagate_task.submit(c.machine, c.measurements, result, c.calibration, c.dots, c.images, c.cameras,
                                       plates_of(c.machine), plates_of(c.machine, CALIBRATION_STAGE))
    verified = verify_compensation(c, result, propagated, orientation, verification_repeats, results_root, detector,
                                   cached)
    formulations = formulations_task.submit(c.machine, result.model, c.measurements.stage("pige").commands).result()
    uncertainty = propagated.result()
    failures, diagnosis, cv_rms = where_the_model_fails(c, result, uncertainty, cached)

    provenance = {"fivecal_version": FIVECAL_VERSION, "detector": detector, "campaign": str(folder),
                  "images_content_sha256": content_key(c.images[["image_id", "content_sha256"]]),
                  "identification_code": IDENTIFICATION_CODE_VERSION, "effects": [e.spec() for e in base.effects],
                  "orientation_objective": orientation, "verification_repeats": verification_repeats,
                  "effect_modules": list(effect_modules or [])}
    pige_table = result.pige_table(uncertainty)
    # The step's tables are written together once all of them are computed (write_partitions):
    # an error anywhere before leaves every table of the campaign as it was.
    pending = {"pdge": result.pdge.table, "pige": pige_table, "compensation": verified.compensation,
               "verification": verified.table, "formulations": formulations, **failures}
    tables = {name: str(path) for name, path in write_partitions(pending, c.campaign_id, provenance, c.root).items()}
    ladder = append_step(c.campaign_id, ladder_step(c.machine, result.model, fit, c.measurements, cv_rms=cv_rms,
                                                    tip=compensated_tip_errors(verified.table)),
                         provenance, c.root)
    tables["model_ladder"] = str(partition_path("model_ladder", c.campaign_id, c.root))

    run = run or datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    sentences = diagnosis_sentences(diagnosis, failures["residual_trends"], VALIDATION_CAMERA)
    account = WhereTheModelFails(failures["residuals"], failures["dot_residuals"], failures["residual_trends"],
                                 ladder, diagnosis, sentences)
    data = calibration_report_data(c.campaign_id, run, result, pige_table, verified.table, verified.compensation,
                                   formulations, c.calibration, _read_optional("detector_comparison", c.root,
                                                                               c.campaign_id),
                                   c.images, account, c.cameras, {**provenance, "tables": tables}, c.simulated)
    paths = report_task(Path(reports_root) / c.campaign_id / run, data)
    logger.info("diagnosis:\n" + "\n".join(sentences))
    means = verified.table.groupby(["phase", "source"])[["position_um", "orientation_arcsec",
                                                         "tool_direction_arcsec"]].mean()
    logger.info(f"verification means:\n{means.round(2).to_string()}")
    return {"campaign_id": c.campaign_id, "report": str(paths["html"]), "markdown": str(paths["markdown"]),
            "cv_rms": cv_rms, "effects": [e.spec() for e in result.model.effects],
            "diagnosis": sentences, "diagnosis_best": diagnosis.best,
            "tables": tables, "cached": cached, "sigma2": fit.sigma2,
            "capture": str(verified.capture_folder), "capture_state": verified.capture_state,
            "verification_means": means.reset_index().to_dict("records")}  # unrounded: no double rounding

"""The dispensing test (§4.3, §5.3), after ``calibrate``: see the tip, and close the calibration on it.

Workpieces of ring targets on the C table; the machine dispenses a dot at every ring of one with the
nominal commands and of a second one with the compensated ones (one capture, two phases), camera 1
images every ring, the §4.3 inspection measures each dot's offset from its ring, and the offsets of
both phases fix the tip's constant offset in the tool frame (tasks.dispensing.tip). The offset is
folded into the identified model as its ``tool_offset`` effect and everything is compensated again: the
``check`` phase dispenses a fresh workpiece with it, and the validation poses are compensated with
it (the ``verification`` table's phase ``after_tip``).

For a simulated campaign the simulator dispenses and renders; for a lab's campaign the flow writes
``dispense_plan.csv`` into the capture folder and measures the images on the next run
(docs/dispensing-test.md). Writes the ``dispense_inspection`` table, the ``verification`` table's
after_tip rows and ``<reports>/<campaign_id>/<run>/dispensing/``.
"""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from prefect import flow, get_run_logger

from flows.lake_calibration import calibration_from_lake
from tasks.analysis.compensation import desired_tip_poses
from tasks.analysis.residuals import plates_of
from tasks.analysis.verification import PHASE_QUANTITIES, modelled_errors, predicted_by, verification_table
from tasks.core.version import FIVECAL_VERSION
from tasks.dispensing.capture import CAMERA, plan_rows, write_plan
from tasks.dispensing.inspection import load_config
from tasks.dispensing.measure import dispense_rows, load_capture_manifest
from tasks.dispensing.tip import constant_tool_frame_error, fit_tip_offset
from tasks.dispensing.tip_uncertainty import AfterTipUncertainty, after_tip_uncertainty
from tasks.dispensing.workpiece import Workpiece, imaging_commands, ring_layout
from tasks.lake.store import read_provenance, read_table, write_partition
from tasks.machine.description import CALIBRATION_STAGE, COMMAND_COLUMNS
from tasks.report.dispensing_test import write_dispensing_report
from tasks.steps.calibration import compensate_task, propagate_task
from tasks.steps.dispensing import DISPENSE_CODE_VERSION, dispense_capture_task, inspect_task
from tasks.vision.pipeline import content_key

PHASES = ("nominal", "compensated", "check")


def _truth_columns(folder: Path) -> pd.DataFrame | None:
    path = folder / "truth" / "dots.csv"
    return pd.read_csv(path) if path.is_file() else None


def _capture(folder: Path, campaign: Path, rows: pd.DataFrame, workpiece: Workpiece, seed: int, simulated: bool,
             config, logger) -> tuple | None:
    """(manifest, inspected rows, truth rows or None) of a capture folder, after the simulator rendered
    it (simulated) or the lab wrote it; None (and the request written) when the lab has not yet."""
    if simulated:
        folder = Path(dispense_capture_task(campaign, folder, rows, workpiece, seed))
    elif not (folder / "manifest.csv").is_file():
        plan = write_plan(folder, rows)
        logger.warning(f"dispensing capture requested: dispense one dot and take one image per row "
                       f"({len(rows)} rows) of {plan}, write images/ and manifest.csv into {folder} "
                       f"(docs/dispensing-test.md), then run dispense-test again")
        return None
    inspected = inspect_task(folder, config)
    manifest = load_capture_manifest(folder)
    return manifest, inspected, _truth_columns(folder)


def _table_rows(parts, machine, model, camera) -> pd.DataFrame:
    frames = []
    for manifest, inspected, truth in parts:
        rows = dispense_rows(manifest, inspected, machine, model, camera)
        if truth is not None:
            rows = rows.merge(truth.drop(columns=["truth_nsd_r"], errors="ignore"), on="image_id", how="left")
        else:
            rows = rows.assign(truth_dx_um=np.nan, truth_dy_um=np.nan, truth_diameter_mm=np.nan, truth_defect=None)
        frames.append(rows.drop(columns=["roi_x0", "roi_y0", "binning"], errors="ignore"))
    return pd.concat(frames, ignore_index=True)


def _fit_rows(rows: pd.DataFrame) -> pd.DataFrame:
    ok = rows["qualified"] & np.isfinite(rows["dx_um"]) & np.isfinite(rows["dy_um"])
    return rows[ok]


def plan_first_capture(lake, workpiece: Workpiece, seed: int, orientation: str) -> tuple[dict, dict, pd.DataFrame]:
    """The nominal and the compensated phase on two workpieces drawn apart over the five-axis poses'
    range: ({phase: layout}, {phase: imaging commands}, the capture's rows)."""
    machine = lake.machine
    five_axis = lake.measurements.stage("pige").commands
    ranges = np.column_stack([five_axis.min(axis=0), five_axis.max(axis=0)])
    layouts = {"nominal": ring_layout(machine, workpiece, ranges, seed),
               "compensated": ring_layout(machine, workpiece, ranges, seed + 1)}
    imaging = {k: imaging_commands(machine, v.centres, v.surface_z_mm, CAMERA) for k, v in layouts.items()}
    dispensed = {"nominal": layouts["nominal"].commands,
                 "compensated": compensate_task.submit(machine, lake.model, layouts["compensated"].commands,
                                                       orientation).result().commands}
    rows = pd.concat([plan_rows(k, layouts[k].centres, layouts[k].surface_z_mm, dispensed[k], imaging[k])
                      for k in ("nominal", "compensated")], ignore_index=True)
    return layouts, imaging, rows


def fit_tip(rows: pd.DataFrame, machine, model):
    """The tip's constant tool-frame offset from the qualified dots of the nominal and compensated
    phases (:func:`tasks.dispensing.tip.fit_tip_offset`): (the fit, the dispensed commands (M, 5) of
    the dots it used)."""
    on = _fit_rows(rows[rows["phase"].isin(["nominal", "compensated"])])
    commands = on[list(COMMAND_COLUMNS)].to_numpy(float)
    fit = fit_tip_offset(machine, model, commands,
                         on[["ring_x_mm", "ring_y_mm"]].to_numpy(float), on[["dx_um", "dy_um"]].to_numpy(float) * 1e-3)
    get_run_logger().info(
        f"tip offset (tool frame) from {fit.dots} dots: "
        + ", ".join(f"{v:+.2f} ± {u:.2f}" for v, u in zip(fit.offset_um, fit.uncertainty_um, strict=True))
        + f" µm; tool-axis error ∝ sin A {fit.tilt_um:+.2f} ± {fit.tilt_uncertainty_um:.2f} µm; dot residual "
        f"rms {fit.residual_rms_um:.2f} µm")
    return fit, commands


def after_tip_model_uncertainty(lake, root: Path | None, fit, fit_commands: np.ndarray,
                                after_tip: np.ndarray) -> AfterTipUncertainty:
    """The model uncertainty of the tip after the tip fit at the validation poses compensated with
    it, ``after_tip`` (N, 5) (:func:`tasks.dispensing.tip_uncertainty.after_tip_uncertainty`): the
    propagation of calibrate's uncertainty (its cached task, same inputs), with the constant
    tool-frame part replaced by what the fit at ``fit_commands`` leaves."""
    machine = lake.machine
    images = read_table("images", root, lake.campaign_id)
    propagated = propagate_task.submit(machine, lake.measurements, lake.result,
                                       read_table("camera_calibration", root, lake.campaign_id),
                                       read_table("dots", root, lake.campaign_id), images, lake.cameras,
                                       plates_of(machine), plates_of(machine, CALIBRATION_STAGE)).result()
    return after_tip_uncertainty(machine, lake.model, propagated, fit_commands, fit.covariance_um2, after_tip)


def verification_with_tip(lake, root: Path | None, fit, fit_commands: np.ndarray,
                          orientation: str) -> tuple[pd.DataFrame, dict, dict | None]:
    """The campaign's verification table with, for a simulated campaign, the true errors of the
    held-out poses compensated with the tip folded in (phase ``after_tip``) and the model
    uncertainty there (:func:`after_tip_model_uncertainty`); that uncertainty's summary (any
    campaign: its mean over the poses, its parts and the covariance of its constant tool-frame
    part, µm); and the truth's summary of the constant tool-frame error before and after the tip
    fit (None for a lab's campaign)."""
    machine, model, truth = lake.machine, lake.model, lake.truth
    verification = read_table("verification", root, lake.campaign_id)
    verification = verification[verification["phase"] != "after_tip"].drop(columns="campaign_id", errors="ignore")
    validation = lake.measurements.stage("validation", camera=CAMERA)
    ids, commands = validation.table.image_id.tolist(), validation.commands
    after_tip = compensate_task.submit(machine, fit.model, commands, orientation).result().commands
    stated = after_tip_model_uncertainty(lake, root, fit, fit_commands, after_tip)
    uncertainty = stated.norms()
    u_summary = {"model_uncertainty_after_tip_um": float(uncertainty[0].mean()),
                 "model_uncertainty_after_tip_parts_um": stated.position_parts_um(),
                 "after_tip_constant_covariance_um2": stated.constant_covariance_um2.tolist()}
    if not lake.simulated:
        return verification, u_summary, None
    desired = desired_tip_poses(machine, commands)
    errors = modelled_errors(machine, truth, desired, after_tip)
    predicted = predicted_by(machine, fit.model, desired)(after_tip)
    errors = errors.assign(**{f"model_uncertainty_{q}": v for q, v in zip(PHASE_QUANTITIES, uncertainty, strict=True)},
                           **{f"model_predicted_{q}": v for q, v in zip(PHASE_QUANTITIES, predicted, strict=True)})
    verification = pd.concat([verification, verification_table({("after_tip", "truth"): (ids, errors)})],
                             ignore_index=True)
    compensated = compensate_task.submit(machine, model, commands, orientation).result().commands
    return verification, u_summary, {
        "constant_before_um": constant_tool_frame_error(machine, truth, desired, compensated).tolist(),
        "constant_after_tip_um": constant_tool_frame_error(machine, truth, desired, after_tip).tolist(),
        "position_after_um": float(modelled_errors(machine, truth, desired, compensated)["position_um"].mean()),
        "position_after_tip_um": float(errors["position_um"].mean()),
    }


@flow(name="dispense-test")
def dispense_test(campaign: str, results_root: str | None = None, reports_root: str = "reports",
                  run: str | None = None, inspection_config: str | None = None,
                  workpiece: Workpiece = Workpiece(),  # noqa: B008 (frozen)
                  effect_modules: list[str] | None = None) -> dict[str, Any]:
    """The dispensing test of a calibrated campaign; returns a summary (tip offset ± u, capture
    states, tables, report; for simulated campaigns the true constant tool-frame error before and
    after the tip fit). Reads the tables ``calibrate`` wrote (images, poses, camera_calibration, pige's
    provenance) and re-uses its cached identification. effect_modules: the user modules defining the
    families of the effects the calibration added (``--effect-module``); by default the ones the
    calibration recorded."""
    logger = get_run_logger()
    config = load_config(inspection_config)
    folder = Path(campaign).resolve()
    root = None if results_root is None else Path(results_root)
    lake = calibration_from_lake(folder, root, effect_modules)  # calibrate's identification, cached
    orientation = lake.provenance.get("orientation_objective", "full")
    seed = int(lake.truth_doc["seed"]) if lake.simulated else int(content_key(lake.campaign_id)[:8], 16)
    full_camera = lake.full_resolution_camera(CAMERA)
    summary: dict[str, Any] = {"campaign_id": lake.campaign_id, "captures": {}, "tables": {}}

    layouts, imaging, first_rows = plan_first_capture(lake, workpiece, seed, orientation)
    key = content_key(DISPENSE_CODE_VERSION, first_rows.round(9), workpiece.to_dict())[:12]
    first = _capture(folder / "captures" / f"dispense-{key}", folder, first_rows, workpiece, seed, lake.simulated,
                     config, logger)
    summary["captures"]["dispense"] = "requested" if first is None else "measured"
    if first is None:
        return summary
    fit, fit_commands = fit_tip(_table_rows([first], lake.machine, lake.model, full_camera), lake.machine,
                                lake.model)

    # a fresh copy of the compensated phase's workpiece, dispensed with the tip folded in
    check_layout = layouts["compensated"]
    check_cmd = compensate_task.submit(lake.machine, fit.model, check_layout.commands, orientation).result().commands
    check_rows = plan_rows("check", check_layout.centres, check_layout.surface_z_mm, check_cmd,
                           imaging["compensated"])
    check_key = content_key(DISPENSE_CODE_VERSION, check_rows.round(9), workpiece.to_dict())[:12]
    check = _capture(folder / "captures" / f"dispense-check-{check_key}", folder, check_rows, workpiece, seed + 1,
                     lake.simulated, config, logger)
    summary["captures"]["check"] = "requested" if check is None else "measured"
    rows = _table_rows([first] if check is None else [first, check], lake.machine, lake.model, full_camera)

    verification, u_summary, truth_summary = verification_with_tip(lake, root, fit, fit_commands, orientation)
    summary.update(u_summary)
    if truth_summary is not None:
        summary["truth"] = truth_summary
    calib_prov = lake.provenance
    provenance = {"fivecal_version": FIVECAL_VERSION, "campaign": str(folder),
                  "dispense_code": DISPENSE_CODE_VERSION,
                  "workpiece": workpiece.to_dict(), "inspection": config.__dict__,
                  "tip_offset_um": fit.offset_um.tolist(), "tip_offset_uncertainty_um": fit.uncertainty_um.tolist(),
                  "tip_fit_dots": fit.dots, "tip_fit_residual_rms_um": fit.residual_rms_um,
                  "tip_tilt_um": fit.tilt_um, "tip_tilt_uncertainty_um": fit.tilt_uncertainty_um,
                  "calibration": {k: calib_prov.get(k) for k in ("effects", "effect_modules", "orientation_objective",
                                                                  "identification_code")},
                  "effect_modules": list(effect_modules or [])}
    summary["tables"]["dispense_inspection"] = str(write_partition("dispense_inspection", lake.campaign_id, rows,
                                                                   provenance, root))
    ver_prov = {**read_provenance("verification", lake.campaign_id, root), "after_tip": provenance}
    for k in ("table", "campaign_id", "schema_version"):
        ver_prov.pop(k, None)
    summary["tables"]["verification"] = str(write_partition("verification", lake.campaign_id, verification,
                                                            ver_prov, root))

    run = run or datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    out_dir = Path(reports_root) / lake.campaign_id / run / "dispensing"
    summary.update(tip_offset_um=fit.offset_um.tolist(), tip_offset_uncertainty_um=fit.uncertainty_um.tolist(),
                   tip_fit_dots=fit.dots, tip_fit_residual_rms_um=fit.residual_rms_um,
                   tip_tilt_um=fit.tilt_um, tip_tilt_uncertainty_um=fit.tilt_uncertainty_um,
                   report=str(write_dispensing_report(out_dir, rows, verification, fit, summary, lake.simulated,
                                                     config.__dict__)))
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary

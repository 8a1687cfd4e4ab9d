"""Prefect task wrappers of the calibration stages (identification, compensation, verification,
formulation comparison, report).

Cache keys are the content of the inputs plus IDENTIFICATION_CODE_VERSION (bump it when the
science of these stages changes: Prefect's TASK_SOURCE would only see these thin wrappers).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from prefect import task
from prefect.cache_policies import NO_CACHE

from tasks.analysis.compensation import Compensation, compensate
from tasks.analysis.diagnosis.diagnose import DIAGNOSIS_CODE_VERSION
from tasks.campaign.capture_request import repeats_key
from tasks.identification.calibration import calibrate
from tasks.identification.measurements import Measurements, assemble_measurements
from tasks.identification.pige_identification import CalibrationResult
from tasks.identification.uncertainty import NOISE_DRAWS, PropagatedUncertainty, propagate_uncertainty
from tasks.machine.context import PoseContext
from tasks.machine.description import Machine
from tasks.machine.effects import EFFECTS
from tasks.machine.error_model import ErrorModel
from tasks.machine.formulations import compare_formulations
from tasks.simulation.verification_capture import simulate_capture
from tasks.vision.intrinsics_uncertainty import intrinsics_covariances, pose_sensitivities
from tasks.vision.pipeline import content_key

# identification-7 was taken by an uncommitted experiment (GCV_gamma, 2026-11-22) whose results sit
# in local Prefect caches: never reuse a version an experiment ran under (give experiments a suffix)
IDENTIFICATION_CODE_VERSION = "identification-23"


def _key(prefix: str, *parts) -> str:
    return f"{prefix}-" + content_key(IDENTIFICATION_CODE_VERSION, *parts)


def _measurements_key(m: Measurements) -> tuple:
    """What a Measurements' content is: its table and its measured poses."""
    return m.table, pd.DataFrame(m.T.reshape(len(m), -1))


def _truth_key(truth: ErrorModel | None):
    return None if truth is None else truth.to_dict()


@task(name="assemble-measurements", cache_policy=NO_CACHE, persist_result=False)
def measurements_task(images: pd.DataFrame, poses: pd.DataFrame) -> Measurements:
    return assemble_measurements(images, poses)


@task(name="identify", persist_result=True,
      cache_key_fn=lambda c, p: _key("identify", *_measurements_key(p["measurements"]),
                                     p["machine"].source, _truth_key(p["truth"]),
                                     None if p["base"] is None else p["base"].to_dict()))
def identify_task(machine: Machine, measurements: Measurements, truth: ErrorModel | None,
                  base: ErrorModel | None = None) -> CalibrationResult:
    """PDGE extraction (eqs. 13–19) and PIGE identification (eq. 22)."""
    return calibrate(machine, measurements, truth, base=base)


@task(name="propagate-uncertainty", persist_result=True,
      cache_key_fn=lambda c, p: _key("uncertainty", p["result"].model.to_dict(), *_measurements_key(p["measurements"]),
                                     p["calibration"], p["machine"].source, p["draws"]))
def propagate_task(machine: Machine, measurements: Measurements, result: CalibrationResult, calibration: pd.DataFrame,
                   dots: pd.DataFrame, images: pd.DataFrame, cameras: dict, plates: dict, targets: dict,
                   draws: int = NOISE_DRAWS) -> PropagatedUncertainty:
    """What the camera self-calibration and the pose noise through the PDGE extraction add to the
    identified parameters' uncertainty (:mod:`tasks.identification.uncertainty`), added effects'
    parameters included. calibration: the ``camera_calibration`` table
    (the intrinsics; its content keys the cache). dots, images: the lake tables the intrinsics'
    covariance and the poses' sensitivities are computed from. plates: {camera: the plate it measures};
    targets: {camera: the plate of its self-calibration views}."""
    covs = intrinsics_covariances(dots, images, cameras, targets, plates, machine.linear_axes)
    sens = pose_sensitivities(dots, measurements.table["image_id"].tolist(), measurements.T, cameras, plates,
                              measurements.table["camera"].tolist())
    return propagate_uncertainty(machine, result, measurements, sens, covs, draws=draws)


def _context_key(context: PoseContext | None, model: ErrorModel):
    """A context's content for a cache key, when ``model`` has effects (only they read it); nothing
    otherwise, so that the keys of models without effects stay as they were whatever the context."""
    if context is None or not model.effects:
        return []
    return [np.column_stack([context.approach, context.time_s, context.temperature_c]).round(9).tolist()]


@task(name="compensate", persist_result=True,
      cache_key_fn=lambda c, p: _key("compensate", p["model"].to_dict(), p["commands"].tolist(),
                                     p["machine"].source, p.get("orientation", "full"),
                                     *_context_key(p.get("context"), p["model"])))
def compensate_task(machine: Machine, model: ErrorModel, commands: np.ndarray, orientation: str = "full",
                    context: PoseContext | None = None) -> Compensation:
    """Compensated commands of the validation poses by inverse kinematics of the identified model,
    under the orientation objective ``orientation``, in the ``context`` the moves will have
    (tasks.analysis.compensation)."""
    return compensate(machine, model, commands, orientation, context)


@task(name="simulate-verification-capture", persist_result=True,
      cache_key_fn=lambda c, p: _key("capture", str(p["campaign_folder"]), str(p["out_folder"]),
                                     list(p["image_ids"]), np.round(p["commands"], 9).tolist(),
                                     *repeats_key(p.get("repeats", 1))))
def capture_task(campaign_folder: Path, out_folder: Path, image_ids: list[str], commands: np.ndarray,
                 repeats: int = 1) -> str:
    """The simulator renders the follow-up capture at the compensated commands, ``repeats`` images
    per pose."""
    return str(simulate_capture(campaign_folder, out_folder, image_ids, commands, repeats=repeats))


@task(name="formulation-comparison", persist_result=True,
      cache_key_fn=lambda c, p: _key("formulations", p["model"].to_dict(), p["commands"].tolist()))
def formulations_task(machine: Machine, model: ErrorModel, commands: np.ndarray) -> pd.DataFrame:
    """Table 5: local PoE vs Denavit–Hartenberg vs global PoE on the identified model."""
    return compare_formulations(machine, model, commands)


@task(name="cross-validate", persist_result=True,
      cache_key_fn=lambda c, p: _key("cv", p["model"].to_dict(), [s.name for s in p["specs"]],
                                     *_measurements_key(p["measurements"]),
                                     p["machine"].source))
def cross_validate_task(machine: Machine, model: ErrorModel, specs: list, measurements: Measurements) -> float:
    """Cross-validated RMS of the whitened five-axis residuals.

    See :func:`tasks.analysis.model_ladder.refit_cross_validated_rms`.
    """
    from tasks.analysis.model_ladder import refit_cross_validated_rms

    return refit_cross_validated_rms(machine, model, specs, measurements)


@task(name="diagnose", persist_result=True,
      cache_key_fn=lambda c, p: _key("diagnose", DIAGNOSIS_CODE_VERSION, p["result"].model.to_dict(),
                                     *_measurements_key(p["measurements"]), p["machine"].source, sorted(EFFECTS)))
def diagnose_task(machine: Machine, measurements: Measurements, result: CalibrationResult):
    """Which catalogue effect the model lacks (:func:`tasks.analysis.diagnosis.diagnose.diagnose`)."""
    from tasks.analysis.diagnosis.diagnose import diagnose

    return diagnose(machine, measurements, result)


@task(name="write-report", cache_policy=NO_CACHE, persist_result=False)
def report_task(out_dir: Path, data: Any) -> dict[str, Path]:
    from tasks.report import write_report

    return write_report(out_dir, data)

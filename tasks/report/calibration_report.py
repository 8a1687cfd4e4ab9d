"""The calibration report of one run, built from the run's results (the flow only hands them over)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import pandas as pd

from tasks.analysis.diagnosis.diagnose import Diagnosis
from tasks.analysis.diagnosis.verdict import residual_follows_sentence
from tasks.identification.pige_identification import CalibrationResult, null_space_sentences
from tasks.machine.camera_model import CameraModel
from tasks.report.data import ReportData
from tasks.report.residual_figures import residual_report

DIAGNOSIS_TITLE = "What the model lacks (diagnosis)"


@dataclass
class WhereTheModelFails:
    """The run's account of its residuals: the tables the residual section reads."""

    residuals: pd.DataFrame       # the residuals table (pose residuals with their variables)
    dot_residuals: pd.DataFrame   # the dot_residuals table
    trends: pd.DataFrame          # the residual_trends table
    ladder: pd.DataFrame          # the campaign's model_ladder table, this run's step included
    diagnosis: Diagnosis
    sentences: list[str]          # the diagnosis in words (:func:`diagnosis_sentences`)


def diagnosis_sentences(diagnosis: Diagnosis, trends: pd.DataFrame, camera: str) -> list[str]:
    """The diagnosis in words; when no family explains the residuals, what ``camera``'s residual
    follows (:func:`tasks.analysis.diagnosis.verdict.residual_follows_sentence`)."""
    sentences = list(diagnosis.sentences)
    if diagnosis.best is None:
        sentences += [s for s in [residual_follows_sentence(trends, camera)] if s]
    return sentences


def calibration_report_data(campaign_id: str, run: str, result: CalibrationResult, pige_table: pd.DataFrame,
                            verification: pd.DataFrame, compensation: pd.DataFrame, formulations: pd.DataFrame,
                            camera_calibration: pd.DataFrame, detector_comparison: pd.DataFrame | None,
                            images: pd.DataFrame, failures: WhereTheModelFails, cameras: Mapping[str, CameraModel],
                            provenance: dict, simulated: bool) -> ReportData:
    """Everything the report of a calibration run shows (:func:`tasks.report.render.write_report`).

    ``pige_table``: the identified constants with their propagated uncertainty; ``provenance``: the
    run's parameters and the paths of the tables it wrote."""
    sections, figures = residual_report(failures.residuals, failures.dot_residuals, failures.ladder, cameras=cameras,
                                        trends=failures.trends, accepted=failures.diagnosis.accepted)
    return ReportData(campaign_id=campaign_id, run=run, pdge=result.pdge.table, pige=pige_table,
                      verification=verification, camera_calibration=camera_calibration,
                      detector_comparison=detector_comparison, formulations=formulations,
                      identifiability=null_space_sentences(result.pige.specs, result.pige.fit),
                      provenance=provenance, simulated=simulated, images=images, compensation=compensation,
                      extra_sections=[(DIAGNOSIS_TITLE, "\n\n".join(failures.sentences)), *sections],
                      extra_figures=figures)

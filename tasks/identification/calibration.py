"""The calibration of a campaign's measured poses: PDGE profiles and constant parameters (§3.3, §4.2).

The alternation of PDGE extraction and the constant-parameter fit
(:func:`tasks.identification.pige_identification.alternate`) gives the start; profiles and constants are
then refined in one least squares (:mod:`tasks.identification.joint_fit`). A model with effects is
calibrated with their parameters fitted too (:mod:`tasks.identification.effect_fit`).
"""

from __future__ import annotations

from tasks.identification.effect_fit import calibrate_with_effects
from tasks.identification.joint_fit import joint_refine
from tasks.identification.measurements import Measurements
from tasks.identification.parameters import ParamSpec
from tasks.identification.pige_identification import (
    IDENTIFICATION_CAMERA,
    IDENTIFICATION_STAGES,
    JOINT_START_ROUNDS,
    CalibrationResult,
    alternate,
    synthetic_measurements,
)
from tasks.machine.description import Machine
from tasks.machine.error_model import ErrorModel


def calibrate(machine: Machine, measurements: Measurements, truth: ErrorModel | None = None,
              specs: list[ParamSpec] | None = None, base: ErrorModel | None = None) -> CalibrationResult:
    """PDGEs from the sweeps, then the constant parameters over the ``pige`` stage (camera 1),
    alternated; then profiles and constants in one least squares over the sweeps and the five-axis
    poses (:mod:`tasks.identification.joint_fit`).

    base: a starting model whose effects (and anything else) are kept; its PDGE profiles are
    replaced by the extracted ones. When it holds effects, their amplitudes (and phases) are fitted
    too, the PDGEs re-extracted with them (:func:`tasks.identification.effect_fit.calibrate_with_effects`).
    truth: the simulator's model, to express it in the same gauge.
    """
    base = base or ErrorModel()
    if base.effects:
        return calibrate_with_effects(machine, measurements, base, truth, specs)
    poses = measurements.stage(*IDENTIFICATION_STAGES, camera=IDENTIFICATION_CAMERA)
    pdge, fit, extraction = alternate(machine, base, measurements, poses, specs, truth, rounds=JOINT_START_ROUNDS)
    pdge, fit, _ = joint_refine(machine, base, measurements, poses, pdge, fit)
    truth_fit = None
    if truth is not None:
        clean = synthetic_measurements(machine, truth, measurements)
        clean_poses = clean.stage(*IDENTIFICATION_STAGES, camera=IDENTIFICATION_CAMERA)
        # the same estimator on exact poses: the noisy fit's smoothers (exact repeats have no variance)
        clean_pdge, truth_fit, _ = alternate(machine, base, clean, clean_poses, specs, rounds=JOINT_START_ROUNDS,
                                             smoothing=pdge.smoothing)
        _, truth_fit, _ = joint_refine(machine, base, clean, clean_poses, clean_pdge, truth_fit, penalty_of=pdge)
    return CalibrationResult(pdge, fit, truth_fit, truth, extraction_model=extraction, joint=True)

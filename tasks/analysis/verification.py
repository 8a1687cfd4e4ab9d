"""Tip errors before and after compensation, as the vision system measures them and as they are.

As the VBM measures: the tip pose in the workpiece frame follows from the measured plate pose
T_cam_plate and the tip's pose in the camera frame (the identified hand–eye relation):
T_plate_tip = T_cam_plate⁻¹ · T_cam_tip. The error is against the desired (nominal) tip pose.
Its measurement noise is propagated from the pose covariance: a plate-frame error (v, ω) moves the
tip by −(v + ω × p_tip), so the noise floor of a pose is sqrt(tr Σ_p) for position and
sqrt(tr Σ_ω) for orientation (the expected error norm if the machine were perfect), and
sqrt(tr P Σ_ω P), P = I − z zᵀ, for the tool direction (z: the tool axis).

Beside the whole orientation error, each row has the tool-direction error: the angle between the
reached and the desired tool axis (tip frame z), the part of the orientation error that five axes
can remove (docs/calibrate.md, step 6).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from tasks.campaign.folder import validation_id_of
from tasks.core import se3
from tasks.core.units import ARCSEC
from tasks.machine.context import PoseContext
from tasks.machine.description import Machine
from tasks.machine.error_model import ErrorModel
from tasks.machine.kinematics import forward, tip_pose_error
from tasks.vision.poses import covariances_from_table, mean_poses, poses_from_table


def measured_tip_poses(machine: Machine, model: ErrorModel, commands: np.ndarray, T_cam_plate: np.ndarray,
                       camera: str) -> np.ndarray:
    """(N, 4, 4) tip poses in the plate (workpiece) frame from measured plate poses (mm)."""
    cam_tip = forward(machine, commands, model).relative(machine.tip, camera)
    return se3.inverse(T_cam_plate) @ cam_tip


def noise_floor(tip_in_plate: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Expected tip error norms (µm, arcsec) from the pose covariances alone: (N,), (N,)."""
    p = tip_in_plate[:, :3, 3]
    A = np.concatenate([np.broadcast_to(np.eye(3), (len(p), 3, 3)), -se3.skew(p)], axis=2)  # v + ω×p = v − p̂ ω
    cov_p = A @ cov @ np.swapaxes(A, 1, 2)
    pos = np.sqrt(np.trace(cov_p, axis1=1, axis2=2)) * 1e3
    ori = np.sqrt(np.trace(cov[:, 3:, 3:], axis1=1, axis2=2)) / ARCSEC
    return pos, ori


def tool_direction_error(measured: np.ndarray, desired: np.ndarray) -> np.ndarray:
    """(N,) angle (arcsec) between the tool axes (tip frame z) of the measured and desired tip
    poses (N, 4, 4), any common frame."""
    a, b = measured[:, :3, 2], desired[:, :3, 2]
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1)) / ARCSEC


def tip_errors_with_tool_direction(measured: np.ndarray, desired: np.ndarray) -> pd.DataFrame:
    """:func:`tasks.machine.kinematics.tip_pose_error` with the column tool_direction_arcsec after
    orientation_arcsec (workpiece frame, mm in, µm and arcsec out)."""
    out = tip_pose_error(measured, desired)
    out.insert(2, "tool_direction_arcsec", tool_direction_error(measured, desired))
    return out


def tool_direction_noise_floor(tip_in_plate: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """(N,) expected tool-direction error (arcsec) from the pose covariances (N, 6, 6) alone: the
    plate-frame tilt noise across the tool axis of each tip pose (N, 4, 4)."""
    z = tip_in_plate[:, :3, 2]
    across = np.eye(3) - z[:, :, None] * z[:, None, :]
    return np.sqrt(np.trace(across @ cov[:, 3:, 3:] @ across, axis1=1, axis2=2)) / ARCSEC


def vbm_errors(machine: Machine, model: ErrorModel, desired: np.ndarray, commands: np.ndarray,
               T_cam_plate: np.ndarray, cov: np.ndarray, camera: str) -> pd.DataFrame:
    """Tip errors as measured (rows of :func:`tip_errors_with_tool_direction` plus noise_floor_* columns)."""
    tips = measured_tip_poses(machine, model, commands, T_cam_plate, camera)
    out = tip_errors_with_tool_direction(tips, desired)
    out["noise_floor_position_um"], out["noise_floor_orientation_arcsec"] = noise_floor(tips, cov)
    out["noise_floor_tool_direction_arcsec"] = tool_direction_noise_floor(tips, cov)
    return out


def capture_errors(machine: Machine, model: ErrorModel, desired: np.ndarray, commands: np.ndarray, image_ids,
                   capture: pd.DataFrame, camera: str) -> tuple[list[str], pd.DataFrame]:
    """VBM tip errors of a follow-up capture whose images :func:`capture_image_id` re-measure the
    validation poses ``image_ids`` (desired tip poses (N, 4, 4), commands (N, 5) in their order).

    capture: poses rows (image_id, status, T.., cov..). The ok images of a pose are averaged
    (:func:`tasks.vision.poses.mean_poses`), so its noise floor falls as 1/√n; the column ``repeats``
    says how many. Poses with no ok image are left out. Returns (the validation image_ids kept,
    their errors)."""
    ok = capture[capture["status"] == "ok"]
    index = {v: i for i, v in enumerate(image_ids)}
    group = np.array([index.get(validation_id_of(c), -1) for c in ok["image_id"]], dtype=int)
    ok, group = ok[group >= 0], group[group >= 0]
    T, cov, count = mean_poses(poses_from_table(ok), covariances_from_table(ok), group, len(image_ids))
    keep = count > 0
    kept = [i for i, k in zip(image_ids, keep, strict=True) if k]
    errors = vbm_errors(machine, model, desired[keep], commands[keep], T[keep], cov[keep], camera)
    return kept, errors.assign(repeats=count[keep])


def modelled_errors(machine: Machine, model: ErrorModel, desired: np.ndarray, commands: np.ndarray,
                    context: PoseContext | None = None) -> pd.DataFrame:
    """Tip errors (µm, arcsec; rows of :func:`tip_errors_with_tool_direction`) that the machine
    described by ``model`` makes at ``commands`` (N, 5) against ``desired`` (N, 4, 4), workpiece frame:
    with the simulator's truth, the true errors; with the identified model, what it predicts.
    context: the approach directions, times and temperatures of the moves (None: neutral, which
    leaves out every effect that depends on them)."""
    return tip_errors_with_tool_direction(forward(machine, commands, model, context).tool_in_workpiece(), desired)


Parts = dict[tuple[str, str], tuple[list[str], pd.DataFrame]]
"""{(phase, source): (validation image_ids, their tip errors)}: the pieces of the verification table."""

PHASE_QUANTITIES = ("position_um", "orientation_arcsec", "tool_direction_arcsec")


def with_phase_columns(parts: Parts, image_ids: list[str], commands: dict[str, np.ndarray], compute,
                       prefix: str) -> Parts:
    """``parts`` of :func:`verification_table` with the columns ``<prefix>_position_um``,
    ``<prefix>_orientation_arcsec`` and ``<prefix>_tool_direction_arcsec`` that depend on the phase's
    commands only, the same for every source: ``compute(commands)`` -> (µm (N,), arcsec (N,),
    arcsec (N,)) at each phase's commands ({phase: (N, 5)} in the order of ``image_ids``), kept for the
    image_ids of each part. Used for the model uncertainty
    (:func:`tasks.identification.uncertainty.expected_tip_errors`, prefix ``model_uncertainty``) and
    for the identified model's own prediction (:func:`predicted_by`, prefix ``model_predicted``)."""
    per_phase = {phase: compute(c) for phase, c in commands.items()}
    out = {}
    for (phase, source), (ids, df) in parts.items():
        keep = np.isin(image_ids, ids)
        values = per_phase[phase]
        out[(phase, source)] = (ids, df.assign(**{f"{prefix}_{q}": v[keep]
                                                  for q, v in zip(PHASE_QUANTITIES, values, strict=True)}))
    return out


def predicted_by(machine: Machine, model: ErrorModel, desired: np.ndarray,
                 contexts: list[tuple[np.ndarray, PoseContext]] | None = None):
    """``compute`` for :func:`with_phase_columns`: the tip error norms (µm, arcsec, arcsec) that
    ``model`` predicts at a phase's commands against ``desired``. After a ``full`` compensation the
    orientation it predicts is what A and C cannot turn (tasks.analysis.compensation).
    contexts: (commands, their context) pairs: a phase whose commands are one of them is predicted
    in that context (neutral otherwise)."""
    def compute(commands: np.ndarray):
        context = next((c for cmd, c in contexts or [] if cmd is commands), None)
        errors = modelled_errors(machine, model, desired, commands, context)
        return tuple(errors[q].to_numpy() for q in PHASE_QUANTITIES)
    return compute


def verification_table(parts: Parts) -> pd.DataFrame:
    """Stack {(phase, source): (validation image_ids, errors)} into the ``verification`` lake table."""
    frames = []
    for (phase, source), (image_ids, df) in parts.items():
        f = df.copy()
        f.insert(0, "source", source)
        f.insert(0, "phase", phase)
        f.insert(0, "pose", np.arange(len(f)))
        f.insert(0, "image_id", list(image_ids))
        frames.append(f)
    return pd.concat(frames, ignore_index=True)

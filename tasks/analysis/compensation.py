"""Compensation by inverse kinematics of the identified model (§5.2).

The desired tip pose of a command is where the *nominal* machine would put the tool. The
compensated command is the one at which the *identified* machine puts it there. X/Y/Z place the
tip; A and C turn the tool about two directions only, A's axis and C's axis as A tilts it. The
rotation about the third direction, perpendicular to both, is one no command can make: in the tip
frame of the prototype it is cos A·y + sin A·z, a tilt of the tool near A = 0. What compensation
does with the orientation is the orientation objective:

* ``full`` (the default): the tip exactly (X/Y/Z); A and C minimise the whole rotation angle, as the
  seed's orientation error counts it. With a perfect model what is left is the error's component
  along that third direction: 42–43″ mean on the prototype's validation poses, mostly a tilt of the
  tool (docs/calibrate.md, "The targets").
* ``tool-axis``: the tip and the tool direction exactly; the rotation about the tool axis is left
  free, which a round dispensing needle does not see. Correcting a tilt ε along the third direction
  takes a turn of C of about ε / sin A, which spins the tool about its axis by about ε·cos A / sin A:
  near A ≈ 0 tens of degrees. A pose whose solution does not converge or leaves an axis' stroke
  keeps its ``full`` compensation, and the table says so.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from tasks.machine.context import PoseContext
from tasks.machine.description import AXIS_ORDER, Machine
from tasks.machine.error_model import ErrorModel
from tasks.machine.inverse_kinematics import inverse
from tasks.machine.kinematics import forward

ORIENTATION_OBJECTIVES = {
    "full": "the whole tip rotation, the rotation about the tool axis included (the seed's metric)",
    "tool-axis": "the tool direction exactly, the rotation about the tool axis left free",
}
SPIN_WEIGHT = 1.0  # full: rotation about the tool axis weighs like a tilt: the whole angle is minimised
ORIENTATION_WEIGHT_MM = 1.0  # mm per rad: orientation settles among A and C, X/Y/Z place the tip
CONVERGED_MM = 1e-7  # tool-axis: largest |target − reached| (mm, and rad × ORIENTATION_WEIGHT_MM) accepted


@dataclass(frozen=True)
class Compensation:
    """Compensated commands (N, 5) (mm, deg) and, per pose, the objective they meet (a key of
    :data:`ORIENTATION_OBJECTIVES`, or ``full`` with the reason the requested one was not met)."""

    commands: np.ndarray
    objective: list[str]


def check_objective(orientation: str) -> str:
    """``orientation`` if it is a key of :data:`ORIENTATION_OBJECTIVES`; ValueError naming the choices."""
    if orientation not in ORIENTATION_OBJECTIVES:
        raise ValueError(f"unknown orientation objective {orientation!r}: choose one of "
                         f"{', '.join(ORIENTATION_OBJECTIVES)}")
    return orientation


def requested_objective(pose_objectives) -> str:
    """The objective a compensation was asked for, from its per-pose labels (:attr:`Compensation.objective`,
    the ``compensation`` table's ``orientation_objective``): "full" when every pose says exactly that,
    "tool-axis" otherwise (a pose that fell back from tool-axis says so in its label)."""
    return "full" if all(str(o) == "full" for o in pose_objectives) else "tool-axis"


def desired_tip_poses(machine: Machine, commands: np.ndarray) -> np.ndarray:
    """(N, 4, 4) tip poses in the workpiece frame (mm) that the nominal machine reaches at ``commands``."""
    return forward(machine, commands).tool_in_workpiece()


def compensate(machine: Machine, model: ErrorModel, commands: np.ndarray, orientation: str = "full",
               context: PoseContext | None = None) -> Compensation:
    """Compensated commands (mm, deg) reaching the nominal tip poses of ``commands`` (N, 5) on
    ``model``, under the orientation objective ``orientation`` (see the module docstring).

    context: the context the compensated moves will have (approach direction per axis, time since
    the campaign's start, temperature; :func:`tasks.campaign.capture_request.planned_capture_context`): the
    model's effects that depend on it (backlash, thermal drift, a user effect reading it) are
    compensated as they will be then. None: neutral (approach 0, time 0, 20 °C), i.e. those
    effects are left uncompensated."""
    check_objective(orientation)
    desired = desired_tip_poses(machine, commands)
    position, direction = desired[:, :3, 3], desired[:, :3, 2]
    full = inverse(machine, position, direction, model, context=context, initial=commands, spin_weight=SPIN_WEIGHT,
                   tool_rotation=desired[:, :3, :3], direction_weight=ORIENTATION_WEIGHT_MM)
    if orientation == "full":
        return Compensation(full, ["full"] * len(full))
    tool, residual = inverse(machine, position, direction, model, context=context, initial=full,
                             direction_weight=ORIENTATION_WEIGHT_MM, return_residual=True)
    strokes = machine.strokes_command()
    inside = np.all((tool >= strokes[:, 0]) & (tool <= strokes[:, 1]), axis=1)
    converged = residual <= CONVERGED_MM  # NaN: not converged
    keep = converged & inside
    objective = np.where(keep, "tool-axis",
                         np.where(converged, "full (tool-axis leaves a stroke)", "full (tool-axis did not converge)"))
    return Compensation(np.where(keep[:, None], tool, full), objective.tolist())


def compensation_table(image_ids, commands: np.ndarray, compensation: Compensation) -> pd.DataFrame:
    """The ``compensation`` lake table: nominal and compensated commands and their difference
    (X/Y/Z in mm, A/C in deg; the correction as µm and arcsec), and the objective met per pose."""
    out = pd.DataFrame({"image_id": list(image_ids)})
    for i, axis in enumerate(AXIS_ORDER):
        out[axis] = commands[:, i]
        out[f"{axis}_compensated"] = compensation.commands[:, i]
        scale = 3600.0 if axis in ("A", "C") else 1000.0
        unit = "arcsec" if axis in ("A", "C") else "um"
        out[f"{axis}_correction_{unit}"] = (compensation.commands[:, i] - commands[:, i]) * scale
    out["orientation_objective"] = compensation.objective
    return out

"""Compensation by inverse kinematics of the identified model (§5.2).

The desired tip pose of a command is where the *nominal* machine would put the tip. The
compensated command is the one at which the *identified* machine puts it there: position and tool
direction (five axes fix five degrees of freedom; the rotation about the tool axis is left free).
Five axes cannot fix all three rotations of the tip: the compensation places the tip exactly (X/Y/Z)
and chooses A and C to minimise the whole orientation error, the rotation about the tool axis
included (the seed's orientation error counts it). Near the singular pose (tool along C at A ≈ 0)
that also stops a tilt of the tool from being "corrected" by a large turn of C that spins the
tool about its axis.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from tasks.error_model import ErrorModel
from tasks.inverse_kinematics import inverse
from tasks.kinematics import forward
from tasks.machine import AXIS_ORDER, Machine


def desired_tip_poses(machine: Machine, commands: np.ndarray) -> np.ndarray:
    """(N, 4, 4) tip poses in the workpiece frame (mm) that the nominal machine reaches at ``commands``."""
    return forward(machine, commands).tool_in_workpiece()


SPIN_WEIGHT = 1.0  # rotation about the tool axis weighs like the tool direction
ORIENTATION_WEIGHT_MM = 1.0  # mm per rad: orientation settles among A and C, X/Y/Z place the tip


def compensate(machine: Machine, model: ErrorModel, commands: np.ndarray) -> np.ndarray:
    """(N, 5) compensated commands (mm, deg) reaching the nominal tip poses of ``commands`` on
    ``model``, as near the commands as the singular poses require."""
    desired = desired_tip_poses(machine, commands)
    return inverse(machine, desired[:, :3, 3], desired[:, :3, 2], model, initial=commands,
                   spin_weight=SPIN_WEIGHT, tool_x_axis=desired[:, :3, 0], direction_weight=ORIENTATION_WEIGHT_MM)


def compensation_table(image_ids, commands: np.ndarray, compensated: np.ndarray) -> pd.DataFrame:
    """The ``compensation`` lake table: nominal and compensated commands and their difference
    (X/Y/Z in mm, A/C in deg; the correction as µm and arcsec)."""
    out = pd.DataFrame({"image_id": list(image_ids)})
    for i, axis in enumerate(AXIS_ORDER):
        out[axis] = commands[:, i]
        out[f"{axis}_compensated"] = compensated[:, i]
        scale = 3600.0 if axis in ("A", "C") else 1000.0
        unit = "arcsec" if axis in ("A", "C") else "um"
        out[f"{axis}_correction_{unit}"] = (compensated[:, i] - commands[:, i]) * scale
    return out

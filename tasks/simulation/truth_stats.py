"""Statistics of the true errors, as the seed reports them (§5.2, Figs. 10–13).

- Tip error over validation poses: mean/max/std of ‖t_a − t_c‖ (µm) and ‖log(R_a⁻¹ R_c)‖
  (arcsec), true machine against the nominal model, and the X/Y/Z components.
- PDGE magnitudes per axis over its sweep: mean of ‖(δx, δy, δz)‖ (µm) and ‖(εx, εy, εz)‖ (arcsec).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd

from tasks.core.units import ARCSEC, UM
from tasks.machine.context import PoseContext
from tasks.machine.description import AXIS_ORDER, Machine
from tasks.machine.error_model import ErrorModel
from tasks.machine.kinematics import forward, tip_pose_error

# The seed's published figures (§5.2): before and after compensation.
SEED_BEFORE = {"position_mean_um": 59.9, "position_max_um": 72.7, "position_std_um": 6.6,
               "orientation_mean_arcsec": 160.0, "orientation_max_arcsec": 331.0,
               "orientation_std_arcsec": 77.9}
SEED_AFTER = {"position_mean_um": 1.80, "position_max_um": 4.90, "position_std_um": 1.1,
              "orientation_mean_arcsec": 52.9, "orientation_max_arcsec": 140.0,
              "orientation_std_arcsec": 39.4}
SEED_PDGE_MEANS = {  # axis: (translational µm, rotational arcsec), Fig. 11
    "X": (40.2, 224.0), "Y": (24.8, 213.0), "Z": (73.5, 101.0), "A": (6.18, 209.0), "C": (0.720, 253.0),
}


def tip_errors(machine: Machine, commands: np.ndarray, errors: ErrorModel,
               context: PoseContext | None = None) -> pd.DataFrame:
    """Per pose: true tip pose against the nominal one, in the workpiece frame.

    Returns position_um, orientation_arcsec and the components dx/dy/dz_um (position difference)
    and rx/ry/rz_arcsec (rotation vector of R_c⁻¹ R_a).
    """
    actual = forward(machine, commands, errors, context).tool_in_workpiece()
    return tip_pose_error(actual, forward(machine, commands).tool_in_workpiece())


def validation_poses(machine: Machine, poses: int = 100, seed: int = 0) -> tuple[np.ndarray, PoseContext]:
    """The ``validation`` poses of the seed's campaign plan with ``poses`` of them (commands (N, 5),
    mm and deg), each with the context the simulator gives it there: approach per axis from the
    plan's moves, time since the campaign's start and temperature
    (:func:`tasks.simulation.campaign_plan.plan_context`)."""
    from tasks.simulation.campaign_plan import CampaignPlan, plan_campaign, plan_context

    plan, _ = plan_campaign(machine, CampaignPlan(validation_poses=poses), seed)
    rows = np.flatnonzero((plan["stage"] == "validation").to_numpy())
    return plan[list(AXIS_ORDER)].to_numpy(dtype=float)[rows], plan_context(plan).take(rows)


def effects_change(machine: Machine, commands: np.ndarray, errors: ErrorModel,
                   context: PoseContext | None = None) -> pd.DataFrame:
    """Per pose, how far ``errors``' effects move the true tip: the norm of the change of the position
    error vector (µm) and of the rotation vector (arcsec) against the same model without its effects,
    at the same commands (N, 5) and context. Columns position_um, orientation_arcsec."""
    with_effects = tip_errors(machine, commands, errors, context)
    without = tip_errors(machine, commands, replace(errors, effects=[]), context)
    d = (with_effects - without)
    return pd.DataFrame({"position_um": np.linalg.norm(d[["dx_um", "dy_um", "dz_um"]].to_numpy(), axis=1),
                         "orientation_arcsec": np.linalg.norm(d[["rx_arcsec", "ry_arcsec", "rz_arcsec"]].to_numpy(),
                                                              axis=1)})


def summarise(err: pd.DataFrame) -> dict[str, float]:
    """mean/max/std of position (µm) and orientation (arcsec) errors, keys as in SEED_BEFORE."""
    out = {}
    for col, key in (("position_um", "position"), ("orientation_arcsec", "orientation")):
        unit = "um" if key == "position" else "arcsec"
        v = err[col].to_numpy()
        out[f"{key}_mean_{unit}"] = float(v.mean())
        out[f"{key}_max_{unit}"] = float(v.max())
        out[f"{key}_std_{unit}"] = float(v.std(ddof=1)) if v.size > 1 else 0.0
    return out


def pdge_magnitudes(machine: Machine, errors: ErrorModel, sweep_commands: dict[str, np.ndarray]) -> pd.DataFrame:
    """Mean translational (µm) and rotational (arcsec) PDGE magnitude per axis over its sweep.

    sweep_commands: {axis: (n,) positions in command units (mm or deg)}.
    """
    rows = []
    for axis, pos in sweep_commands.items():
        profile = errors.pdge.get(axis)
        if profile is None:
            continue
        e = profile(machine.axes[axis].to_internal(np.asarray(pos, dtype=float)))
        rows.append({
            "axis": axis,
            "translation_mean_um": float(np.linalg.norm(e[:, :3], axis=1).mean() / UM),
            "rotation_mean_arcsec": float(np.linalg.norm(e[:, 3:], axis=1).mean() / ARCSEC),
            "seed_translation_mean_um": SEED_PDGE_MEANS[axis][0],
            "seed_rotation_mean_arcsec": SEED_PDGE_MEANS[axis][1],
        })
    return pd.DataFrame(rows)


SEED_SWEEP_STEP = {"X": 1.0, "Y": 1.0, "Z": 0.1, "A": 1.0, "C": 1.0}  # mm or deg (§5.2)


def sweep_positions(positions: int = 50) -> dict[str, np.ndarray]:
    """The seed's PDGE sweep positions of each axis (command units): 50 steps of 1 mm / 0.1 mm / 1°.

    Fig. 11's means refer to these; the prototype's true PDGEs are scaled to them. (A campaign's
    own sweeps are planned by :func:`tasks.simulation.campaign_plan.sweep_positions`.)
    """
    k = np.arange(positions) - positions // 2
    return {a: k * SEED_SWEEP_STEP[a] for a in AXIS_ORDER}

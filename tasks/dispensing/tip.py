"""Where the dots land, and the tip offset that the dots reveal.

A needle dispenser holds its opening a small standoff above the surface; the drop that forms
there (well under a millimetre: surface tension dominates gravity, Bond number ≪ 1) wets the
surface at the point nearest the opening, the foot of the surface normal through it. A dot lands
at the (x, y) of the real tip position in the workpiece frame, whatever its height. Its offset from
the ring is the tip's error in the surface plane: a tip offset t in the tool frame moves the dot by
P R t (R the tip rotation, P the projection onto the surface), so at A = 0 the component along the
tool axis is invisible and the spread of A over the rings (sin A) makes it seen. Along the tool
axis the drop could not tell it: moving the opening along its own axis moves that axis' trace on
the surface not at all.

The fit: measured dot − ring offsets of qualified dots (any phases; each with its commands) against
those the identified model predicts with a constant tool-frame offset t added to it (the
``tool_offset`` effect, tasks.machine.effects); Gauss–Newton on t (µm), covariance σ² (JᵀJ)⁻¹ with σ² from
the residuals. The camera sees plates, never the tip: no other measurement fixes t.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from tasks.core.units import UM
from tasks.machine.context import PoseContext
from tasks.machine.description import Machine
from tasks.machine.effects import ToolOffset
from tasks.machine.error_model import ErrorModel
from tasks.machine.kinematics import forward

MAX_CONDITION = 1e3  # beyond it the tool-axis component is not seen (mean |sin A| below ~1e-3)
TIP_FIT_STEP_UM = 1.0  # finite-difference step of the Jacobian (the landing is linear in t to < 1e-6)


def landing_points(machine: Machine, model: ErrorModel | None, commands: np.ndarray,
                   context: PoseContext | None = None) -> np.ndarray:
    """(N, 2) where the dots land on the workpiece surface (mm, workpiece frame) when the machine
    described by ``model`` dispenses at ``commands`` (N, 5): the foot of the surface normal
    through the tip."""
    return forward(machine, commands, model, context).tool_in_workpiece()[:, :2, 3]


def tool_offset_of(model: ErrorModel) -> np.ndarray:
    """(3,) the model's tool_offset effect (µm, tip frame), zeros when it has none."""
    out = np.zeros(3)
    for e in model.effects:
        if isinstance(e, ToolOffset):
            out += [e["dx_um"], e["dy_um"], e["dz_um"]]
    return out


def with_tool_offset(model: ErrorModel, offset_um) -> ErrorModel:
    """A copy of ``model`` whose tool_offset effect is its own plus ``offset_um`` (3,) (µm, tip frame)."""
    total = tool_offset_of(model) + np.asarray(offset_um, dtype=float)
    others = [e for e in model.effects if not isinstance(e, ToolOffset)]
    effect = ToolOffset(dx_um=total[0], dy_um=total[1], dz_um=total[2])
    return replace(model, effects=[*others, effect])


@dataclass(frozen=True)
class TipFit:
    """The tip offset the dots reveal: ``offset_um`` (3,) added to the model's tool_offset (µm,
    tip frame), its covariance (3, 3) (µm²); ``tilt_um`` ± ``tilt_uncertainty_um``: the part of the
    tool-axis error that grows as sin A (µm per unit sin A; fitted, not folded in); the rms of the
    post-fit dot residuals (µm), the number of dots used and the model with the offset folded in."""

    offset_um: np.ndarray
    covariance_um2: np.ndarray
    tilt_um: float
    tilt_uncertainty_um: float
    residual_rms_um: float
    dots: int
    model: ErrorModel

    @property
    def uncertainty_um(self) -> np.ndarray:
        """(3,) standard uncertainties (µm)."""
        return np.sqrt(np.diag(self.covariance_um2))


def tip_fit_jacobian(machine: Machine, model: ErrorModel, commands: np.ndarray, offset_um=None,
                     base: np.ndarray | None = None) -> np.ndarray:
    """(2N, 4) the tip fit's Jacobian at ``commands`` (N, 5): how the landing points (x, y of each
    dot, workpiece frame) move per unit of the tool-frame offset t (three columns) and of the
    tool-axis error b sin A (the fourth), mm per mm, for ``model`` with ``offset_um`` (3,) (µm)
    added to its tool_offset (zeros by default). base: the landing points there, if already known."""
    t = np.zeros(3) if offset_um is None else np.asarray(offset_um, dtype=float)
    if base is None:
        base = landing_points(machine, with_tool_offset(model, t), commands)
    J = np.empty((2 * len(commands), 4))
    for k in range(3):
        step = np.zeros(3)
        step[k] = TIP_FIT_STEP_UM
        moved = landing_points(machine, with_tool_offset(model, t + step), commands)
        J[:, k] = ((moved - base) / (TIP_FIT_STEP_UM * UM)).ravel()  # mm per mm
    # the landing is linear in a per-pose tool-axis offset
    J[:, 3] = J[:, 2] * np.repeat(np.sin(np.deg2rad(commands[:, 3])), 2)
    return J


def tip_fit_gain(machine: Machine, model: ErrorModel, commands: np.ndarray) -> np.ndarray:
    """(3, 2N) the tip fit's linear response at ``commands`` (N, 5): the change of the fitted
    tool-frame offset t (µm) per change of the dots' landing points (x, y of each dot, µm,
    workpiece frame), with the sin A nuisance term fitted beside it: the first three rows of
    (JᵀJ)⁻¹Jᵀ (:func:`tip_fit_jacobian`)."""
    J = tip_fit_jacobian(machine, model, np.asarray(commands, dtype=float))
    return np.linalg.solve(J.T @ J, J.T)[:3]


def fit_tip_offset(machine: Machine, model: ErrorModel, commands: np.ndarray, ring_mm: np.ndarray,
                   offset_mm: np.ndarray, iterations: int = 3) -> TipFit:
    """Fit the constant tool-frame tip offset from dot offsets.

    commands: (N, 5) the commands each dot was dispensed at; ring_mm: (N, 2) ring centres and
    offset_mm: (N, 2) measured dot − ring offsets (mm, workpiece frame). Beside the constant t, an
    error along the tool axis growing as sin A is fitted (b sin A): the dots see the tool-axis error
    only through sin A and along the direction the tool tilts, the same direction a constant tool-y
    offset moves them, so b sin A · sin A (even in A) would otherwise pass for a y offset of about
    b·mean(sin² A). It is a nuisance parameter (reported, not folded in: it averages out over poses
    symmetric in A). Raises ValueError with fewer than 4 dots or without the spread of A that makes
    the tool axis seen."""
    commands = np.asarray(commands, dtype=float)
    if len(commands) < 4:
        raise ValueError(f"the tip fit needs at least 4 qualified dots, got {len(commands)}")
    measured = np.asarray(ring_mm, float) + np.asarray(offset_mm, float)
    t, b = np.zeros(3), 0.0
    for _ in range(iterations):
        base = landing_points(machine, with_tool_offset(model, t), commands)
        J = tip_fit_jacobian(machine, model, commands, t, base)
        if np.linalg.cond(J) > MAX_CONDITION:
            raise ValueError("the dots do not fix the tip offset: dispense at more than one A angle")
        r = (measured - base).ravel() / UM - J[:, 3] * b  # µm
        step = np.linalg.solve(J.T @ J, J.T @ r)
        t, b = t + step[:3], b + step[3]
    final = landing_points(machine, with_tool_offset(model, t), commands)
    res = (measured - final).ravel() / UM - J[:, 3] * b
    dof = max(len(res) - 4, 1)
    sigma2 = float(res @ res / dof)
    cov = sigma2 * np.linalg.inv(J.T @ J)
    return TipFit(offset_um=t, covariance_um2=cov[:3, :3], tilt_um=float(b),
                  tilt_uncertainty_um=float(np.sqrt(cov[3, 3])), residual_rms_um=float(np.sqrt(sigma2)),
                  dots=len(commands), model=with_tool_offset(model, t))


def constant_tool_frame_error(machine: Machine, truth: ErrorModel, desired: np.ndarray,
                              commands: np.ndarray) -> np.ndarray:
    """(3,) the mean of the true tip position error expressed in the true tip frame (µm) over poses
    at ``commands`` (N, 5) against ``desired`` (N, 4, 4): the constant tool-frame part of the error."""
    tip = forward(machine, commands, truth).tool_in_workpiece()
    error = tip[:, :3, 3] - desired[:, :3, 3]  # reached − desired, workpiece frame
    local = np.einsum("nji,nj->ni", tip[:, :3, :3], error)  # Rᵀ (reached − desired)
    return local.mean(axis=0) / UM

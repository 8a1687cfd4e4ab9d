"""Inverse kinematics: commands X/Y/Z/A/C that put the tip at a desired position and tool
direction in the workpiece frame, under any error model.

Used for compensation (the commands that make the *real* machine reach what the ideal one
would) and by the simulator to aim camera 1 at plate a. Generic over the machine description:
batched Gauss–Newton on the six residuals (tip position mm, tool direction scaled to mm) with a
forward-difference Jacobian, started from a coarse search over the rotary axes.
"""

from __future__ import annotations

import numpy as np

from tasks.machine.context import PoseContext
from tasks.machine.description import AXIS_ORDER, Machine
from tasks.machine.error_model import ErrorModel
from tasks.machine.kinematics import forward

DIRECTION_WEIGHT_MM = 100.0  # 1 rad of tool direction weighs like 100 mm of position
_STEP = np.array([1e-4, 1e-4, 1e-4, 1e-5, 1e-5])  # finite-difference steps (mm, mm, mm, deg, deg)


def _tip_state(machine, commands, errors, context, spin_weight: float = 0.0,
               direction_weight: float = DIRECTION_WEIGHT_MM):
    """(N, 6) or (N, 12): tip position (mm), tool direction × direction_weight (mm per unit) and,
    with a spin weight, the tip frame's x and y axes × spin_weight × direction_weight; workpiece frame.

    A small rotation ω of the tip moves its z, x and y axes by |ω×z|² = ωx² + ωy², |ω×x|² = ωy² + ωz²
    and |ω×y|² = ωx² + ωz² (tip frame): with x and y both in, spin weight 1 weighs every direction of
    rotation alike (2|ω|²), so the least squares minimises the whole rotation angle."""
    g = forward(machine, commands, errors, context).tool_in_workpiece()
    parts = [g[:, :3, 3], direction_weight * g[:, :3, 2]]
    if spin_weight:
        parts += [spin_weight * direction_weight * g[:, :3, 0], spin_weight * direction_weight * g[:, :3, 1]]
    return np.concatenate(parts, axis=1)


def _rotary_start(machine: Machine, direction: np.ndarray, prefer: np.ndarray) -> np.ndarray:
    """Initial (N, 5) commands: linear axes at 0, rotary axes from a 5° grid search on direction.

    A five-axis head reaches most directions on two branches (here (A, C) and (-A, C + 180°)):
    among grid points within 0.01 of the best direction match, take the one nearest ``prefer``.
    """
    rot = [i for i, a in enumerate(AXIS_ORDER) if machine.axes[a].is_rotary]
    grids = [np.arange(lo, hi + 1e-9, 5.0) for lo, hi in machine.strokes_command()[rot]]
    mesh = np.stack(np.meshgrid(*grids, indexing="ij"), -1).reshape(-1, len(rot))
    cand = np.zeros((mesh.shape[0], 5))
    cand[:, rot] = mesh
    d = forward(machine, cand, None).tool_in_workpiece()[:, :3, 2]  # (M, 3)
    match = direction @ d.T  # (N, M)
    near = match > match.max(axis=1, keepdims=True) - 0.01
    dist = np.abs(prefer[:, None, rot] - cand[None, :, rot]).sum(axis=-1)
    best = np.argmin(np.where(near, dist, np.inf), axis=1)
    return cand[best]


def inverse(
    machine: Machine,
    tip_position_mm,
    tool_direction,
    errors: ErrorModel | None = None,
    context: PoseContext | None = None,
    initial=None,
    prefer=None,
    tol_mm: float = 1e-9,
    max_iter: int = 30,
    spin_weight: float = 0.0,
    tool_rotation=None,
    direction_weight: float = DIRECTION_WEIGHT_MM,
    return_residual: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Commands (N, 5) [mm, deg] that reach the desired tip poses.

    tip_position_mm: (N, 3) tip position in the workpiece frame (mm).
    tool_direction: (N, 3) desired tool axis (tip frame z) in the workpiece frame (unit).
    errors: the machine's error model (None: ideal). initial: (N, 5) start commands (default:
    grid search over the rotary axes, on the branch nearest ``prefer`` (N, 5) or (5,), default
    home). Raises ``ValueError`` for poses that do not converge.

    spin_weight: w > 0 adds the rotation about the tool axis to the least squares (``tool_rotation``
    (N, 3, 3): the desired tip rotation in the workpiece frame); w = 1 weighs it like a tilt of the
    tool, so the least squares minimises the whole rotation angle. Two rotary axes turn the tool
    about two directions only, so the whole rotation cannot in general be fixed; near the singular
    pose of a five-axis head (tool along C, A ≈ 0) a small tilt of the tool can only be corrected by
    a large turn of C that spins the tool about its axis, and the weight stops that trade where it
    costs more spin than it gains tilt. No convergence error
    is raised then (the problem is overdetermined): the caller reads what is left from the forward
    kinematics. direction_weight (mm per unit of direction, i.e. per rad) sets how orientation
    trades against position in that least squares; X/Y/Z can always place the tip, so a small
    weight keeps the position exact and settles the orientation among A and C.

    return_residual: return (commands, residual (N,)) instead and raise nothing, the residual being
    the largest |target − reached| of each pose in the least squares' weighted units (mm; direction
    × direction_weight; with a spin weight it keeps the rotation that A and C cannot make, and is
    then no convergence test).
    """
    target_p = np.atleast_2d(np.asarray(tip_position_mm, dtype=float))
    target_d = np.atleast_2d(np.asarray(tool_direction, dtype=float))
    target_d = target_d / np.linalg.norm(target_d, axis=1, keepdims=True)
    target = np.concatenate([target_p, direction_weight * target_d], axis=1)
    if spin_weight:
        R = np.asarray(tool_rotation, dtype=float).reshape(-1, 3, 3)
        target = np.concatenate([target, spin_weight * direction_weight * R[:, :, 0],
                                 spin_weight * direction_weight * R[:, :, 1]], axis=1)
    n = target.shape[0]
    if initial is None:
        prefer = np.zeros((n, 5)) if prefer is None else np.broadcast_to(np.asarray(prefer, float), (n, 5))
        cmd = _rotary_start(machine, target_d, prefer)
    else:
        cmd = np.array(initial, dtype=float)
    cmd = np.atleast_2d(cmd).copy()
    for _ in range(max_iter):
        state = _tip_state(machine, cmd, errors, context, spin_weight, direction_weight)
        r = target - state  # (N, 6) or (N, 12)
        if np.max(np.abs(r)) < tol_mm:
            break
        # Jacobian by forward differences, all 5 columns in one batched FK of 5N poses
        pert = cmd[:, None, :] + np.eye(5)[None] * _STEP  # (N, 5, 5)
        ctx5 = None if context is None else context.take(np.repeat(np.arange(n), 5))
        s5 = _tip_state(machine, pert.reshape(-1, 5), errors, ctx5, spin_weight, direction_weight).reshape(n, 5, -1)
        J = np.swapaxes((s5 - state[:, None, :]) / _STEP[None, :, None], 1, 2)  # (N, 6 or 12, 5)
        JtJ = np.swapaxes(J, 1, 2) @ J
        Jtr = np.einsum("nij,ni->nj", J, r)
        step = np.linalg.solve(JtJ + 1e-12 * np.eye(5), Jtr[..., None])[..., 0]
        cmd = cmd + step
        if spin_weight and np.max(np.abs(step)) < tol_mm:
            break
    if spin_weight and not return_residual:
        return cmd  # overdetermined: no convergence test, the caller reads what is left
    residual = np.max(np.abs(target - _tip_state(machine, cmd, errors, context, spin_weight, direction_weight)),
                      axis=1)
    if return_residual:
        return cmd, residual
    bad = np.flatnonzero(~(residual <= max(tol_mm, 1e-7)))  # NaN counts as not converged
    if bad.size:
        raise ValueError(f"inverse kinematics did not converge for poses {bad[:10].tolist()} "
                         f"(max residual {residual[bad].max():.3g} mm)")
    return cmd

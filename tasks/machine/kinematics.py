"""Forward and inverse kinematics by the local product of exponentials (eqs. 4–12).

Joint i moves its link frame relative to the previous one by

    g_{i-1,i}(θ_i) = e^{t̂_{i-1,i}} · e^{ξ̂_D(θ_i)} · e^{(Ad_{E_I} ξ_i)^ θ_i}              (eq. 12)

with the fixed home offset t_{i-1,i}, the PDGE error motion ξ_D (eq. 8) and the ideal unit twist
ξ_i in the joint's own frame, whose axis the PIGEs move: E_I = e^{ξ̂_I} (eqs. 9–11) tilts or shifts
the axis line, e^{(Ad_E ξ)^ θ} = E · e^{ξ̂ θ} · E⁻¹. A PIGE is position independent in the
paper's sense (a fixed error of the axis line) and changes nothing at the joint's zero: the
errors present at home belong to the PDGE's value there. Chains start at the
base; attachments (cameras, plates, tip) ride on one link. Everything is batched over N poses.

SYNOPSIS
    >>> from tasks.machine.description import load_machine
    >>> from tasks.machine.kinematics import forward
    >>> m = load_machine("prototype")
    >>> fk = forward(m, [[0, 0, 0, 10, 30]])          # X Y Z mm, A C deg
    >>> fk.tool_in_workpiece().shape
    (1, 4, 4)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from tasks.core import se3
from tasks.core.units import ARCSEC, UM
from tasks.machine.context import PoseContext
from tasks.machine.description import AXIS_ORDER, Machine
from tasks.machine.error_model import ErrorModel, pige_joint_transforms


def ideal_joint_motion(machine: Machine, axis: str, theta: np.ndarray) -> np.ndarray:
    """e^{ξ̂ θ} for one axis: (N,) mm or rad -> (N, 4, 4). Closed forms, no generic exp."""
    ax = machine.axes[axis]
    d = np.asarray(ax.direction, dtype=float)
    theta = np.asarray(theta, dtype=float)
    if ax.is_rotary:
        # Rodrigues for a unit axis through the frame origin
        K = se3.skew(d)
        s, c = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
        R = np.eye(3) + s * K + (1.0 - c) * (K @ K)
        return se3.from_rotation_translation(R, np.zeros((theta.shape[0], 3)))
    return se3.translation(theta[:, None] * d)


def pige_moved_axis(E: np.ndarray, J: np.ndarray) -> np.ndarray:
    """Joint motion about the axis line moved by the PIGE transform E (4, 4): E · J · E⁻¹, (N, 4, 4).

    J: ideal motions e^{ξ̂θ} (N, 4, 4) in the joint's frame. Identity where J is (θ = 0)."""
    return E @ J @ se3.inverse(E)


@dataclass
class ForwardKinematics:
    """Poses of every link and attachment for a batch of N poses, in the base frame (mm)."""

    machine: Machine
    link_poses: dict[str, np.ndarray]  # link name -> (N, 4, 4), "base" included
    attachment_errors: dict[str, np.ndarray]  # attachment -> (N, 6)

    def pose(self, name: str) -> np.ndarray:
        """Base-frame pose (N, 4, 4) of a link or attachment."""
        if name in self.link_poses:
            return self.link_poses[name]
        att = self.machine.attachments[name]
        T = self.link_poses[att.link] @ att.pose_in_link
        if name in self.attachment_errors:
            T = T @ se3.error_motion(self.attachment_errors[name])
        return T

    def relative(self, of: str, seen_from: str) -> np.ndarray:
        """Pose of ``of`` in the frame of ``seen_from``: (N, 4, 4)."""
        return se3.inverse(self.pose(seen_from)) @ self.pose(of)

    def tool_in_workpiece(self) -> np.ndarray:
        """g_tw of eq. 12: the dispensing tip in the workpiece frame, (N, 4, 4)."""
        return self.relative(self.machine.tip, self.machine.workpiece)

    def camera_view(self, camera: str) -> np.ndarray:
        """T_cam_plate: the plate this camera measures, in the camera frame, (N, 4, 4)."""
        return self.relative(self.machine.views[camera], camera)


def forward(
    machine: Machine,
    commands,
    errors: ErrorModel | None = None,
    context: PoseContext | None = None,
) -> ForwardKinematics:
    """Forward kinematics of N poses.

    commands: (N, 5) X, Y, Z [mm], A, C [deg] in AXIS_ORDER (a single pose (5,) is allowed).
    errors: the error model (None: the ideal machine). context: approach directions, time and
    temperature for effects that need them (default: neutral).
    """
    cmd = np.atleast_2d(np.asarray(commands, dtype=float))
    q = machine.commands_to_internal(cmd)
    n = q.shape[0]
    errors = errors or ErrorModel.none()
    context = context or PoseContext.neutral(n)
    joint_err = errors.joint_error_vectors(machine, q, context)
    pige = pige_joint_transforms(errors.pige)
    links = {"base": np.broadcast_to(np.eye(4), (n, 4, 4))}
    for chain in (machine.tool_chain, machine.workpiece_chain):
        T = None
        for axis in chain:
            # joint factor of eq. 12, built right to left: e^{ξ_D} e^{ξ_I} e^{ξθ}
            J = ideal_joint_motion(machine, axis, q[:, AXIS_ORDER.index(axis)])
            if axis in pige:
                J = pige_moved_axis(pige[axis], J)
            if axis in joint_err:
                J = se3.error_motion(joint_err[axis]) @ J
            # the home offset e^{t̂} is a pure translation: left-multiplying adds it to the translation
            J[:, :3, 3] += machine.link_offsets[axis][:3, 3]
            T = J if T is None else T @ J
            links[axis] = T
    return ForwardKinematics(machine, links, errors.attachment_error_vectors(machine, q, context))


def pose_error(measured: np.ndarray, nominal: np.ndarray) -> np.ndarray:
    """Pose residual e = log(nominal⁻¹ · measured) in se(3) (eq. 20): (N, 6) (v mm, w rad)."""
    return se3.log(se3.inverse(nominal) @ measured)


def position_orientation_error(actual: np.ndarray, nominal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tip position error ‖t_a − t_c‖ (mm) and orientation error ‖log(R_a⁻¹ R_c)‖ (rad), per pose.

    The quantities averaged in the seed's Δt and ΔR (§5.2). actual, nominal: (N, 4, 4).
    """
    dt = np.linalg.norm(actual[:, :3, 3] - nominal[:, :3, 3], axis=1)
    dR = se3.rotation_angle(np.swapaxes(actual[:, :3, :3], 1, 2) @ nominal[:, :3, :3])
    return dt, dR


def tip_pose_error(measured: np.ndarray, desired: np.ndarray) -> pd.DataFrame:
    """Tip error per pose: position (µm), orientation (arcsec) and X/Y/Z components, workpiece frame.

    measured, desired: (N, 4, 4) tip poses in the workpiece frame (mm). Components: t_a − t_c (µm)
    and the rotation vector of R_c⁻¹ R_a (arcsec). Returns position_um,
    orientation_arcsec, dx_um, dy_um, dz_um, rx_arcsec, ry_arcsec, rz_arcsec.
    """
    d = (measured[:, :3, 3] - desired[:, :3, 3]) / UM
    r = se3.log_so3(np.swapaxes(desired[:, :3, :3], 1, 2) @ measured[:, :3, :3]) / ARCSEC
    return pd.DataFrame({"position_um": np.linalg.norm(d, axis=1), "orientation_arcsec": np.linalg.norm(r, axis=1),
                         "dx_um": d[:, 0], "dy_um": d[:, 1], "dz_um": d[:, 2],
                         "rx_arcsec": r[:, 0], "ry_arcsec": r[:, 1], "rz_arcsec": r[:, 2]})

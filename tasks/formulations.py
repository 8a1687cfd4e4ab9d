"""Three kinematic formulations of one machine and one error model: the seed's Table 5.

The seed (§5.2, Table 5) swaps only the kinematic-modelling module of its calibration algorithm
and compares the mean single-run time, the time to build 300 error matrices and the error norms
of its local product of exponentials (§3.2, eq. 12) with the Denavit–Hartenberg method and the
global product of exponentials. This module builds the two alternatives on the same
:class:`~tasks.machine.Machine` and the same :class:`~tasks.error_model.ErrorModel` (11 PIGEs,
per-axis PDGE profiles) and compares them with :func:`tasks.kinematics.forward`, which is the
simulator's truth.

* **Local PoE (ours, eq. 12).** ``g_{i-1,i} = e^{t̂} e^{ξ̂_D(θ)} e^{ξ̂_I} e^{ξ̂ θ}`` per joint, every
  error in the joint's own frame. Exact by construction.
* **Denavit–Hartenberg.** Modified (Craig) DH:
  ``A_i = Rx(α_{i-1}) Tx(a_{i-1}) Rz(θ_i) Tz(d_i)``; frame i has z along joint i, x along the
  common normal to joint i+1; frame 0 coincides with frame 1 at home. The parameters are derived
  from the axis lines of the Machine (direction, home position). Where z_{i-1} ∥ z_i (always
  for link 1 under Craig's frame-0 convention) Hayati's β, ``Rx(α) Tx(a) Ry(β) Rz(θ) Tz(d)``,
  is added. Errors enter as perturbations (δα, δa, δθ, δd[, δβ]) of each joint's own link,
  fitted to that joint's six-component error by a first-order least-squares projection
  (rotations first, then translations). A link has four (five) parameters for six error
  components, so two (one) components per joint are lost. :func:`dh_parameter_table` lists
  which components each joint loses.
* **Global PoE.** ``g = e^{ξ̂'_1 θ_1} ··· e^{ξ̂'_n θ_n} g'(0)`` with screws fixed in the base
  frame. Every joint's error (PIGE and PDGE evaluated at the pose) perturbs only that joint's
  own global screw, ``ξ'_i = Ad(E^g_i) ξ_i``, and the home pose,
  ``g'(0) = E^g_1 ··· E^g_n g(0)``, where ``E^g_i = M_i E_i M_i⁻¹`` is the joint's error moved
  to the base frame at home. This is the fixed-screw-axes assumption: an error of joint i does not
  move the screws of the joints after it. The model is exact for one moving axis. It is wrong when
  an earlier joint's error should tilt or shift a later screw (joint coupling: A's errors
  move the C axis).

Frames and units: base frame B of the Machine; mm and rad inside; commands (N, 5) are X, Y, Z
[mm], A, C [deg] in AXIS_ORDER; every formulation returns the tip in the workpiece frame
``g_tw`` (N, 4, 4), as :meth:`ForwardKinematics.tool_in_workpiece`.

SYNOPSIS
    >>> from tasks.machine import load_machine
    >>> from tasks.prototype_errors import load_prototype_errors
    >>> from tasks.formulations import compare_formulations, format_table5
    >>> m = load_machine("prototype")
    >>> table = compare_formulations(m, load_prototype_errors(), [[0, 0, 0, 10, 30]], repeats=1)
    >>> list(table.formulation)
    ['local PoE (ours)', 'Denavit–Hartenberg', 'global PoE']
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd

from tasks import se3
from tasks.context import PoseContext
from tasks.error_model import ARCSEC, PIGE_SCREWS, UM, ErrorModel, pige_joint_transforms
from tasks.kinematics import forward, position_orientation_error
from tasks.machine import AXIS_ORDER, Machine

TABLE5_COLUMNS = (
    "formulation",
    "mean_single_run_ms",
    "total_300_ms",
    "position_error_norm_um",
    "orientation_error_norm_arcsec",
    "note",
)
LOCAL_POE, DH, GLOBAL_POE = "local PoE (ours)", "Denavit–Hartenberg", "global PoE"
_PARALLEL_TOL = 1e-9  # |z_{i-1} × z_i| below this: nominally parallel axes (Hayati's β)


# ---------------------------------------------------------------------------------------------
# shared pieces: joint errors of eq. 12 and attachments
# ---------------------------------------------------------------------------------------------


def _prepare(machine: Machine, commands, errors: ErrorModel | None, context: PoseContext | None):
    """Joint values q (N, 5) [mm, rad], PDGE (+ effect) six-vectors per joint (N, 6), the PIGEs
    {name: value} (mm, rad) and the attachment error motions, as forward() evaluates them."""
    cmd = np.atleast_2d(np.asarray(commands, dtype=float))
    q = machine.commands_to_internal(cmd)
    errors = errors or ErrorModel.none()
    context = context or PoseContext.neutral(q.shape[0])
    return (q, errors.joint_error_vectors(machine, q, context), errors.pige,
            errors.attachment_error_vectors(machine, q, context))


def _error_transforms(joint_err: dict, pige: dict) -> dict[str, np.ndarray]:
    """E_i = e^{ξ̂_D(θ_i)} e^{ξ̂_I}, the error factor of eq. 12 in joint i's local frame (eqs. 8–11).

    (N, 4, 4) with PDGEs, (4, 4) with PIGEs only; joints without errors are absent.
    """
    pige_T = pige_joint_transforms(pige)
    E = {}
    for axis in AXIS_ORDER:
        if axis in joint_err:
            D = se3.error_motion(joint_err[axis])  # eq. 8
            E[axis] = D @ pige_T[axis] if axis in pige_T else D
        elif axis in pige_T:
            E[axis] = pige_T[axis]
    return E


def _error_twists(joint_err: dict, pige: dict) -> dict[str, np.ndarray]:
    """First-order error twist of each joint in its local frame: the PDGE six-vector plus the sum of
    its PIGE screws, (N, 6) or (6,), mm / rad. Equals log(E_i) to first order."""
    out: dict[str, np.ndarray] = {}
    for name, value in pige.items():
        if value == 0.0:
            continue
        axis, k = PIGE_SCREWS[name]
        out.setdefault(axis, np.zeros(6))[k] += value
    for axis, e in joint_err.items():
        out[axis] = e + out[axis] if axis in out else e
    return out


def _attachment_in_link(machine: Machine, name: str, attachment_errors: dict) -> np.ndarray:
    """Pose of an attachment in its link's local-PoE frame, with its error motion if any."""
    T = machine.attachments[name].pose_in_link
    if name in attachment_errors:
        T = T @ se3.error_motion(attachment_errors[name])
    return T


def _home_poses(machine: Machine, chain: tuple[str, ...]) -> list[np.ndarray]:
    """M_i: home pose (4, 4) of each local-PoE link frame in the base frame (products of e^{t̂})."""
    T, out = np.eye(4), []
    for axis in chain:
        T = T @ machine.link_offsets[axis]
        out.append(T)
    return out


class _PerMachineCache:
    """Derived geometry per Machine object (Machine is not hashable: its fields are dicts)."""

    def __init__(self, build: Callable[[Machine], object]):
        self.build = build
        self.store: dict[int, tuple[Machine, object]] = {}

    def __call__(self, machine: Machine):
        hit = self.store.get(id(machine))
        if hit is None or hit[0] is not machine:
            hit = (machine, self.build(machine))
            self.store[id(machine)] = hit
        return hit[1]


# ---------------------------------------------------------------------------------------------
# local PoE (the reference)
# ---------------------------------------------------------------------------------------------


def local_poe_tool_in_workpiece(machine: Machine, commands, errors: ErrorModel | None = None,
                                context: PoseContext | None = None) -> np.ndarray:
    """Tip in the workpiece frame by the local PoE of eq. 12 (:func:`tasks.kinematics.forward`).

    commands: (N, 5) X, Y, Z [mm], A, C [deg]. Returns g_tw (N, 4, 4), mm.
    """
    return forward(machine, commands, errors, context).tool_in_workpiece()


# ---------------------------------------------------------------------------------------------
# Denavit–Hartenberg (modified, Craig) with Hayati's β for parallel axes
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DHJoint:
    """One modified-DH link ``A_i = Rx(α_{i-1}) Tx(a_{i-1}) [Ry(β)] Rz(θ_i) Tz(d_i)``.

    alpha, theta0 in rad; a, d0 in mm; theta0/d0 are the offsets the joint variable adds to
    (θ_i = theta0 + q for a rotary joint, d_i = d0 + q for a linear one). ``frame_home``: DH frame
    i at home in the base frame. ``dh_to_joint``: C_i, the constant pose of joint i's local-PoE
    frame in DH frame i. ``jacobian`` (6, k): body twist of A_i per unit perturbation of
    ``parameters``. ``error_map`` (k, 6): joint i's local-frame error twist -> the parameter
    perturbations (first-order least squares, rotations first).
    """

    axis: str
    prismatic: bool
    alpha: float
    a: float
    theta0: float
    d0: float
    hayati: bool
    frame_home: np.ndarray
    dh_to_joint: np.ndarray
    jacobian: np.ndarray
    error_map: np.ndarray

    @property
    def parameters(self) -> tuple[str, ...]:
        return ("alpha", "a", "theta", "d", "beta") if self.hayati else ("alpha", "a", "theta", "d")

    def dh_error_twist(self, local_twist: np.ndarray) -> np.ndarray:
        """Joint error twist (..., 6) in its local-PoE frame -> the same error in DH frame i."""
        return local_twist @ se3.adjoint(self.dh_to_joint).T

    def lost_twist(self, local_twist: np.ndarray) -> np.ndarray:
        """The part (..., 6) of a joint error (local-frame twist, mm / rad) that the DH
        perturbations of this link cannot represent, in DH frame i (first order)."""
        e = self.dh_error_twist(local_twist)
        return e - (local_twist @ self.error_map.T) @ self.jacobian.T


@dataclass(frozen=True)
class DHChain:
    """A kinematic chain in modified DH: ``base`` = frame 0 in the base frame (4, 4)."""

    axes: tuple[str, ...]
    joints: tuple[DHJoint, ...]
    base: np.ndarray


def _closest_points(p1, z1, p2, z2):
    """Feet on line 1 and line 2 of the common normal of two non-parallel lines (unit z)."""
    w = p1 - p2
    b, d, e = z1 @ z2, z1 @ w, z2 @ w
    den = 1.0 - b * b
    return p1 + z1 * (b * e - d) / den, p2 + z2 * (e - b * d) / den


def _perpendicular(z: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to z: the base axis least aligned with z, orthogonalised."""
    e = np.eye(3)[np.argmin(np.abs(z))]
    x = e - (e @ z) * z
    return x / np.linalg.norm(x)


def _dh_matrix(alpha, a, theta, d, beta=None) -> np.ndarray:
    """Modified DH link transforms (..., 4, 4) in closed form, with Hayati's β if given.

    Rx(α) Tx(a) Rz(θ) Tz(d) = [[cθ, -sθ, 0, a], [cα sθ, cα cθ, -sα, -sα d], [sα sθ, sα cθ, cα, cα d]].
    With β: Rx(α) Tx(a) Ry(β) Rz(θ) Tz(d) = Tx(a) Rx(α) Ry(β) Rz(θ) Tz(d), Hayati's tilt about y
    at the foot of the common normal on axis i. Angles rad, lengths mm, broadcast to one shape.
    """
    alpha, a, theta, d = np.broadcast_arrays(*(np.asarray(v, dtype=float) for v in (alpha, a, theta, d)))
    out = np.zeros((*alpha.shape, 4, 4))
    out[..., 3, 3] = 1.0
    if beta is not None:
        R = se3.rot_x(alpha) @ se3.rot_y(np.broadcast_to(beta, alpha.shape)) @ se3.rot_z(theta)
        out[..., :3, :3] = R
        out[..., :3, 3] = R[..., :, 2] * d[..., None]
        out[..., 0, 3] += a
        return out
    ca, sa, ct, st = np.cos(alpha), np.sin(alpha), np.cos(theta), np.sin(theta)
    out[..., 0, 0], out[..., 0, 1], out[..., 0, 3] = ct, -st, a
    out[..., 1, 0], out[..., 1, 1], out[..., 1, 2], out[..., 1, 3] = ca * st, ca * ct, -sa, -sa * d
    out[..., 2, 0], out[..., 2, 1], out[..., 2, 2], out[..., 2, 3] = sa * st, sa * ct, ca, ca * d
    return out


def _dh_jacobian(alpha: float, a: float, theta: float, d: float, hayati: bool) -> np.ndarray:
    """(6, k) body twists log(A(p)⁻¹ A(p + δp)) / δp of one link at nominal (β = 0).

    Columns (δα, δa, δθ, δd[, δβ]); α does not enter: each perturbation acts after Rx(α).
    """
    z = np.array([0.0, 0.0, d])
    G = se3.from_rotation_translation(se3.rot_z(theta), np.array([a, 0.0, 0.0])) @ se3.translation(z)  # Tx Rz Tz
    H = se3.from_rotation_translation(se3.rot_z(theta), np.zeros(3)) @ se3.translation(z)  # Rz(θ) Tz(d)
    unit = np.eye(6)  # (tx, ty, tz, rx, ry, rz)
    cols = [
        se3.adjoint(se3.inverse(G)) @ unit[3],  # δα: rotation about x_{i-1}, before Tx Rz Tz
        se3.adjoint(se3.inverse(H)) @ unit[0],  # δa: translation along x_{i-1}, before Rz Tz
        unit[5],  # δθ: rotation about z_i (commutes with Tz)
        unit[2],  # δd: translation along z_i
    ]
    if hayati:
        cols.append(se3.adjoint(se3.inverse(H)) @ unit[4])  # δβ: rotation about y after Tx(a) Rx(α)
    return np.column_stack(cols)


def _projection(J: np.ndarray) -> np.ndarray:
    """(k, 6) first-order least-squares map from an error twist to the DH perturbations.

    Lexicographic, so no length scale is needed: the rotational parameters (α, θ, β) fit the
    rotation part; the translational ones (a, d) fit what translation the rotations leave.
    """
    rot = [0, 2] + ([4] if J.shape[1] == 5 else [])
    tra = [1, 3]
    P = np.zeros((J.shape[1], 6))
    P_rot = np.linalg.pinv(J[3:, rot]) @ np.eye(6)[3:]
    P[rot] = P_rot
    P[tra] = np.linalg.pinv(J[:3, tra]) @ (np.eye(6)[:3] - J[:3, rot] @ P_rot)
    return P


def _dh_chain(machine: Machine, chain: tuple[str, ...]) -> DHChain:
    """Modified-DH description of a chain, derived from its axis lines (direction, home point)."""
    lines = [(np.asarray(machine.axes[a].home_position_mm, float), np.asarray(machine.axes[a].direction, float))
             for a in chain]
    lines = [(p, z / np.linalg.norm(z)) for p, z in lines]
    homes = _home_poses(machine, chain)
    frames: list[np.ndarray] = []
    o_prev = x_prev = None
    for i, (p, z) in enumerate(lines):
        # where the previous frame's x axis (the common normal) meets this axis
        f = p if x_prev is None else _closest_points(p, z, o_prev, x_prev)[0]
        nxt = lines[i + 1] if i + 1 < len(lines) else None
        if nxt is not None and np.linalg.norm(np.cross(z, nxt[1])) > _PARALLEL_TOL:
            o, o_next = _closest_points(p, z, *nxt)
            x = np.cross(z, nxt[1]) if np.linalg.norm(o_next - o) <= _PARALLEL_TOL else o_next - o
            x /= np.linalg.norm(x)  # along the common normal, towards the next axis (a ≥ 0)
        else:  # parallel to the next axis, or the last axis: origin where x_{i-1} meets the axis
            o = f
            w = (nxt[0] - o) if nxt is not None else np.zeros(3)
            w = w - (w @ z) * z
            if np.linalg.norm(w) > _PARALLEL_TOL:
                x = w / np.linalg.norm(w)
            else:
                x = x_prev if x_prev is not None else _perpendicular(z)
        frames.append(se3.from_rotation_translation(np.column_stack([x, np.cross(z, x), z]), o))
        o_prev, x_prev = o, x
    joints = []
    prev_frame, prev_z = frames[0], lines[0][1]  # frame 0 = frame 1 at home (Craig)
    for axis, F, M, (_, z) in zip(chain, frames, homes, lines, strict=True):
        T = se3.inverse(prev_frame) @ F
        R, t = T[:3, :3], T[:3, 3]
        alpha, theta = np.arctan2(-R[1, 2], R[2, 2]), np.arctan2(-R[0, 1], R[0, 0])
        a, d = t[0], -np.sin(alpha) * t[1] + np.cos(alpha) * t[2]
        if not np.allclose(_dh_matrix(alpha, a, theta, d), T, atol=1e-9):
            raise ValueError(f"axis {axis}: DH frames could not be placed (got a non-DH link transform)")
        hayati = bool(np.linalg.norm(np.cross(prev_z, z)) <= _PARALLEL_TOL)
        J = _dh_jacobian(alpha, a, theta, d, hayati)
        C = se3.inverse(F) @ M
        joints.append(DHJoint(axis=axis, prismatic=not machine.axes[axis].is_rotary, alpha=float(alpha), a=float(a),
                              theta0=float(theta), d0=float(d), hayati=hayati, frame_home=F, dh_to_joint=C,
                              jacobian=J, error_map=_projection(J) @ se3.adjoint(C)))
        prev_frame, prev_z = F, z
    return DHChain(axes=tuple(chain), joints=tuple(joints), base=frames[0])


def _build_dh(machine: Machine) -> dict[str, DHChain]:
    return {"tool": _dh_chain(machine, machine.tool_chain), "workpiece": _dh_chain(machine, machine.workpiece_chain)}


_DH_CACHE = _PerMachineCache(_build_dh)


def dh_model(machine: Machine) -> dict[str, DHChain]:
    """{'tool': DHChain, 'workpiece': DHChain} of a Machine, derived once per Machine object."""
    return _DH_CACHE(machine)


def _dh_attachment_pose(machine: Machine, name: str, q: np.ndarray, twists: dict, att_err: dict) -> np.ndarray:
    """Base-frame pose (N, 4, 4) of an attachment through the DH chain with projected errors."""
    link = machine.attachments[name].link
    axes = machine.parents(link)  # base -> link, empty for "base"
    T = np.broadcast_to(np.eye(4), (q.shape[0], 4, 4))
    if not axes:
        return T @ _attachment_in_link(machine, name, att_err)
    chain = dh_model(machine)["tool" if axes[0] in machine.tool_chain else "workpiece"]
    T = T @ chain.base
    for j in chain.joints[: len(axes)]:
        qi = q[:, AXIS_ORDER.index(j.axis)]
        alpha, a, theta, d, beta = j.alpha, j.a, j.theta0, j.d0, None
        if j.axis in twists:
            dp = twists[j.axis] @ j.error_map.T  # first-order projection on the DH parameters
            alpha, a, theta, d = alpha + dp[..., 0], a + dp[..., 1], theta + dp[..., 2], d + dp[..., 3]
            if j.hayati:
                beta = dp[..., 4]
        if j.prismatic:
            d = d + qi
        else:
            theta = theta + qi
        T = T @ _dh_matrix(alpha, a, theta, d, beta)
    return T @ chain.joints[len(axes) - 1].dh_to_joint @ _attachment_in_link(machine, name, att_err)


def dh_tool_in_workpiece(machine: Machine, commands, errors: ErrorModel | None = None,
                         context: PoseContext | None = None) -> np.ndarray:
    """Tip in the workpiece frame by modified DH (Craig) with Hayati's β, errors projected.

    commands: (N, 5) X, Y, Z [mm], A, C [deg]. Each joint's error twist (its PDGE six-vector of
    eq. 8 evaluated at the pose plus its PIGE screws of eqs. 9–11, in its local frame) is mapped
    to first order onto its own link's (δα, δa, δθ, δd[, δβ]); the link transforms are then
    evaluated exactly with the perturbed parameters. Returns g_tw (N, 4, 4), mm.
    """
    q, joint_err, pige, att_err = _prepare(machine, commands, errors, context)
    twists = _error_twists(joint_err, pige)
    g_bt = _dh_attachment_pose(machine, machine.tip, q, twists, att_err)
    g_bw = _dh_attachment_pose(machine, machine.workpiece, q, twists, att_err)
    return se3.inverse(g_bw) @ g_bt  # eq. 12: g_tw = g_bw⁻¹ g_bt


def dh_parameter_table(machine: Machine) -> pd.DataFrame:
    """Modified DH parameters of both chains, with what each joint's error loses.

    One row per joint: alpha_deg (α_{i-1}), a_mm (a_{i-1}), theta_deg (θ_i offset), d_mm (d_i
    offset), the joint variable, whether Hayati's β is used, and the base-frame directions of the
    rotation and translation components of that joint's error that its link cannot represent
    (at home; they turn with the preceding joints).
    """
    rows = []
    for name, chain in dh_model(machine).items():
        for j in chain.joints:
            R = j.frame_home[:3, :3]
            rot = [0, 2] + ([4] if j.hayati else [])
            lost_r = _complement(j.jacobian[3:, rot])
            lost_t = _complement(j.jacobian[:3, [1, 3]])
            rows.append({
                "chain": name, "joint": j.axis, "variable": "d" if j.prismatic else "θ",
                "alpha_deg": np.degrees(j.alpha), "a_mm": j.a, "theta_deg": np.degrees(j.theta0), "d_mm": j.d0,
                "hayati_beta": j.hayati,
                "lost_rotation_about": _fmt_dirs(lost_r, R), "lost_translation_along": _fmt_dirs(lost_t, R),
            })
    df = pd.DataFrame(rows)
    for c in ("alpha_deg", "a_mm", "theta_deg", "d_mm"):
        df[c] = df[c].round(9) + 0.0  # no "-0.0"
    return df


def _complement(A: np.ndarray) -> np.ndarray:
    """Orthonormal basis (3, m) of the orthogonal complement of A's column space."""
    u, s, _ = np.linalg.svd(A, full_matrices=True)
    rank = int((s > 1e-12).sum())
    return u[:, rank:]


def _fmt_dirs(basis: np.ndarray, R: np.ndarray) -> str:
    """Base-frame directions of a DH-frame basis, as '+x'-style labels where axis-aligned."""
    out = []
    for v in (R @ basis).T:
        k = int(np.argmax(np.abs(v)))
        out.append(f"{'xyz'[k]}" if abs(abs(v[k]) - 1) < 1e-9 else np.array2string(v, precision=3))
    return ", ".join(out) or "-"


def dh_pige_loss(machine: Machine) -> pd.DataFrame:
    """For each PIGE, the fraction (0..1) of its unit error that the DH projection loses.

    0: represented exactly by its joint's DH perturbations; 1: dropped entirely.
    """
    joints = {j.axis: j for chain in dh_model(machine).values() for j in chain.joints}
    rows = []
    for name, (axis, k) in PIGE_SCREWS.items():
        e = np.zeros(6)
        e[k] = 1.0
        j = joints[axis]
        lost = j.lost_twist(e)
        rows.append({"pige": name, "joint": axis, "lost_fraction": float(np.linalg.norm(lost) /
                                                                         np.linalg.norm(j.dh_error_twist(e)))})
    return pd.DataFrame(rows)


def dh_lost_error(machine: Machine, errors: ErrorModel, commands) -> pd.DataFrame:
    """Per joint, mean over the poses of the error the DH projection drops (first order).

    Columns: joint, lost_translation_um (‖v‖ of the lost twist in DH frame i), lost_rotation_arcsec
    (‖ω‖), of_translation_um / of_rotation_arcsec (the same norms of the joint's whole error).
    """
    q, joint_err, pige, _ = _prepare(machine, commands, errors, None)
    twists = _error_twists(joint_err, pige)
    rows = []
    for chain in dh_model(machine).values():
        for j in chain.joints:
            e = twists.get(j.axis, np.zeros(6))
            e = np.broadcast_to(e, (q.shape[0], 6))
            lost, whole = j.lost_twist(e), j.dh_error_twist(e)
            rows.append({
                "joint": j.axis,
                "lost_translation_um": np.linalg.norm(lost[:, :3], axis=1).mean() / UM,
                "lost_rotation_arcsec": np.linalg.norm(lost[:, 3:], axis=1).mean() / ARCSEC,
                "of_translation_um": np.linalg.norm(whole[:, :3], axis=1).mean() / UM,
                "of_rotation_arcsec": np.linalg.norm(whole[:, 3:], axis=1).mean() / ARCSEC,
            })
    return pd.DataFrame(rows)


# ---------------------------------------------------------------------------------------------
# global PoE with fixed screw axes
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class GlobalChain:
    """Global PoE data of a chain: home poses M_i (n, 4, 4), their inverses and the ideal unit
    screws ξ_i = Ad(M_i) ξ_i^local (n, 6), all in the base frame at home."""

    axes: tuple[str, ...]
    home: np.ndarray
    home_inv: np.ndarray
    screws: np.ndarray


def _build_global(machine: Machine) -> dict[str, GlobalChain]:
    out = {}
    for name, chain in (("tool", machine.tool_chain), ("workpiece", machine.workpiece_chain)):
        M = np.stack(_home_poses(machine, chain))
        screws = np.stack([se3.adjoint(Mi) @ machine.axes[a].unit_twist for a, Mi in zip(chain, M, strict=True)])
        out[name] = GlobalChain(tuple(chain), M, se3.inverse(M), screws)
    return out


_GLOBAL_CACHE = _PerMachineCache(_build_global)


def global_screws(machine: Machine) -> dict[str, GlobalChain]:
    """{'tool': GlobalChain, 'workpiece': GlobalChain} of a Machine, derived once per Machine object."""
    return _GLOBAL_CACHE(machine)


def _global_attachment_pose(machine: Machine, name: str, q: np.ndarray, E: dict, att_err: dict) -> np.ndarray:
    """Base-frame pose (N, 4, 4): g = e^{ξ̂'_1 θ_1} ··· e^{ξ̂'_k θ_k} g'(0) (global PoE)."""
    link = machine.attachments[name].link
    axes = machine.parents(link)  # base -> link, empty for "base"
    n = q.shape[0]
    T = np.broadcast_to(np.eye(4), (n, 4, 4))
    if not axes:
        return T @ _attachment_in_link(machine, name, att_err)
    chain = global_screws(machine)["tool" if axes[0] in machine.tool_chain else "workpiece"]
    home_error = None  # E^g_1 ··· E^g_k, the perturbation of g(0)
    for i, axis in enumerate(axes):
        xi = chain.screws[i]
        if axis in E:
            Eg = chain.home[i] @ E[axis] @ chain.home_inv[i]  # joint error moved to the base frame at home
            xi = xi @ np.swapaxes(se3.adjoint(Eg), -1, -2)  # ξ'_i = Ad(E^g_i) ξ_i: only its own error
            home_error = Eg if home_error is None else home_error @ Eg
        T = T @ se3.exp(xi * q[:, AXIS_ORDER.index(axis), None])
    g0 = chain.home[len(axes) - 1] @ _attachment_in_link(machine, name, att_err)
    return T @ (g0 if home_error is None else home_error @ g0)


def global_poe_tool_in_workpiece(machine: Machine, commands, errors: ErrorModel | None = None,
                                 context: PoseContext | None = None) -> np.ndarray:
    """Tip in the workpiece frame by the global PoE with fixed global screw axes.

    commands: (N, 5) X, Y, Z [mm], A, C [deg]. Each joint's error E_i (eqs. 8–11 at the pose) is
    moved to the base frame at home, E^g_i = M_i E_i M_i⁻¹. It perturbs only that joint's global
    screw (ξ'_i = Ad(E^g_i) ξ_i) and the home pose (g'(0) = E^g_1 ··· E^g_n g(0)).
    Returns g_tw (N, 4, 4), mm.
    """
    q, joint_err, pige, att_err = _prepare(machine, commands, errors, context)
    E = _error_transforms(joint_err, pige)
    g_bt = _global_attachment_pose(machine, machine.tip, q, E, att_err)
    g_bw = _global_attachment_pose(machine, machine.workpiece, q, E, att_err)
    return se3.inverse(g_bw) @ g_bt


# ---------------------------------------------------------------------------------------------
# Table 5
# ---------------------------------------------------------------------------------------------

FORMULATIONS: tuple[tuple[str, Callable, str], ...] = (
    (LOCAL_POE, local_poe_tool_in_workpiece,
     "eq. 12: errors in each joint's local frame; the simulator's truth"),
    (DH, dh_tool_in_workpiece,
     "modified DH + Hayati β; each joint's 6 error components projected on its 4 (5) link parameters"),
    (GLOBAL_POE, global_poe_tool_in_workpiece,
     "fixed global screws, each perturbed by its own joint's error; coupling to later axes ignored"),
)


def _best_of(fn: Callable[[], object], repeats: int) -> float:
    """Shortest wall time (s) of ``repeats`` calls, by time.perf_counter."""
    best = np.inf
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def compare_formulations(machine: Machine, errors: ErrorModel, commands, repeats: int = 5) -> pd.DataFrame:
    """The seed's Table 5 on ``commands`` (N, 5): X, Y, Z [mm], A, C [deg].

    One row per formulation with TABLE5_COLUMNS:
    * mean_single_run_ms: evaluating the formulation pose by pose over the commands (one call per
      pose, errors evaluated inside), best of ``repeats`` loops, divided by N; ms per pose.
    * total_300_ms: one batched call for all N poses, best of ``repeats``; ms (N = 300 in the seed).
    * position_error_norm_um, orientation_error_norm_arcsec: mean over poses of ‖t_f − t_true‖
      and ‖log(R_f⁻¹ R_true)‖ of g_tw against the local PoE with the full error model.
    Derived geometry (DH parameters, global screws, link offsets) is built once, before timing.
    """
    cmd = np.atleast_2d(np.asarray(commands, dtype=float))
    truth = forward(machine, cmd, errors).tool_in_workpiece()
    rows = []
    for name, fn, note in FORMULATIONS:
        fn(machine, cmd[:1], errors)  # warm-up: caches of derived geometry, not timed
        total = _best_of(lambda fn=fn: fn(machine, cmd, errors), repeats)
        single = _best_of(lambda fn=fn: [fn(machine, c, errors) for c in cmd], repeats) / cmd.shape[0]
        dt, dR = position_orientation_error(fn(machine, cmd, errors), truth)
        rows.append({
            "formulation": name,
            "mean_single_run_ms": 1e3 * single,
            "total_300_ms": 1e3 * total,
            "position_error_norm_um": float(dt.mean() / UM),
            "orientation_error_norm_arcsec": float(dR.mean() / ARCSEC),
            "note": note,
        })
    return pd.DataFrame(rows, columns=list(TABLE5_COLUMNS))


def format_table5(df: pd.DataFrame) -> str:
    """Markdown table of :func:`compare_formulations`' result."""
    head = ("| formulation | mean single run (ms/pose) | total, N poses batched (ms) | position error norm (µm) "
            "| orientation error norm (″) | note |")
    lines = [head, "|---|---:|---:|---:|---:|---|"]
    for r in df.itertuples(index=False):
        lines.append(f"| {r.formulation} | {r.mean_single_run_ms:.4f} | {r.total_300_ms:.3f} | "
                     f"{r.position_error_norm_um:.3g} | {r.orientation_error_norm_arcsec:.3g} | {r.note} |")
    return "\n".join(lines)

"""Batched rigid-body algebra on SE(3) and se(3).

Conventions (Murray, Li & Sastry): a twist is a 6-vector ``xi = (v, w)`` — linear part first,
then angular; ``hat(xi) = [[w^, v], [0, 0]]``. Translations are in mm, angles in radians.
Every function takes arrays with any leading batch shape ``(...)``: twists ``(..., 6)``,
homogeneous transforms ``(..., 4, 4)``, rotation vectors ``(..., 3)``.

SYNOPSIS
    >>> import numpy as np
    >>> from tasks.core import se3
    >>> T = se3.exp(np.array([1.0, 0, 0, 0, 0, np.pi / 2]))
    >>> np.allclose(se3.log(T), [1.0, 0, 0, 0, 0, np.pi / 2])
    True
"""

from __future__ import annotations

import numpy as np

# Below this rotation angle (rad) the closed forms switch to Taylor series; the series used
# are accurate to ~1e-16 for |theta| < 1e-4.
_SMALL_ANGLE = 1e-4


def skew(w: np.ndarray) -> np.ndarray:
    """so(3) matrix of a 3-vector: ``skew(w) @ x == cross(w, x)``. (..., 3) -> (..., 3, 3)."""
    w = np.asarray(w, dtype=float)
    out = np.zeros((*w.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -w[..., 2], w[..., 1]
    out[..., 1, 0], out[..., 1, 2] = w[..., 2], -w[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -w[..., 1], w[..., 0]
    return out


def hat(xi: np.ndarray) -> np.ndarray:
    """se(3) matrix of a twist (v, w) (eq. 1). (..., 6) -> (..., 4, 4)."""
    xi = np.asarray(xi, dtype=float)
    out = np.zeros((*xi.shape[:-1], 4, 4))
    out[..., :3, :3] = skew(xi[..., 3:])
    out[..., :3, 3] = xi[..., :3]
    return out


def vee(m: np.ndarray) -> np.ndarray:
    """Inverse of :func:`hat`. (..., 4, 4) -> (..., 6)."""
    m = np.asarray(m, dtype=float)
    return np.stack(
        [m[..., 0, 3], m[..., 1, 3], m[..., 2, 3], m[..., 2, 1], m[..., 0, 2], m[..., 1, 0]], axis=-1
    )


def _rotation_coefficients(theta: np.ndarray):
    """A = sin t / t, B = (1 - cos t) / t^2, C = (t - sin t) / t^3, with Taylor series near 0."""
    t2 = theta * theta
    small = theta < _SMALL_ANGLE
    safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - t2 / 6.0, np.sin(safe) / safe)
    b = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(safe)) / (safe * safe))
    c = np.where(small, 1.0 / 6.0 - t2 / 120.0, (safe - np.sin(safe)) / (safe**3))
    return a, b, c


def exp_so3(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: rotation matrix of a rotation vector (rad). (..., 3) -> (..., 3, 3)."""
    w = np.asarray(w, dtype=float)
    theta = np.linalg.norm(w, axis=-1)
    a, b, _ = _rotation_coefficients(theta)
    W = skew(w)
    return np.eye(3) + a[..., None, None] * W + b[..., None, None] * (W @ W)


def exp(xi: np.ndarray) -> np.ndarray:
    """Exponential map se(3) -> SE(3) of twists (v, w) (eq. 3). (..., 6) -> (..., 4, 4).

    The twist already carries the joint displacement: for a unit screw ``s`` moved by ``theta``
    call ``exp(s * theta)``. A pure translation (w = 0) gives ``[[I, v], [0, 1]]``.
    """
    xi = np.asarray(xi, dtype=float)
    v, w = xi[..., :3], xi[..., 3:]
    theta = np.linalg.norm(w, axis=-1)
    a, b, c = _rotation_coefficients(theta)
    W = skew(w)
    W2 = W @ W
    out = np.zeros((*xi.shape[:-1], 4, 4))
    out[..., :3, :3] = np.eye(3) + a[..., None, None] * W + b[..., None, None] * W2
    V = np.eye(3) + b[..., None, None] * W + c[..., None, None] * W2
    out[..., :3, 3] = np.einsum("...ij,...j->...i", V, v)
    out[..., 3, 3] = 1.0
    return out


def _axial(R: np.ndarray) -> np.ndarray:
    """(R - R^T)^∨ = 2 sin(θ) n for rotation matrices (..., 3, 3) -> (..., 3)."""
    return np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)


def log_so3(R: np.ndarray) -> np.ndarray:
    """Rotation vector (rad) of rotation matrices. (..., 3, 3) -> (..., 3).

    Accurate for all angles in [0, pi], including the neighbourhood of pi.
    """
    R = np.asarray(R, dtype=float)
    cos_t = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    axial = _axial(R)
    theta = np.arctan2(np.linalg.norm(axial, axis=-1) / 2.0, cos_t)  # arccos loses digits near 0 and pi
    small = theta < _SMALL_ANGLE
    safe = np.where(small, 1.0, theta)
    # theta / (2 sin theta), with its series near 0
    factor = np.where(small, 0.5 + theta * theta / 12.0, safe / (2.0 * np.sin(safe)))
    w = factor[..., None] * axial
    # Near pi, sin(theta) -> 0 and the axial vector loses precision: take the axis from R + I.
    near_pi = theta > np.pi - 1e-3
    if np.any(near_pi):
        Rp = R[near_pi]
        c = cos_t[near_pi][:, None, None]
        # symmetric part of Rodrigues: (R + R^T)/2 = cos(t) I + (1 - cos(t)) n n^T
        S = ((Rp + np.swapaxes(Rp, -1, -2)) / 2.0 - c * np.eye(3)) / (1.0 - c)
        diag = np.diagonal(S, axis1=-2, axis2=-1)
        k = np.argmax(diag, axis=-1)
        col = np.take_along_axis(S, k[:, None, None].repeat(3, axis=1), axis=2)[..., 0]
        n = col / np.linalg.norm(col, axis=-1, keepdims=True)
        ax = axial[near_pi]
        sign = np.where(np.einsum("...i,...i->...", n, ax) < 0, -1.0, 1.0)
        w[near_pi] = (sign * theta[near_pi])[:, None] * n
    return w


def log(T: np.ndarray) -> np.ndarray:
    """Logarithm SE(3) -> se(3): the twist (v, w) with ``exp(xi) == T``. (..., 4, 4) -> (..., 6)."""
    T = np.asarray(T, dtype=float)
    w = log_so3(T[..., :3, :3])
    theta = np.linalg.norm(w, axis=-1)
    W = skew(w)
    small = theta < _SMALL_ANGLE
    safe = np.where(small, 1.0, theta)
    a, b, _ = _rotation_coefficients(theta)
    # V^-1 = I - W/2 + (1/t^2) (1 - A / (2B)) W^2, series 1/12 + t^2/720 near 0
    d = np.where(small, 1.0 / 12.0 + theta * theta / 720.0, (1.0 - a / (2.0 * b)) / (safe * safe))
    Vinv = np.eye(3) - 0.5 * W + d[..., None, None] * (W @ W)
    v = np.einsum("...ij,...j->...i", Vinv, T[..., :3, 3])
    return np.concatenate([v, w], axis=-1)


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms, using R^T. (..., 4, 4) -> (..., 4, 4)."""
    T = np.asarray(T, dtype=float)
    R = T[..., :3, :3]
    Rt = np.swapaxes(R, -1, -2)
    out = np.zeros_like(T)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, T[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def adjoint(T: np.ndarray) -> np.ndarray:
    """Adjoint matrix Ad_T mapping twists (v, w): ``hat(Ad_T xi) = T hat(xi) T^-1``.

    (..., 4, 4) -> (..., 6, 6), ``[[R, p^ R], [0, R]]``.
    """
    T = np.asarray(T, dtype=float)
    R = T[..., :3, :3]
    out = np.zeros((*T.shape[:-2], 6, 6))
    out[..., :3, :3] = R
    out[..., 3:, 3:] = R
    out[..., :3, 3:] = skew(T[..., :3, 3]) @ R
    return out


def from_rotation_translation(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Homogeneous transforms from rotations (..., 3, 3) and translations (..., 3) in mm."""
    R = np.asarray(R, dtype=float)
    p = np.asarray(p, dtype=float)
    shape = np.broadcast_shapes(R.shape[:-2], p.shape[:-1])
    out = np.zeros((*shape, 4, 4))
    out[..., :3, :3] = R
    out[..., :3, 3] = p
    out[..., 3, 3] = 1.0
    return out


def translation(p: np.ndarray) -> np.ndarray:
    """Pure translations (mm). (..., 3) -> (..., 4, 4)."""
    p = np.asarray(p, dtype=float)
    return from_rotation_translation(np.broadcast_to(np.eye(3), (*p.shape[:-1], 3, 3)), p)


def rot_x(angle: np.ndarray) -> np.ndarray:
    """Rotations about x by ``angle`` (rad). (...) -> (..., 3, 3)."""
    c, s = np.cos(angle), np.sin(angle)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack([o, z, z, z, c, -s, z, s, c], axis=-1).reshape(*np.shape(c), 3, 3)


def rot_y(angle: np.ndarray) -> np.ndarray:
    """Rotations about y by ``angle`` (rad). (...) -> (..., 3, 3)."""
    c, s = np.cos(angle), np.sin(angle)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack([c, z, s, z, o, z, -s, z, c], axis=-1).reshape(*np.shape(c), 3, 3)


def rot_z(angle: np.ndarray) -> np.ndarray:
    """Rotations about z by ``angle`` (rad). (...) -> (..., 3, 3)."""
    c, s = np.cos(angle), np.sin(angle)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack([c, -s, z, s, c, z, z, z, o], axis=-1).reshape(*np.shape(c), 3, 3)


def error_motion(e: np.ndarray) -> np.ndarray:
    """Small error motion of eq. (8): e^{δx} e^{δy} e^{δz} e^{εx} e^{εy} e^{εz}.

    e: (..., 6) = (δx, δy, δz [mm], εx, εy, εz [rad]) in the joint's local frame. The three
    translations commute, so the product is ``[[Rx(εx) Ry(εy) Rz(εz), δ], [0, 1]]``.
    Returns (..., 4, 4).
    """
    e = np.asarray(e, dtype=float)
    ca, cb, cc = np.cos(e[..., 3]), np.cos(e[..., 4]), np.cos(e[..., 5])
    sa, sb, sc = np.sin(e[..., 3]), np.sin(e[..., 4]), np.sin(e[..., 5])
    out = np.zeros((*e.shape[:-1], 4, 4))
    # Rx(a) Ry(b) Rz(c), multiplied out
    out[..., 0, 0], out[..., 0, 1], out[..., 0, 2] = cb * cc, -cb * sc, sb
    out[..., 1, 0] = ca * sc + sa * sb * cc
    out[..., 1, 1] = ca * cc - sa * sb * sc
    out[..., 1, 2] = -sa * cb
    out[..., 2, 0] = sa * sc - ca * sb * cc
    out[..., 2, 1] = sa * cc + ca * sb * sc
    out[..., 2, 2] = ca * cb
    out[..., :3, 3] = e[..., :3]
    out[..., 3, 3] = 1.0
    return out


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle (rad) of rotation matrices (..., 3, 3): the norm of their log."""
    R = np.asarray(R)
    cos_t = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return np.arctan2(np.linalg.norm(_axial(R), axis=-1) / 2.0, cos_t)  # arccos loses digits near 0 and pi


def rot_zyx_deg(rx_deg: float, ry_deg: float, rz_deg: float) -> np.ndarray:
    """Rz(rz) · Ry(ry) · Rx(rx) for angles in degrees: (3, 3). Rotates about x first, then y, then z
    (fixed axes)."""
    rx, ry, rz = np.radians([rx_deg, ry_deg, rz_deg])
    return rot_z(rz) @ rot_y(ry) @ rot_x(rx)

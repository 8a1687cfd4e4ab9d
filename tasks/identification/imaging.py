"""What a camera effect does to a measured pose: the imaging model at pose level.

An effect's ``camera_changes`` (:mod:`tasks.machine.effects`) alters how a camera images its plate: a
focal-length scale (N,) or distortion terms the calibrated 5-parameter model lacks. The pose
measurement (PnP with the calibrated intrinsics) then returns a biased pose. To first order the
bias is the linearised PnP solution for the shift of the dots' undistorted normalised
coordinates:

    x_d' = (1 + s)·x_d + δ_extra(x)                 distorted coordinates the camera records
    δx_u = J_d⁻¹ (x_d' − x_d)                        what undistortion with the calibrated model returns
    b = argmin_b Σ_dots ‖J_pnp b − δx_u‖²            plate-frame twist, T_meas = T · exp(b)

with x the dot's undistorted normalised coordinates (X/Z, Y/Z in the camera frame), J_d the
2×2 Jacobian of the calibrated distortion at x, s = focal_scale − 1, δ_extra the terms of
:class:`tasks.simulation.render.ExtraDistortion` (k4 r⁸ radial, s1..s4 thin prism) and J_pnp (2·D × 6) the
derivative of the dots' normalised coordinates with respect to the plate-frame twist. Every dot
weighs the same, as in an unweighted PnP. A focal scale s mostly moves the plate along the optical
axis (depth × (1 − s)); extra distortion moves and tilts it according to where the plate sits in
the image.

SYNOPSIS
    >>> T_meas = apparent_view(machine, model.effects, "camera1", T_cam_plate, q, context)
"""

from __future__ import annotations

import numpy as np

from tasks.core import se3
from tasks.machine.camera_model import distort_normalised
from tasks.machine.description import Machine

EXTRA_TERMS = ("k4", "s1", "s2", "s3", "s4")


def extra_distortion_shift(xy: np.ndarray, extra: dict) -> np.ndarray:
    """Shift (..., 2) of distorted normalised coordinates by the extra terms, on undistorted ``xy``.

    Same formula as :class:`tasks.simulation.render.ExtraDistortion`: x_d += x k4 r⁸ + s1 r² + s2 r⁴,
    y_d += y k4 r⁸ + s3 r² + s4 r⁴ (dimensionless)."""
    x, y = xy[..., 0], xy[..., 1]
    r2 = x * x + y * y
    k4 = float(extra.get("k4", 0.0)) * r2**4
    dx = x * k4 + float(extra.get("s1", 0.0)) * r2 + float(extra.get("s2", 0.0)) * r2 * r2
    dy = y * k4 + float(extra.get("s3", 0.0)) * r2 + float(extra.get("s4", 0.0)) * r2 * r2
    return np.stack([dx, dy], axis=-1)


def _distortion_jacobian(xy: np.ndarray, distortion, h: float = 1e-7) -> np.ndarray:
    """(..., 2, 2) ∂x_d/∂x of the calibrated distortion at undistorted ``xy`` (central differences)."""
    cols = []
    for k in range(2):
        d = np.zeros(2)
        d[k] = h
        cols.append((distort_normalised(xy + d, distortion) - distort_normalised(xy - d, distortion)) / (2 * h))
    return np.stack(cols, axis=-1)


def imaging_bias(machine: Machine, camera: str, T_cam_plate: np.ndarray, focal_delta: np.ndarray | None,
                 extra: dict | None) -> np.ndarray:
    """(N, 6) plate-frame twist b (mm, rad) with T_meas ≈ T_cam_plate · exp(b).

    T_cam_plate: (N, 4, 4) the plate in the camera frame (mm). focal_delta: (N,) focal_scale − 1
    (None: no change). extra: {k4, s1..s4} extra distortion (None: none)."""
    T = np.asarray(T_cam_plate, dtype=float)
    n = T.shape[0]
    cam = machine.cameras[camera]
    dots = machine.plates[machine.views[camera]].dot_centres_mm()  # (D, 3) plate frame
    R, t = T[:, :3, :3], T[:, :3, 3]
    P = np.einsum("nij,dj->ndi", R, dots) + t[:, None, :]  # (N, D, 3) camera frame
    xy = P[..., :2] / P[..., 2:3]  # (N, D, 2) undistorted normalised
    shift = np.zeros_like(xy)  # distorted-coordinate shift
    if focal_delta is not None:
        shift += np.asarray(focal_delta, dtype=float)[:, None, None] * distort_normalised(xy, cam.distortion)
    if extra:
        shift += extra_distortion_shift(xy, extra)
    if not np.any(shift):
        return np.zeros((n, 6))
    Jd = _distortion_jacobian(xy, cam.distortion)  # (N, D, 2, 2)
    dxu = np.linalg.solve(Jd, shift[..., None])[..., 0]  # (N, D, 2)
    # dP/d(v, w) for T exp(b): dP = R v - R [p]x w   -> (N, D, 3, 6)
    dP = np.concatenate([np.broadcast_to(R[:, None], (n, dots.shape[0], 3, 3)),
                         -np.einsum("nij,djk->ndik", R, se3.skew(dots))], axis=-1)
    z = P[..., 2][..., None]  # (N, D, 1)
    Jx = (dP[..., 0, :] - xy[..., 0:1] * dP[..., 2, :]) / z  # (N, D, 6)
    Jy = (dP[..., 1, :] - xy[..., 1:2] * dP[..., 2, :]) / z
    J = np.concatenate([Jx, Jy], axis=1)  # (N, 2D, 6)
    y = np.concatenate([dxu[..., 0], dxu[..., 1]], axis=1)  # (N, 2D)
    JtJ = np.einsum("nki,nkj->nij", J, J)
    Jty = np.einsum("nki,nk->ni", J, y)
    return np.linalg.solve(JtJ, Jty[..., None])[..., 0]


def camera_effect_bias(machine: Machine, effects, camera: str, T_cam_plate: np.ndarray, q: np.ndarray,
                       context) -> np.ndarray | None:
    """(N, 6) imaging bias of every camera effect in ``effects`` for ``camera``; None when they change nothing.

    q: (N, 5) joint values (mm, rad) of the N poses; context: their :class:`tasks.machine.context.PoseContext`."""
    if not effects:
        return None
    from tasks.machine.effects import camera_changes

    ch = camera_changes(effects, camera, machine, q, context)
    delta = np.asarray(ch["focal_scale"], dtype=float) - 1.0
    extra = ch["extra_distortion"]
    if not np.any(delta) and not extra:
        return None
    return imaging_bias(machine, camera, T_cam_plate, delta if np.any(delta) else None, extra)


def apparent_view(machine: Machine, effects, camera: str, T_cam_plate: np.ndarray, q: np.ndarray,
                  context) -> np.ndarray:
    """The pose ``camera`` would measure (N, 4, 4) given the true ``T_cam_plate`` and the camera effects."""
    b = camera_effect_bias(machine, effects, camera, T_cam_plate, q, context)
    return T_cam_plate if b is None else T_cam_plate @ se3.exp(b)


def imaging_corrected(machine: Machine, model, meas):
    """``meas`` with each measured pose corrected for the imaging bias of ``model``'s camera effects,
    T_meas · exp(−b) with b evaluated at the measured pose: what the PDGE extraction should read
    when the model explains part of the poses by imaging. Returns ``meas`` itself when nothing changes."""
    if not getattr(model, "effects", None):
        return meas
    from tasks.identification.measurements import Measurements

    q = machine.commands_to_internal(meas.commands)
    cams = meas.table.camera.to_numpy()
    T = meas.T
    for cam in np.unique(cams):
        rows = np.flatnonzero(cams == cam)
        b = camera_effect_bias(machine, model.effects, str(cam), meas.T[rows], q[rows], meas.context.take(rows))
        if b is not None:
            T = T.copy() if T is meas.T else T
            T[rows] = meas.T[rows] @ se3.exp(-b)
    return meas if T is meas.T else Measurements(meas.table, T, meas.cov, meas.context)

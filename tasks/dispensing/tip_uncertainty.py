"""The model uncertainty of the tip after the dispensing test has folded its tip offset in.

After compensation the tip misses by what the identified model gets wrong. To first order, with
the machine's truth M̂ + δ (δ the model's error, which the propagation of
:mod:`tasks.identification.uncertainty` samples by its re-fitted models: camera directions and
noise draws), the true tip at the compensated commands q_i of a validation pose is

    tip_i = desired_i + Δ_i(δ),           Δ_i(δ): how δ moves the tip at q_i (workpiece frame).

Nearly all of Δ is one constant tool-frame vector (the intrinsics reach the tip that way), and
that is what the dispensing test measures. Its dots land where the true tip is (the horizontal
part, P_j), so a dot dispensed at commands q_j is off the model's prediction by P_j Δ_j(δ) + ε_j
(ε: the dot's measurement noise), and the tip fit, linear in its data, returns

    t̂ = G [P Δ(δ) + ε],                   G: the first three rows of (JᵀJ)⁻¹Jᵀ (the sin A term fitted beside).

G P Δ(δ) is the constant part of Δ plus whatever its pose-varying part averages to, in the fit's
weighting, over the dispensing poses (not the validation poses). Compensating with t̂ folded into
the tool offset moves the tip by −R_i t̂ (R_i: the tip frame at q_i), so the error after the tip
fit is

    e_i = Δ_i(δ) − R_i G P Δ(δ) − R_i G ε.

The model error and the dot noise are independent, so

    Cov e_i = Cov_δ[Δ_i(δ) − R_i G P Δ(δ)] + R_i Σ_t R_iᵀ,

the first term over the same re-fits as the model uncertainty after compensation (the constant
part cancels re-fit by re-fit, the pose-varying part and what the dispensing poses make of it
stay, cross terms included), the second the tip fit's covariance Σ_t = σ²(JᵀJ)⁻¹ restricted to t,
with σ² from the dot residuals. Those residuals also carry the pose-varying model error at the
dispensing poses, which the first term already counts: Σ_t states the dot noise slightly high
(the pose-varying error is a few tenths of a micron per axis against 1.2 µm of dot noise). A tool
offset turns nothing: the orientation's uncertainty is the model's at the new commands.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks.core.units import UM
from tasks.dispensing.tip import landing_points, tip_fit_gain
from tasks.identification.uncertainty import (
    PropagatedUncertainty,
    change_variance,
    tip_error_norms,
    tip_pose_changes,
)
from tasks.machine.description import Machine
from tasks.machine.error_model import ErrorModel
from tasks.machine.kinematics import forward


def after_tip_changes(machine: Machine, model: ErrorModel, models: list[ErrorModel], fit_commands: np.ndarray,
                      commands: np.ndarray) -> np.ndarray:
    """(K, N, 6) for each of ``models`` (the truth, were it that model), the tip pose error after
    the tip fit at ``commands`` (N, 5) (the validation poses compensated with the tip folded in):
    how far the model moves the tip there, less the tip-frame offset the tip fit would take from
    the dots it moves at ``fit_commands`` (M, 5) (the dispensed commands of the dots the fit used).
    Position mm (workpiece frame), rotation rad (tip frame); ``model`` is the identified model
    the tip fit started from (its tool offset before the fit)."""
    gain = tip_fit_gain(machine, model, fit_commands)  # (3, 2M)
    base = landing_points(machine, model, fit_commands)
    R = forward(machine, commands, model).tool_in_workpiece()[:, :3, :3]
    out = tip_pose_changes(machine, model, models, commands)
    for k, m in enumerate(models):
        taken = gain @ ((landing_points(machine, m, fit_commands) - base).ravel() / UM)  # µm, tip frame
        out[k, :, :3] -= R @ taken * UM
    return out


@dataclass(frozen=True)
class AfterTipUncertainty:
    """The model uncertainty of the tip after the tip fit at N poses, by source: per-component
    variances (N, 6) of the tip pose error (position mm², workpiece frame; rotation rad², tip frame)
    from the camera directions, the noise draws and the tip fit's own dot noise (position only);
    ``constant_covariance_um2`` (3, 3): the covariance of the constant tool-frame part of the error
    (its mean over the poses in the tip frame, µm²), to read the true constant part against."""

    camera: np.ndarray
    noise: np.ndarray
    tip_fit: np.ndarray
    constant_covariance_um2: np.ndarray

    def norms(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Expected tip error norms (µm, arcsec, arcsec) (N,) ×3: position, whole orientation, tool
        direction (:func:`tasks.identification.uncertainty.tip_error_norms`)."""
        return tip_error_norms(self.camera + self.noise + self.tip_fit)

    def position_parts_um(self) -> dict[str, float]:
        """{source: rms over the poses of its expected position error norm (µm)}: which term makes u."""
        return {k: float(np.sqrt(np.mean(v[:, :3].sum(axis=1))) / UM)
                for k, v in (("camera", self.camera), ("noise", self.noise), ("tip_fit", self.tip_fit))}


def after_tip_uncertainty(machine: Machine, model: ErrorModel, prop: PropagatedUncertainty,
                          fit_commands: np.ndarray, fit_covariance_um2: np.ndarray,
                          commands: np.ndarray) -> AfterTipUncertainty:
    """The model uncertainty of the tip after the dispensing test's tip fit at ``commands`` (N, 5),
    the validation poses compensated with the fitted offset folded in: the model's uncertainty
    (``prop``, propagated for ``model``, the identified model before the fit) with its constant
    tool-frame part replaced by what the tip fit leaves (module docstring). fit_commands: (M, 5)
    the dispensed commands of the dots the fit used; fit_covariance_um2: (3, 3) the fit's
    covariance of the offset (µm², tip frame: :attr:`tasks.dispensing.tip.TipFit.covariance_um2`)."""
    fit_commands = np.asarray(fit_commands, dtype=float)
    cov_t = np.asarray(fit_covariance_um2, dtype=float)
    n_camera = len(prop.camera_models)
    changes = after_tip_changes(machine, model, [*prop.camera_models, *prop.noise_models], fit_commands, commands)
    camera, noise = changes[:n_camera], changes[n_camera:]
    R = forward(machine, commands, model).tool_in_workpiece()[:, :3, :3]
    tip_fit = np.zeros((len(commands), 6))
    tip_fit[:, :3] = np.einsum("nij,jk,nik->ni", R, cov_t, R) * UM**2

    def constant(changes: np.ndarray) -> np.ndarray:  # (K, 3) µm: the mean over the poses in the tip frame
        return np.einsum("nji,knj->kni", R, changes[..., :3]).mean(axis=1) / UM

    c_cam, c_noise = constant(camera), constant(noise)
    cov_c = c_cam.T @ c_cam + cov_t
    if len(c_noise) >= 2:
        cov_c += np.cov(c_noise.T, ddof=1)
    empty = np.zeros((0, len(commands), 6))
    return AfterTipUncertainty(change_variance(camera, empty), change_variance(empty, noise), tip_fit, cov_c)

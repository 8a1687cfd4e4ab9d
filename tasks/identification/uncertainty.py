"""The standard uncertainty of every identified parameter, with what the LM's covariance leaves out.

SYNOPSIS
    >>> prop = propagate_uncertainty(machine, result, measurements, sensitivities, intrinsics_cov)
    >>> prop.combined                    # (P,) internal units: √(camera² + noise²)
    >>> expected_tip_errors(machine, result.model, prop, commands)   # µm, arcsec per pose

The LM of eq. 22 reports σ²(JᵀJ)⁻¹: the spread of the constant parameters if the five-axis poses
were the only noisy input and the PDGE profiles were exact. Two inputs it holds fixed are not:

* **the camera self-calibration.** Every pose of a camera shares its intrinsics' error. Each
  eigen-direction of the intrinsics covariance Σ_θ (:mod:`tasks.vision.intrinsics_uncertainty`) is
  applied at one standard deviation to every pose of that camera, T ← T · exp(S_k dθ), and the
  whole calibration (PDGE extraction and constant fit, alternated) is re-run. The sum of the
  squared parameter changes is the camera contribution (the GUM law of propagation with
  sensitivities by finite differences). 8 re-fits per camera.
* **the PDGE profiles.** They are extracted from the sweeps' noisy poses and then held fixed in
  the fit. A parametric bootstrap carries the pose noise through both: each draw adds noise with
  the error model the fit weights by, every pose's own covariance plus the floor (C_k + C_floor:
  0.1 µm, 1″; no image is believed better than that), to every pose and re-runs the calibration;
  the sample standard deviation of the re-fitted parameters is the noise contribution (it
  contains the LM's). Where the fit's residuals say that the poses scatter more than that
  (σ² > 1), each draw is scaled by √σ², as the LM's σ²(JᵀJ)⁻¹ is (the Birge ratio).
  Each draw chooses the smoothers' roughness again by GCV, as the calibration does: the choice
  follows the noise, and on the full-size campaign it is most of the spread of the A and C
  location terms (δAY spread 14 times, βCY 3.4 times that with the roughness held, in full
  re-calibrations from re-drawn pixel noise; docs/calibrate.md).

A re-fit of a calibration that ended with the joint step (:mod:`tasks.identification.joint_fit`)
is that step's Gauss–Newton from the identified solution (:func:`_joint_refit`). Otherwise (a fit
with added effects) it is the alternation of :func:`~tasks.identification.pige_identification.alternate`
linearised about the identified solution: it starts there and replaces each constant fit by a
Gauss–Newton step with the fit's own Jacobian (:func:`_linearised_refit`); the camera re-fits hold
the PDGE smoothers' roughness (:mod:`tasks.identification.smoothing`), the noise draws choose it
again. It measures how this estimator moves with its inputs (the 33 re-fits of the demo take
about 19 s on 2 cores). tests/identification/test_identification.py checks its camera part against re-running
the whole calibration. Units: the parameters' internal units (mm, rad).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

from tasks.core import se3
from tasks.core.units import ARCSEC, UM
from tasks.identification.imaging import imaging_corrected
from tasks.identification.levenberg_marquardt import right_singular
from tasks.identification.measurements import Measurements
from tasks.identification.parameters import apply_parameters
from tasks.identification.pdge_extraction import extract_pdges
from tasks.identification.pige_identification import (
    COV_FLOOR,
    IDENTIFICATION_CAMERA,
    IDENTIFICATION_STAGES,
    CalibrationResult,
    pose_residuals,
    whitening,
)
from tasks.machine.description import Machine
from tasks.machine.error_model import ErrorModel
from tasks.machine.kinematics import forward

NOISE_DRAWS = 16
"""Bootstrap draws: the standard deviation from 16 draws is good to about ±18 % (1/√(2·15))."""
UNCERTAINTY_SEED = 20261121


@dataclass
class PropagatedUncertainty:
    """names: (P,) the parameters (``result.pige.specs``). fit: (P,) the LM's standard uncertainty.
    camera: (P,) from the intrinsics of every camera; by_camera: {camera: (P,)}. noise: (P,) from
    the pose noise through the PDGE extraction and the fit (NaN without draws). camera_models,
    noise_models: the re-fitted models (for :func:`expected_tip_errors`). All internal units."""

    names: list[str]
    fit: np.ndarray
    camera: np.ndarray
    by_camera: dict[str, np.ndarray]
    noise: np.ndarray
    camera_models: list[ErrorModel]
    noise_models: list[ErrorModel]

    @property
    def combined(self) -> np.ndarray:
        """(P,) √(camera² + noise²), the LM's uncertainty standing in for noise without draws."""
        noise = np.where(np.isfinite(self.noise), self.noise, self.fit)
        return np.sqrt(self.camera**2 + noise**2)


LINEARISED_ROUNDS = 10
"""Rounds of the linearised alternation: its slowest mode (an A-axis offset against the A
profile) shrinks by about 0.8 per round, so 10 rounds carry about 90 % of a perturbation."""


def _linearised_refit(machine: Machine, result: CalibrationResult, measurements: Measurements,
                      rounds: int = LINEARISED_ROUNDS) -> Callable[..., tuple]:
    """(``measurements`` moved, reselect_smoothing) -> (parameter values (P,), model): the
    alternation of :func:`tasks.identification.pige_identification.alternate` (or of the fit with
    added effects, :mod:`tasks.identification.effect_fit`) from ``result``'s solution, each constant fit
    replaced by a Gauss–Newton step with the fit's own Jacobian in its identifiable subspace (the
    perturbations are small: a linear response). Each round extracts the PDGEs from the sweep
    poses corrected for the model's imaging bias, as the fit does, with the PDGE smoothers'
    roughness held at ``result``'s, or chosen again by GCV in every round (reselect_smoothing), as
    the calibration itself chooses it."""
    if result.joint:
        return _joint_refit(machine, result, measurements)
    specs, fit = result.pige.specs, result.pige.fit
    steps = np.array([s.jacobian_step for s in specs])
    s, Vt = right_singular(fit.jacobian * steps)  # natural units, as the LM took its subspace
    k = fit.x.size - fit.null_space.shape[1]
    V = Vt[:k].T
    gain = steps[:, None] * (V @ np.diag(1.0 / s[:k] ** 2) @ V.T @ (fit.jacobian * steps).T)  # (P, M)
    # what the parameters are added to: the identified model less its parameters (for a fit with
    # added effects, its effects with the fitted amplitudes at zero), with the PDGEs it was
    # extracted with (the base's: none from the sweeps)
    extraction = result.extraction_model or ErrorModel()
    skeleton = replace(apply_parameters(result.model, specs, -fit.x), pdge=dict(extraction.pdge))

    # a perturbation moves the poses, not their covariances: one whitening serves every re-fit
    W = whitening(measurements.stage(*IDENTIFICATION_STAGES, camera=IDENTIFICATION_CAMERA).cov)

    def refit(m: Measurements, reselect_smoothing: bool = False) -> tuple:
        poses = m.stage(*IDENTIFICATION_STAGES, camera=IDENTIFICATION_CAMERA)
        x, ext = fit.x, extraction
        smoothing = None if reselect_smoothing else result.pdge.smoothing
        for _ in range(rounds):
            profiles = extract_pdges(machine, ext, imaging_corrected(machine, ext, m),
                                     smoothing=smoothing).profiles
            with_pdge = replace(skeleton, pdge={**skeleton.pdge, **profiles})
            r = np.einsum("nij,nj->ni", W, pose_residuals(machine, apply_parameters(with_pdge, specs, x), poses))
            x = x - gain @ r.ravel()
            ext = apply_parameters(skeleton, specs, x)
        return x, apply_parameters(with_pdge, specs, x)

    return refit


def _joint_refit(machine: Machine, result: CalibrationResult, measurements: Measurements) -> Callable[..., tuple]:
    """The re-fit of a calibration that ended with the joint step (:mod:`tasks.identification.joint_fit`):
    that step's Gauss–Newton from ``result``'s solution on the moved poses, its penalties held or
    (reselect_smoothing) set again from the moved sweeps (GCV's roughness), as the calibration sets them."""
    from tasks.identification.joint_fit import JointStep

    fit = result.pige.fit
    step = JointStep.build(machine, result.pige.specs, result.model, fit.x, fit.jacobian, fit.null_space,
                           result.pdge.smoothing, measurements)
    extraction = result.extraction_model or ErrorModel()

    def refit(m: Measurements, reselect_smoothing: bool = False) -> tuple:
        solver = step
        if reselect_smoothing:
            again = extract_pdges(machine, extraction, m)
            solver = step.with_penalty(again.smoothing)
        x, profiles = solver.solve(m)
        return x, solver.model_at(x, profiles)

    return refit


def _moved(meas: Measurements, twist: np.ndarray) -> Measurements:
    """``meas`` with every pose moved by the plate-frame twist (N, 6): T · exp(δ̂)."""
    return Measurements(meas.table, meas.T @ se3.exp(twist), meas.cov, meas.context)


def propagate_uncertainty(machine: Machine, result: CalibrationResult, measurements: Measurements,
                          sensitivities: np.ndarray | None = None,
                          intrinsics_cov: Mapping[str, np.ndarray] | None = None,
                          draws: int = NOISE_DRAWS, seed: int = UNCERTAINTY_SEED,
                          workers: int = 2) -> PropagatedUncertainty:
    """Camera and noise contributions to the uncertainty of ``result``'s parameters (module docstring).

    measurements: what ``result`` was calibrated from. sensitivities: (N, 6, 8) ∂δ/∂θ of its poses
    (:func:`tasks.vision.intrinsics_uncertainty.pose_sensitivities`). intrinsics_cov: {camera: (8, 8)};
    a camera without one (or with a NaN one) contributes nothing; without both, the pose noise alone
    (poses without images, as in the pose-level tests). draws: bootstrap draws (0: none).
    Deterministic for a given seed. workers: re-fits run side by side in threads."""
    refit = _linearised_refit(machine, result, measurements)
    # the response is measured against the same iteration on the unperturbed measurements: what is
    # left of the alternation's own convergence cancels
    x0, _ = refit(measurements)
    cams = measurements.table["camera"].to_numpy()
    jobs: list[tuple[str, np.ndarray]] = []
    camera_covs = intrinsics_cov if sensitivities is not None and intrinsics_cov else {}
    for cam, cov in camera_covs.items():
        if not np.all(np.isfinite(cov)) or not np.any(cams == cam):
            continue
        w, V = np.linalg.eigh(cov)
        for k in range(w.size):
            twist = sensitivities @ (np.sqrt(max(w[k], 0.0)) * V[:, k])  # (N, 6)
            twist[cams != cam] = 0.0
            jobs.append((cam, twist))
    rng = np.random.default_rng(seed)
    birge = np.sqrt(max(result.pige.fit.sigma2, 1.0))
    # the error model the fit weights by (C + C_floor), which its σ² is measured against
    L = birge * np.linalg.cholesky(measurements.cov + COV_FLOOR)
    for _ in range(draws):
        jobs.append(("noise", np.einsum("nij,nj->ni", L, rng.standard_normal((len(measurements), 6)))))
    with ThreadPoolExecutor(max_workers=max(workers, 1)) as pool:
        fits = list(pool.map(lambda job: refit(_moved(measurements, job[1]), job[0] == "noise"), jobs))
    labels = [label for label, _ in jobs]
    delta = np.array([x - x0 for x, _ in fits]).reshape(len(fits), x0.size)
    by_camera = {cam: np.sqrt(np.nansum(delta[[lab == cam for lab in labels]] ** 2, axis=0))
                 for cam in dict.fromkeys(lab for lab in labels if lab != "noise")}
    camera = np.sqrt(sum((u**2 for u in by_camera.values()), np.zeros(x0.size)))
    noisy = delta[[lab == "noise" for lab in labels]]
    noise = noisy.std(axis=0, ddof=1) if len(noisy) >= 2 else np.full(x0.size, np.nan)
    return PropagatedUncertainty(
        names=[s.name for s in result.pige.specs], fit=result.pige.fit.uncertainty, camera=camera,
        by_camera=by_camera, noise=noise,
        camera_models=[m for (x, m), lab in zip(fits, labels, strict=True) if lab != "noise"],
        noise_models=[m for (x, m), lab in zip(fits, labels, strict=True) if lab == "noise"])


def tool_frame_offset_changes(machine: Machine, model: ErrorModel, models: list[ErrorModel],
                              commands: np.ndarray, R_tool: np.ndarray) -> np.ndarray:
    """(K, 3) µm: for each of ``models``, the constant tool-frame part of how far it moves the tip
    from where ``model`` puts it at ``commands`` (N, 5): the mean over the poses of the change of the
    tip position expressed in the tool frame (R_tool (N, 3, 3): tool frame -> workpiece frame)."""
    ref = forward(machine, commands, model).tool_in_workpiece()[:, :3, 3]
    out = np.zeros((len(models), 3))
    for k, m in enumerate(models):
        d = (forward(machine, commands, m).tool_in_workpiece()[:, :3, 3] - ref) / UM
        out[k] = np.einsum("nji,nj->ni", R_tool, d).mean(axis=0)
    return out


def tool_frame_offset_covariance(machine: Machine, model: ErrorModel, prop: PropagatedUncertainty,
                                 commands: np.ndarray, R_tool: np.ndarray) -> np.ndarray:
    """(3, 3) covariance (µm²) of the constant tool-frame part of the modelled tip position at
    ``commands`` (N, 5) (:func:`tool_frame_offset_changes`), over the camera directions (summed
    outer products) and the noise draws (their sample covariance). What compensation leaves of the
    model's uncertainty is almost all this one vector (the intrinsics reach the tip as a constant
    offset), so the true constant tool-frame error after compensation, c, is to be read against
    it: cᵀ Σ⁻¹ c is χ² with 3 degrees of freedom if the stated uncertainty is right."""
    camera = tool_frame_offset_changes(machine, model, prop.camera_models, commands, R_tool)
    cov = camera.T @ camera
    if len(prop.noise_models) >= 2:
        noise = tool_frame_offset_changes(machine, model, prop.noise_models, commands, R_tool)
        cov += np.cov(noise.T, ddof=1)
    return cov


def tip_pose_changes(machine: Machine, model: ErrorModel, models: list[ErrorModel],
                     commands: np.ndarray) -> np.ndarray:
    """(K, N, 6) how far each of ``models`` moves the modelled tip pose from where ``model`` puts it
    at ``commands`` (N, 5): position (mm, workpiece frame), then the rotation vector (rad, tip frame,
    whose z is the tool axis)."""
    ref = forward(machine, commands, model).tool_in_workpiece()
    out = np.zeros((len(models), len(commands), 6))
    for k, m in enumerate(models):
        T = forward(machine, commands, m).tool_in_workpiece()
        out[k, :, :3] = T[:, :3, 3] - ref[:, :3, 3]
        out[k, :, 3:] = se3.log_so3(np.swapaxes(ref[:, :3, :3], 1, 2) @ T[:, :3, :3])
    return out


def change_variance(camera: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """(N, C) the variance a propagation states from the changes its re-fits make, camera (K, N, C)
    and noise (D, N, C): the camera directions summed, the noise draws' sample variance (none with
    fewer than 2 draws)."""
    var = (camera**2).sum(axis=0)
    if len(noise) >= 2:
        var = var + np.var(noise, axis=0, ddof=1)
    return var


def tip_error_norms(var: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Expected norms (µm, arcsec, arcsec) (N,) ×3 of position, whole orientation and tool direction
    (the rotation's tip-frame x and y) from per-component variances (N, 6) of
    :func:`tip_pose_changes` (mm², rad²)."""
    return (np.sqrt(var[:, :3].sum(axis=1)) / UM, np.sqrt(var[:, 3:].sum(axis=1)) / ARCSEC,
            np.sqrt(var[:, 3:5].sum(axis=1)) / ARCSEC)


def expected_tip_errors(machine: Machine, model: ErrorModel, prop: PropagatedUncertainty,
                        commands: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Expected tip error norms (µm, arcsec, arcsec) (N,) ×3 at ``commands`` (N, 5) from the
    identified model's uncertainty alone: position, whole orientation and tool direction, the rms
    change of the modelled tip pose (:func:`tip_pose_changes`) over the camera directions (summed)
    and the noise draws (variance). After compensation this is what the tip would miss by if the
    model were right but for its uncertainty."""
    var = change_variance(tip_pose_changes(machine, model, prop.camera_models, commands),
                          tip_pose_changes(machine, model, prop.noise_models, commands))
    return tip_error_norms(var)

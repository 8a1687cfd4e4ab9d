"""PDGE profiles and constant parameters in one penalised least squares (the joint step).

SYNOPSIS
    >>> step = JointStep.build(machine, result, measurements)   # about the alternation's solution
    >>> x, profiles = step.solve(measurements)                   # constants (P,), {axis: profile}

Why. The alternation (:func:`tasks.identification.pige_identification.alternate`) extracts each
profile from its own sweep and then holds it fixed in the fit of the constants. A sweep measures
the error motion where its plate is, and the profile is wanted at the joint's frame: camera 2 sees
plate b 150 mm along the A axis from A's frame, camera 1 plate a 40 mm above C's, so a plate's
tilt noise (tens of arcsec per image) becomes tens of µm of translation noise in the profile (50
µm per image on A). No smoothing of one sweep can remove it, and the constants then absorb what
the profile gets wrong (σ² of 13–34 on the tests' small plan with noise on the A sweep alone).
The five-axis poses see plate a next to both rotary axes' frames and measure the same error
motions directly, laterally to a fraction of a µm. So every profile is estimated from every
image that moves its axis: the sweeps *and* the five-axis poses, in one least squares with the
constants.

What is solved. About the alternation's solution (the model M₀: constants x₀, profiles v₀ at
their sweep positions), with r the whitened pose residuals of eq. 20 of camera 1's identification
poses and of the other cameras' sweeps,

    min ‖r + J_x δx + Σ_j J_j G_j c_j + J_ν ν‖² + Σ_j (v₀ⱼ + G_j c_j)ᵀ P_j (v₀ⱼ + G_j c_j)

- J_x: the constant fit's Jacobian (camera 1's rows; the other cameras' rows do not see them).
- J_j: the residuals' response to axis j's six error-motion components at each knot: the response
  to a constant change of the joint's error (central differences, one per component) times the
  natural cubic spline's weight of each knot at the pose's axis position (a profile is linear in
  its knot values).
- G_j: a basis of the profile changes that keep the gauge of :mod:`.pdge_extraction` (zero at home,
  orthogonal to the axis' line-error signatures): what it excludes, the constants carry.
- ν: the constant poses at the ends of a chain outside the fit (camera mount, plate mount: 12, as
  in :func:`tasks.analysis.residuals.chain_constant_part`) and the line errors of the axis it sweeps (its
  gauge as seen by that camera), fitted to that camera's rows only.
- P_j: the smoothing spline's roughness penalty per component, λ_jc K_j / s²_jc with the λ that the
  sweep's GCV chose and s² the variance of a position's mean that the rows' own whitening implies
  (:func:`sweep_variances`: the pose covariances, floor included, carried to the error motion).
  That is the whitened form of the spline's own criterion, Σ (y − f)² / s² + (λ / s²) ∫ f''², so
  a sweep alone gives the alternation's profile. The scale must be the whitening's, not the sweep's
  scatter: the data rows are weighed by the stated covariances, and a penalty scaled by another
  variance weighs the spline's prior against them by the ratio of the two. On exact poses (the
  scatter is the profile's own step-to-step change, far below the stated noise) that ratio was
  3.6·10⁴ on C's εx and 1.2·10⁶ on its δy: C's εx, smoothed by GCV's λ to 0.9″ RMS off the
  truth, was held there, and the unpenalised profiles of X, Y and Z took up the five-axis poses'
  residual (up to 5.9″ of X's εx, 1.6 µm at held-out tips; tests/identification/test_identification.py).

Gauss–Newton with J held, three steps, then the constant fit's LM from the result (its diagnostics
and the Jacobian at the new point), twice: the system is rebuilt about the first solution, because
the alternation's solution it starts from can be 100 standard uncertainties away. Units: internal (mm, rad) for
x; knot values in file units (µm, arcsec) inside the solve.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.linalg import cho_solve

from tasks.core import se3
from tasks.identification.measurements import Measurements
from tasks.identification.parameters import ParamSpec, apply_parameters
from tasks.identification.pdge_extraction import (
    COMPONENT_COLUMNS,
    PdgeResult,
    TabulatedProfile,
    line_error_signatures,
)
from tasks.identification.pige_identification import (
    IDENTIFICATION_CAMERA,
    IDENTIFICATION_STAGES,
    PigeFit,
    identify_pige,
    pose_residuals,
    whitening,
)
from tasks.identification.smoothing import penalty_matrix
from tasks.machine.description import AXIS_ORDER, Machine
from tasks.machine.error_model import COMPONENT_SCALE, ErrorModel

GAUSS_NEWTON_STEPS = 3


def joint_rows(measurements: Measurements) -> np.ndarray:
    """(N,) bool: the rows the joint step uses: camera 1's identification poses and every other
    camera's sweep images."""
    t = measurements.table
    fit_rows = t.stage.isin(IDENTIFICATION_STAGES) & (t.camera == IDENTIFICATION_CAMERA)
    other_sweeps = (t.stage == "pdge") & (t.camera != IDENTIFICATION_CAMERA)
    return (fit_rows | other_sweeps).to_numpy()


def knot_weights(positions: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(N, K) weights of the natural cubic spline through K knots at ``positions`` evaluated at
    ``q`` (N,) (clipped to the knots' range, as :class:`TabulatedProfile` is): value = weights @ knots."""
    spline = CubicSpline(positions, np.eye(positions.size), axis=0, bc_type="natural")
    return spline(np.clip(q, positions[0], positions[-1]))


def gauge_complement(machine: Machine, axis: str, positions: np.ndarray) -> np.ndarray:
    """(6K, p) orthonormal basis (file units, knot-major: index m·6 + c) of the profile changes
    that are zero at home and orthogonal to the axis' line-error signatures."""
    K = positions.size
    sig = line_error_signatures(machine, axis, positions) / COMPONENT_SCALE[None, :, None]  # (K, 6, m)
    home = int(np.argmin(np.abs(positions)))
    at_home = np.zeros((6, K * 6))
    at_home[np.arange(6), home * 6 + np.arange(6)] = 1.0
    constraints = np.vstack([at_home, sig.reshape(K * 6, -1).T])  # (6 + m, 6K)
    q, r = np.linalg.qr(constraints.T, mode="complete")
    rank = int(np.sum(np.abs(np.diag(r)) > np.abs(r).max() * 1e-10))
    return q[:, rank:]


@dataclass
class _Axis:
    axis: str
    positions: np.ndarray  # (K,) internal units
    G: np.ndarray  # (6K, p)
    penalty: np.ndarray  # (p, p) Gᵀ P G
    penalty_full: np.ndarray  # (6K, 6K) P
    cols: slice
    variance: np.ndarray  # (6,) variance of a position's mean (file units²), from the whitening


@dataclass
class JointStep:
    """The linear system of the module docstring, built about one solution. Use :meth:`build`."""

    machine: Machine
    specs: list[ParamSpec]
    skeleton: ErrorModel  # the model without its parameters and profiles
    x0: np.ndarray
    profiles0: dict[str, TabulatedProfile]
    axes: list[_Axis]
    rows: np.ndarray
    W: np.ndarray  # (n, 6, 6)
    J: np.ndarray  # (6n, P + Σp + n_ν)
    JtJ: np.ndarray
    steps: np.ndarray  # (P,) natural units of x
    n_x: int
    null_x: np.ndarray  # (P, k) natural-unit directions of x the fit does not identify
    _factor: np.ndarray | None = None

    @classmethod
    def build(cls, machine: Machine, specs: list[ParamSpec], model: ErrorModel, x: np.ndarray,
              fit_jacobian: np.ndarray, null_space: np.ndarray, smoothing: dict[str, np.ndarray],
              measurements: Measurements) -> JointStep:
        """About ``model`` (constants ``x`` (P,) internal units included, the PDGE profiles as
        TabulatedProfiles): fit_jacobian (6·n₁, P) of the constant fit over camera 1's
        identification poses (whitened); null_space (P, k) its unidentified directions (natural
        units); smoothing {axis: (6,) λ}."""
        rows = joint_rows(measurements)
        meas = measurements.select(rows)
        n = len(meas)
        W = whitening(meas.cov)
        steps = np.array([s.jacobian_step for s in specs])
        skeleton = replace(apply_parameters(model, specs, -np.asarray(x)), pdge={})
        cam1 = ((meas.table.camera == IDENTIFICATION_CAMERA) & meas.table.stage.isin(IDENTIFICATION_STAGES)).to_numpy()
        J_x = np.zeros((n, 6, len(specs)))
        J_x[cam1] = (fit_jacobian * steps).reshape(int(cam1.sum()), 6, len(specs))  # natural units
        q = machine.commands_to_internal(meas.commands)

        def white(m: ErrorModel) -> np.ndarray:
            return np.einsum("nij,nj->ni", W, pose_residuals(machine, m, meas))

        blocks, axes, col = [J_x.reshape(6 * n, -1)], [], len(specs)
        nuisance = []
        for axis in AXIS_ORDER:
            profile = model.pdge.get(axis)
            if not isinstance(profile, TabulatedProfile) or len(profile.positions) < 5:
                continue
            positions = np.asarray(profile.positions, float)
            # response of every row to each of the joint's six error components (per file unit)
            S = np.zeros((n, 6, 6))
            base_off = np.asarray(model.joint_offsets.get(axis, np.zeros(6)), float)
            for c in range(6):
                h = COMPONENT_SCALE[c]
                plus = replace(model, joint_offsets={**model.joint_offsets, axis: base_off + h * np.eye(6)[c]})
                minus = replace(model, joint_offsets={**model.joint_offsets, axis: base_off - h * np.eye(6)[c]})
                S[:, :, c] = (white(plus) - white(minus)) / 2.0
            w = knot_weights(positions, q[:, AXIS_ORDER.index(axis)])  # (n, K)
            knots = np.einsum("nrc,nm->nrmc", S, w).reshape(6 * n, -1)  # (6n, 6K) knot-major
            G = gauge_complement(machine, axis, positions)
            sweep = ((meas.table.stage == "pdge") & (meas.table.group == axis)).to_numpy()
            var = sweep_variances(S[sweep], meas.table[axis].to_numpy(dtype=float)[sweep])
            P = _penalty(positions, smoothing.get(axis), var)
            blocks.append(knots @ G)
            axes.append(_Axis(axis, positions, G, G.T @ P @ G, P, slice(col, col + G.shape[1]), var))
            col += G.shape[1]
            # another camera's sweep of this axis: its line errors as that camera sees them
            other = (~cam1) & (meas.table.group == axis).to_numpy()
            if other.any():
                sig = line_error_signatures(machine, axis, positions) / COMPONENT_SCALE[None, :, None]
                line_cols = knots @ sig.reshape(positions.size * 6, -1)
                line_cols[np.repeat(~other, 6)] = 0.0
                nuisance.append(line_cols)
        for camera in np.unique(meas.table.camera[~cam1]):
            sel = (meas.table.camera == camera).to_numpy() & ~cam1
            design = np.zeros((n, 6, 12))
            design[sel] = np.concatenate([se3.adjoint(se3.inverse(meas.T[sel])),
                                          np.broadcast_to(np.eye(6), (int(sel.sum()), 6, 6))], axis=2)
            nuisance.append(np.einsum("nij,njk->nik", W, design).reshape(6 * n, 12))
        J = np.concatenate(blocks + nuisance, axis=1)
        return cls(machine, specs, skeleton, np.asarray(x, float), dict(model.pdge), axes, rows, W, J, J.T @ J,
                   steps, len(specs), null_space)

    def model_at(self, x: np.ndarray, profiles: dict[str, TabulatedProfile]) -> ErrorModel:
        return apply_parameters(replace(self.skeleton, pdge={**self.skeleton.pdge, **profiles}), self.specs, x)

    def with_penalty(self, smoothing: dict[str, np.ndarray]) -> JointStep:
        """The same system with the penalties of the roughness ``smoothing`` ({axis: (6,) λ}) of
        another extraction (the variances are the whitening's, the same for moved poses)."""
        axes = []
        for a in self.axes:
            P = _penalty(a.positions, smoothing.get(a.axis), a.variance)
            axes.append(replace(a, penalty=a.G.T @ P @ a.G, penalty_full=P))
        return replace(self, axes=axes, _factor=None)

    def factor(self) -> np.ndarray:
        """Lower Cholesky factor of the normal matrix JᵀJ + GᵀPG (computed once)."""
        if self._factor is None:
            N = self.JtJ.copy()
            for a in self.axes:
                N[a.cols, a.cols] += a.penalty
            if self.null_x.size:  # what the constant fit leaves unidentified stays where it is
                N[: self.n_x, : self.n_x] += 1e6 * (self.null_x @ self.null_x.T)
            self._factor = np.linalg.cholesky(N + 1e-12 * np.diag(np.diag(N)) + 1e-15 * np.eye(N.shape[0]))
        return self._factor

    def covariance(self) -> np.ndarray:
        """(P, P) covariance of the constants (internal units) for unit-variance whitened residuals
        (multiply by σ²): the constants' block of the inverse normal matrix, the profiles' noise in it."""
        L = self.factor()
        cov_n = cho_solve((L, True), np.eye(L.shape[0])[:, : self.n_x])[: self.n_x]
        return cov_n * np.outer(self.steps, self.steps)

    def residual_variance(self, measurements: Measurements, x: np.ndarray,
                          profiles: dict[str, TabulatedProfile]) -> float:
        """σ² of the joint fit at (x (P,) internal units, profiles): the whitened residual sum of
        squares over its rows (the nuisance at its best, one linear step) over the residual degrees
        of freedom 6n − tr(N⁻¹ JᵀJ), the trace counting what the penalised profiles, the constants
        and the nuisance fit out of the data (Hastie & Tibshirani's effective degrees of freedom of
        a linear smoother). The constant fit's own RSS / (6n₁ − P) counts only the P constants."""
        meas = measurements.select(self.rows)
        L = self.factor()
        v = {a.axis: np.asarray(profiles[a.axis].values, float) / COMPONENT_SCALE for a in self.axes}
        r = np.einsum("nij,nj->ni", self.W, pose_residuals(self.machine, self.model_at(x, profiles), meas)).ravel()
        g = self.J.T @ r
        for a in self.axes:
            g[a.cols] += a.G.T @ (a.penalty_full @ v[a.axis].ravel())
        after = r - self.J @ cho_solve((L, True), g)
        dof = np.trace(cho_solve((L, True), self.JtJ))
        return float(after @ after / (after.size - dof))

    def solve(self, measurements: Measurements, steps: int = GAUSS_NEWTON_STEPS
              ) -> tuple[np.ndarray, dict[str, TabulatedProfile]]:
        """Gauss–Newton from the build point on ``measurements`` (same rows as at build; the poses
        may be moved). Returns (x (P,) internal units, {axis: profile})."""
        meas = measurements.select(self.rows)
        L = self.factor()
        x = self.x0.copy()
        v = {a.axis: np.asarray(self.profiles0[a.axis].values, float) / COMPONENT_SCALE for a in self.axes}
        for _ in range(steps):
            profiles = {a.axis: TabulatedProfile(a.positions, v[a.axis] * COMPONENT_SCALE) for a in self.axes}
            r = np.einsum("nij,nj->ni", self.W, pose_residuals(self.machine, self.model_at(x, profiles), meas)).ravel()
            g = self.J.T @ r
            for a in self.axes:
                g[a.cols] += a.G.T @ (a.penalty_full @ v[a.axis].ravel())
            z = -cho_solve((L, True), g)
            x = x + z[: self.n_x] * self.steps
            for a in self.axes:
                v[a.axis] = v[a.axis] + (a.G @ z[a.cols]).reshape(-1, 6)
        return x, {a.axis: TabulatedProfile(a.positions, v[a.axis] * COMPONENT_SCALE) for a in self.axes}


def sweep_variances(S: np.ndarray, commands: np.ndarray) -> np.ndarray:
    """(6,) variance of a position's mean of each error-motion component (file units²) that the
    whitening implies for a sweep: S (m, 6, 6) the whitened residuals' response of its m images to
    the six components (per file unit), commands (m,) the swept axis' command of each. An image's
    covariance of the components is (SᵀS)⁻¹ (the pose covariance, floor included, carried to the
    joint's error motion); its diagonal, averaged over the images, over the mean count of images
    per position: the scale the smoothing spline's λ is relative to
    (:func:`tasks.identification.smoothing.smooth` weighs positions by their count)."""
    per_image = np.linalg.inv(np.einsum("mri,mrj->mij", S, S))
    _, count = np.unique(commands, return_counts=True)
    return np.diagonal(per_image, axis1=1, axis2=2).mean(axis=0) / count.mean()


def _penalty(positions: np.ndarray, lam: np.ndarray | None, variance: np.ndarray) -> np.ndarray:
    """(6K, 6K) P = K ⊗ diag(λ / s²) (knot-major), file units; a NaN or missing λ (a sweep too short
    to smooth) penalises nothing."""
    lam = np.nan_to_num(np.asarray(np.full(6, np.nan) if lam is None else lam, float), nan=0.0)
    return np.kron(penalty_matrix(positions), np.diag(lam / variance))


def with_profiles(pdge: PdgeResult, profiles: dict[str, TabulatedProfile]) -> PdgeResult:
    """``pdge`` with its profiles and the ``fit_*`` columns of its table replaced by ``profiles``
    (same positions)."""
    table = pdge.table.copy()
    for axis, profile in profiles.items():
        rows = (table["axis"] == axis).to_numpy()
        values = np.asarray(profile.values, float) / COMPONENT_SCALE
        for k, col in enumerate(COMPONENT_COLUMNS):
            table.loc[rows, f"fit_{col}"] = values[:, k]
    return replace(pdge, table=table, profiles={**pdge.profiles, **profiles})


JOINT_ITERATIONS = 2
"""Outer iterations: the system is rebuilt about each solution. From the alternation's first round
the first leaves up to 20u (the responses change with the 100u it moves), the second 0.1u."""


def joint_refine(machine: Machine, base: ErrorModel, measurements: Measurements, poses: Measurements,
                 pdge: PdgeResult, fit: PigeFit, iterations: int = JOINT_ITERATIONS,
                 penalty_of: PdgeResult | None = None) -> tuple[PdgeResult, PigeFit, JointStep]:
    """The joint step (module docstring) from the alternation's ``pdge`` and ``fit``: the refined
    profiles, the constant fit over ``poses`` run from the joint solution with those profiles (its
    covariance replaced by the joint one, which carries the profiles' noise, and its σ² by the joint
    fit's, which counts the degrees of freedom the profiles take: :meth:`JointStep.residual_variance`),
    and the last step (for the uncertainty propagation's re-fits).

    penalty_of: the extraction whose roughness sets the penalties (default ``pdge``'s own): the truth
    expressed in a fit's gauge takes the noisy fit's, as its alternation does."""
    penalty_of = penalty_of or pdge
    for _ in range(iterations):
        f = fit.fit
        step = JointStep.build(machine, fit.specs, fit.model, f.x, f.jacobian, f.null_space, penalty_of.smoothing,
                               measurements)
        x, profiles = step.solve(measurements)
        pdge = with_profiles(pdge, profiles)
        fit = identify_pige(machine, replace(base, pdge={**base.pdge, **profiles}), poses, fit.specs, x0=x)
    sigma2 = step.residual_variance(measurements, fit.fit.x, profiles)
    cov = step.covariance() * sigma2
    ok = fit.fit.identifiable
    cov[~ok, :] = np.nan
    cov[:, ~ok] = np.nan
    return pdge, replace(fit, fit=replace(fit.fit, covariance=cov, sigma2=sigma2)), step

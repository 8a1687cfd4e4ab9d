"""PIGE identification over the five-axis poses (§4.2, eqs. 20 and 22) and the whole calibration.

SYNOPSIS
    >>> result = calibrate(machine, measurements)            # PDGEs, then PIGEs
    >>> result.model                                         # ErrorModel for compensation
    >>> result.pige_table()                                  # the `pige` lake table

Residual of image k (eq. 20): e_k = log(T_model(q_k)⁻¹ · T_meas,k) in se(3), the plate-frame
twist in which the pose covariance C_k is given. Residuals are whitened by (C_k + C_floor)^(-1/2)
so that the poorly measured tilts (tens of arcsec per image at 300 mm) weigh what they are worth
and the well measured lateral position (a fraction of a µm) what it is worth. C_floor keeps one
image from dominating (0.1 µm, 1″).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import pandas as pd

from tasks.core.units import MAX_UNCERTAINTY
from tasks.identification.levenberg_marquardt import FitResult, levenberg_marquardt
from tasks.identification.measurements import Measurements
from tasks.identification.parameters import ParamSpec, apply_parameters, default_parameters
from tasks.identification.pdge_extraction import PdgeResult, extract_pdges
from tasks.machine.description import Machine
from tasks.machine.error_model import ErrorModel
from tasks.machine.kinematics import forward, pose_error

COV_FLOOR = np.diag([1e-4**2] * 3 + [(np.pi / 648000) ** 2] * 3)  # (0.1 µm)², (1″)²
# the constant parameters are fitted over camera 1's five-axis poses and its sweeps of X, Y, Z
# and C: the sweeps' long travel fixes the directions of motion (squareness, eq. 21)
IDENTIFICATION_STAGES = ("pige", "pdge")
IDENTIFICATION_CAMERA = "camera1"


def whitening(cov: np.ndarray) -> np.ndarray:
    """(N, 6, 6) matrices W with Wᵀ W = (C + C_floor)⁻¹."""
    L = np.linalg.cholesky(cov + COV_FLOOR)
    return np.linalg.inv(L)


def as_measured(machine: Machine, model: ErrorModel, camera: str, T_cam_plate: np.ndarray, meas: Measurements,
                rows: np.ndarray) -> np.ndarray:
    """``T_cam_plate`` (n, 4, 4) of ``meas``' ``rows`` (bool mask) as ``camera`` would measure it: with the
    imaging bias of the model's camera effects (focal drift, extra distortion; :mod:`tasks.identification.imaging`)."""
    if not model.effects:
        return T_cam_plate
    from tasks.identification.imaging import apparent_view

    idx = np.flatnonzero(rows)
    q = machine.commands_to_internal(meas.commands[idx])
    return apparent_view(machine, model.effects, camera, T_cam_plate, q, meas.context.take(idx))


def pose_residuals(machine: Machine, model: ErrorModel, meas: Measurements) -> np.ndarray:
    """(N, 6) residuals of eq. 20 (mm, rad) of each image against ``model``, per image's camera."""
    fk = forward(machine, meas.commands, model, meas.context)
    out = np.empty((len(meas), 6))
    for cam, rows in meas.camera_rows.items():
        out[rows] = pose_error(meas.T[rows], as_measured(machine, model, cam, fk.camera_view(cam)[rows], meas, rows))
    return out


def synthetic_measurements(machine: Machine, truth: ErrorModel, like: Measurements) -> Measurements:
    """``like`` with its measured poses replaced by the true ones (noise-free): used to express the
    simulator's truth in the identification's gauge."""
    fk = forward(machine, like.commands, truth, like.context)
    T = np.empty_like(like.T)
    cams = like.table.camera.to_numpy()
    for cam in np.unique(cams):
        rows = cams == cam
        T[rows] = as_measured(machine, truth, str(cam), fk.camera_view(str(cam))[rows], like, rows)
    return Measurements(like.table, T, like.cov, like.context)


@dataclass
class PigeFit:
    specs: list[ParamSpec]
    fit: FitResult
    model: ErrorModel
    n_images: int

    def values_file_units(self) -> np.ndarray:
        return self.fit.x / np.array([s.scale for s in self.specs])

    def uncertainties_file_units(self) -> np.ndarray:
        return self.fit.uncertainty / np.array([s.scale for s in self.specs])


def identify_pige(machine: Machine, base: ErrorModel, meas: Measurements,
                  specs: list[ParamSpec] | None = None, tau: float = 1e-5, x0: np.ndarray | None = None,
                  adjust: Callable[[ErrorModel, np.ndarray], ErrorModel] | None = None) -> PigeFit:
    """Levenberg–Marquardt (eq. 22) of ``specs`` over ``meas`` with the PDGEs of ``base`` fixed.

    x0: starting values (internal units; default zeros). adjust: optional ``(model, x) -> model``
    applied after the parameters (the effect fit uses it to move the PDGE profiles with the
    effects' parameters, :mod:`tasks.identification.effect_fit`)."""
    specs = specs or default_parameters()
    W = whitening(meas.cov)

    def model_at(x: np.ndarray) -> ErrorModel:
        model = apply_parameters(base, specs, x)
        return adjust(model, x) if adjust is not None else model

    steps = np.array([s.jacobian_step for s in specs])  # 1 µm or 1″: well inside the linear range

    def residuals(x_natural: np.ndarray) -> np.ndarray:
        e = pose_residuals(machine, model_at(x_natural * steps), meas)
        return np.einsum("nij,nj->ni", W, e).ravel()

    # the LM runs in natural units (one step = 1 µm, 1″ or one unit of an effect's parameter), where
    # its identifiable subspace is meant to be taken; results are converted back to internal units
    start = np.zeros(len(specs)) if x0 is None else np.asarray(x0, dtype=float)
    fit_n = levenberg_marquardt(residuals, start / steps, np.ones(len(specs)), tau=tau)
    fit = replace(fit_n, x=fit_n.x * steps, covariance=fit_n.covariance * np.outer(steps, steps),
                  jacobian=fit_n.jacobian / steps)
    return PigeFit(specs, fit, model_at(fit.x), len(meas))


def null_space_sentences(specs: list[ParamSpec], fit: FitResult) -> list[str]:
    """One sentence per direction the poses leave unexcited, naming the parameters it mixes."""
    out = []
    for k in range(fit.null_space.shape[1]):
        v = fit.null_space[:, k]
        order = np.argsort(-np.abs(v))
        terms = [f"{v[i]:+.2f}·{specs[i].name}" for i in order if abs(v[i]) > 0.05]
        out.append("The poses do not determine the combination " + " ".join(terms)
                   + "; its parameters are reported as unidentifiable.")
    return out


@dataclass
class CalibrationResult:
    """pdge: PDGE extraction. pige: the fit. model: the identified error model (PDGE profiles,
    PIGEs, constants, mounts, effects). truth_pige: the same fit on noise-free truth (simulated only).
    extraction_model: the model the PDGEs were extracted with (the base, its effects at their fitted
    values). notes: warnings of the fit in words (e.g. an effect these poses cannot identify). joint: the
    profiles and constants come from the joint step (:mod:`tasks.identification.joint_fit`).
    alternation: for a joint result, the alternation's converged solution it started from (None: the
    diagnosis computes it, :func:`tasks.analysis.diagnosis.linearisation.alternation_of`)."""

    pdge: PdgeResult
    pige: PigeFit
    truth_pige: PigeFit | None = None
    truth: ErrorModel | None = None
    extraction_model: ErrorModel | None = None
    notes: list[str] = field(default_factory=list)
    joint: bool = False
    alternation: CalibrationResult | None = None

    @property
    def model(self) -> ErrorModel:
        return self.pige.model

    def pige_table(self, propagated=None) -> pd.DataFrame:
        """The ``pige`` lake table (µm / arcsec): value, standard uncertainty, identifiable, truth.

        propagated: a :class:`tasks.identification.uncertainty.PropagatedUncertainty` of this
        result; ``uncertainty`` is then its combined value (camera self-calibration and pose noise
        through the PDGE extraction), with the parts in ``uncertainty_fit`` (the LM's),
        ``uncertainty_noise`` and ``uncertainty_camera``. Without it ``uncertainty`` is the LM's."""
        specs, fit = self.pige.specs, self.pige.fit
        scale = np.array([s.scale for s in specs])
        value = np.where(fit.identifiable, self.pige.values_file_units(), np.nan)
        unc_fit = self.pige.uncertainties_file_units()
        nan = np.full(len(specs), np.nan)
        if propagated is None:
            unc, unc_noise, unc_camera = unc_fit, nan, nan
        else:
            unc = np.where(fit.identifiable, propagated.combined / scale, np.nan)
            unc_noise = np.where(fit.identifiable, propagated.noise / scale, np.nan)
            unc_camera = np.where(fit.identifiable, propagated.camera / scale, np.nan)
        rows = []
        # the truth in the fit's gauge, by name: a fit with added effects has parameters the truth's lacks
        truth_by_name = (dict(zip([t.name for t in self.truth_pige.specs], self.truth_pige.values_file_units(),
                                  strict=True)) if self.truth_pige else {})
        truth_gauge = np.array([truth_by_name.get(sp.name, np.nan) for sp in specs])
        for i, s in enumerate(specs):
            nominal = np.nan
            if self.truth is not None and s.kind == "pige":
                nominal = self.truth.pige.get(s.name, 0.0) / s.scale
            note = self._note(s, bool(fit.identifiable[i]), value[i], unc[i], propagated is not None)
            rows.append({"name": s.name, "kind": s.kind, "joint": s.target, "unit": s.unit, "value": value[i],
                         "uncertainty": unc[i], "uncertainty_fit": unc_fit[i], "uncertainty_noise": unc_noise[i],
                         "uncertainty_camera": unc_camera[i], "identifiable": bool(fit.identifiable[i]),
                         "note": note, "truth": truth_gauge[i], "truth_nominal": nominal})
        return pd.DataFrame(rows)

    def _note(self, spec: ParamSpec, identifiable: bool, value: float, uncertainty: float, propagated: bool) -> str:
        """The pige table's note (file units): why a parameter has no value; how far an added effect's
        amplitude lies from zero; a propagated uncertainty beyond the SVD's limit of identification."""
        if not identifiable:
            return "unidentifiable from these poses (see the identifiability section)"
        notes = [_distance_from_zero(value, uncertainty)] if self._is_effect_amplitude(spec) else []
        limit = MAX_UNCERTAINTY * spec.jacobian_step / spec.scale  # the SVD's limit in the file unit
        if propagated and uncertainty > limit:
            unit = "µm" if spec.unit == "um" else spec.unit
            notes.append(f"u above the {limit:g} {unit} up to which the fit's SVD counts a parameter "
                         "identified: the campaign hardly determines it")
        return "; ".join(n for n in notes if n)

    def _is_effect_amplitude(self, spec: ParamSpec) -> bool:
        if spec.kind != "effect":
            return False
        from tasks.identification.effect_params import param

        return param(type(self.model.effects[spec.component]), spec.param).amplitude


EFFECT_ABSENT_U = 2.0
"""An added effect's amplitude within this many standard uncertainties of zero is reported as
consistent with the effect's absence (two-sided, about 95 % for a Gaussian estimate)."""


def _distance_from_zero(value: float, uncertainty: float) -> str:
    """The pige table's note for an added effect's amplitude: how far from zero, in its uncertainty."""
    if not (np.isfinite(value) and np.isfinite(uncertainty) and uncertainty > 0):
        return ""
    z = abs(value) / uncertainty
    verdict = ": consistent with no such effect" if z < EFFECT_ABSENT_U else ""
    return f"{z:.1f}u from zero{verdict}"


ALTERNATION_ROUNDS = 6
ALTERNATION_CONVERGED = 0.1  # stop when no parameter moves by more than this many standard uncertainties
JOINT_START_ROUNDS = 2
"""Rounds of the alternation before the joint step (:mod:`tasks.identification.joint_fit`): it only
has to bring the constants near enough for the joint system's responses."""


def alternate(machine: Machine, base: ErrorModel, measurements: Measurements, poses: Measurements,
              specs: list[ParamSpec] | None = None, truth: ErrorModel | None = None,
              rounds: int = ALTERNATION_ROUNDS,
              start: tuple[ErrorModel, np.ndarray] | None = None,
              smoothing: dict[str, np.ndarray] | None = None) -> tuple[PdgeResult, PigeFit, ErrorModel]:
    """PDGE extraction (eqs. 13–19) and the fit of the constant parameters (eq. 22), alternated.

    The extraction of an axis' PDGE reads everything else from the current model: without the
    constant errors it would put them into the swept axis' profile (a constant camera-frame offset,
    e.g. from a principal-point error, turns with C and would become a once-per-turn PDGE of C).
    So: extract with the model, fit the constants with the profiles fixed, extract again with the
    fitted constants, until no parameter moves by more than ALTERNATION_CONVERGED of its
    uncertainty (usually 3–5 rounds). Returns (PDGEs, fit, the model the PDGEs were extracted with).

    start: (extraction model, parameter values) of an earlier solution to begin from instead of
    ``base`` and zeros: a re-fit of slightly changed measurements then converges in a round or two.
    smoothing: the PDGE smoothers' roughness to hold ({axis: (6,)}, :class:`PdgeResult`); default GCV."""
    extraction, x = (base, None) if start is None else start
    for _ in range(rounds):
        pdge = extract_pdges(machine, extraction, measurements, truth, smoothing)
        with_pdge = replace(base, pdge={**base.pdge, **pdge.profiles})
        fit = identify_pige(machine, with_pdge, poses, specs, x0=x)
        moved = np.abs(fit.fit.x - (0.0 if x is None else x)) / np.where(fit.fit.identifiable, fit.fit.uncertainty,
                                                                           np.inf)
        x = fit.fit.x
        if np.nanmax(moved) < ALTERNATION_CONVERGED:
            break
        extraction = replace(fit.model, pdge=dict(base.pdge))
    return pdge, fit, extraction

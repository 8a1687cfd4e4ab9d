"""The calibration linearised around its solution: residual, own-parameter columns and candidate columns.

SYNOPSIS
    >>> lin = linearise(machine, measurements, result)       # result of calibrate(...)
    >>> G, raw = lin.columns([unit_pair(effect, "amount_um")])
    >>> G.shape, lin.residual.shape                           # (1, M), (M,)

What is compared. The fit of eq. 22 minimises the whitened residuals r (M = 6 N, N = camera 1's
sweep and five-axis images) over the model's own parameters, whose whitened Jacobian J (M, P) the
LM leaves at its solution (natural units). A candidate effect with amplitude a changes r by G a:

    G = W · Σ_channels D_c · (u_c + Σ_j I_j G_j H_j A_j (D^sweep_j · u^sweep))            (1)

u_c (N, 6): the effect per unit amplitude on each channel (joint screws, attachments, imaging;
:mod:`tasks.analysis.diagnosis.sensitivity`) at the identification images; D_c: the residual's derivative
per image; the bracket's second term is the PDGE profiles' response when the effect enters the
extraction (:mod:`tasks.identification.pdge_response`): the part of the effect that the splines swallow
cancels there. W: the whitening of each image's pose covariance (as in the fit). The "raw" column
W Σ D_c u_c leaves the extraction out: comparing its norm with the projected norm of G tells how
much the model already absorbs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from tasks.analysis.diagnosis.sensitivity import IMAGING, Sensitivity, error_motion_sensitivity, residual_sensitivity
from tasks.identification.imaging import imaging_bias, imaging_corrected
from tasks.identification.measurements import Measurements
from tasks.identification.pdge_response import AxisResponse, axis_responses
from tasks.identification.pige_identification import (
    IDENTIFICATION_CAMERA,
    IDENTIFICATION_STAGES,
    CalibrationResult,
    whitening,
)
from tasks.machine.description import AXIS_ORDER, Machine
from tasks.machine.effects import Effect, camera_changes
from tasks.machine.error_model import ErrorModel

CHUNK = 64  # candidate columns evaluated at once (memory: CHUNK × N × 6 per channel)


def channel_values(machine: Machine, pairs: list[tuple[Effect, Effect]], meas: Measurements) -> dict:
    """{channel: (B, N, 6)} effect per unit amplitude, (one − zero) of each pair, at ``meas``' images.

    Joint and attachment channels in mm / rad; the imaging channel is the plate-frame bias twist
    (evaluated at the measured poses, which differ from the true ones by µm)."""
    q = machine.commands_to_internal(meas.commands)
    ctx = meas.context
    n, b = len(meas), len(pairs)
    out: dict[tuple, np.ndarray] = {}

    def add(ch, k, value):
        if ch not in out:
            out[ch] = np.zeros((b, n, 6))
        out[ch][k] += np.broadcast_to(np.asarray(value, dtype=float), (n, 6))

    cams = meas.table.camera.to_numpy()
    groups = [(str(cam), np.flatnonzero(cams == cam)) for cam in np.unique(cams)]
    groups = [(cam, rows, q[rows], ctx.take(rows)) for cam, rows in groups]
    for k, (one, zero) in enumerate(pairs):
        for sign, e in ((1.0, one), (-1.0, zero)):
            for axis, v in e.joint_errors(machine, q, ctx).items():
                add(("joint", axis), k, sign * np.asarray(v))
            for name, v in e.attachment_errors(machine, q, ctx).items():
                add(("attachment", name), k, sign * np.asarray(v))
        for cam, rows, sub_q, sub_ctx in groups:
            c1 = camera_changes([one], cam, machine, sub_q, sub_ctx)
            c0 = camera_changes([zero], cam, machine, sub_q, sub_ctx)
            delta = c1["focal_scale"] - c0["focal_scale"]
            extra = {t: (c1["extra_distortion"] or {}).get(t, 0.0) - (c0["extra_distortion"] or {}).get(t, 0.0)
                     for t in set(c1["extra_distortion"] or {}) | set(c0["extra_distortion"] or {})}
            if np.any(delta) or any(extra.values()):
                bias = imaging_bias(machine, cam, meas.T[rows], delta if np.any(delta) else None, extra)
                if IMAGING not in out:
                    out[IMAGING] = np.zeros((b, n, 6))
                out[IMAGING][k, rows] += bias
    return out


@dataclass
class SweepLink:
    """One axis' sweep as the extraction sees it: its map to the profile (response), the error
    motions' sensitivities, and the profile's interpolation weights at the identification images."""

    response: AxisResponse
    sensitivity: Sensitivity
    interpolation: np.ndarray  # (N, K)


@dataclass
class Linearisation:
    """The fit around its solution. residual: (M,) whitened (row 6n+i: image n, component i, plate
    frame). own: (M, P) whitened Jacobian of the model's parameters in natural units (1 µm, 1″, one
    unit of an effect parameter). ident: the M/6 identification images (camera 1, sweeps and five-axis
    poses, the fit's order). W: (N, 6, 6) whitening. sensitivity: whitened residual sensitivities."""

    machine: Machine
    measurements: Measurements
    result: CalibrationResult
    ident: Measurements
    W: np.ndarray
    residual: np.ndarray
    own: np.ndarray
    own_names: list[str]
    sensitivity: Sensitivity | None = None
    sweeps: dict[str, SweepLink] | None = None
    images: Measurements | None = None  # every image of the fit or a sweep: effects are evaluated once on these
    rows: dict | None = None  # {"ident" | axis: (n,) row indices into images}

    @property
    def n_images(self) -> int:
        return len(self.ident)

    def columns(self, pairs: list[tuple[Effect, Effect]]) -> tuple[np.ndarray, np.ndarray]:
        """Whitened residual columns (B, M) per unit amplitude of each (one, zero) pair, eq. (1), and
        the raw columns (B, M) without the extraction's response."""
        full, raw = [], []
        for start in range(0, len(pairs), CHUNK):
            f, r = self._columns(pairs[start:start + CHUNK])
            full.append(f)
            raw.append(r)
        if not full:
            return np.zeros((0, self.residual.size)), np.zeros((0, self.residual.size))
        return np.concatenate(full), np.concatenate(raw)

    def _columns(self, pairs):
        b, n = len(pairs), self.n_images
        u_all = channel_values(self.machine, pairs, self.images)
        u = {ch: v[:, self.rows["ident"]] for ch, v in u_all.items()}
        raw = self.sensitivity.apply(u)
        raw = np.zeros((b, n, 6)) if raw is None else raw
        moved = dict(u)
        for axis, link in self.sweeps.items():
            u_sw = {ch: v[:, self.rows[axis]] for ch, v in u_all.items()}
            dE = link.sensitivity.apply(u_sw)
            if dE is None:
                continue
            dP = link.response.profile_change(dE)  # (B, K, 6)
            at = np.matmul(link.interpolation, dP)  # (B, N, 6)
            ch = ("joint", axis)
            moved[ch] = moved[ch] + at if ch in moved else at
        full = self.sensitivity.apply(moved)
        full = np.zeros((b, n, 6)) if full is None else full
        return full.reshape(b, -1), raw.reshape(b, -1)


def own_columns(result: CalibrationResult) -> tuple[np.ndarray, list[str]]:
    """(M, P) whitened Jacobian of the fit's parameters in natural units, and their names."""
    specs = result.pige.specs
    steps = np.array([s.jacobian_step for s in specs])
    return result.pige.fit.jacobian * steps, [s.name for s in specs]


def alternation_of(machine: Machine, measurements: Measurements, result: CalibrationResult) -> CalibrationResult:
    """The alternation's converged solution behind ``result`` (``result`` itself when it did not end
    with the joint step): the estimator eq. 1 describes, whose profiles come from the sweeps alone.

    The joint step lets the five-axis poses shape the profiles, and eq. 1 does not model that
    response: on the test campaign with a hidden 30 µm/h drift of Y with time the joint step leaves
    a CV RMS of 2.2 where the alternation leaves 6.1, and the amplitude scored against its residual
    is 22.6 µm/h where the alternation's gives 30.3. So every fit the diagnosis compares (with and
    without candidates, with and without added effects) is the alternation's. Computed once per
    result (kept in ``result.alternation``)."""
    if not result.joint:
        return result
    if result.alternation is None:
        from tasks.identification.pige_identification import alternate

        poses = measurements.stage(*IDENTIFICATION_STAGES, camera=IDENTIFICATION_CAMERA)
        pdge, fit, ext = alternate(machine, ErrorModel(), measurements, poses, result.pige.specs)
        result.alternation = CalibrationResult(pdge, fit, extraction_model=ext)
    return result.alternation


def linearise(machine: Machine, measurements: Measurements, result: CalibrationResult,
              candidates: bool = True) -> Linearisation:
    """The linearisation of ``result`` (a :func:`calibrate` result on ``measurements``), about its
    alternation's solution (:func:`alternation_of`).

    candidates: also build what candidate columns need (sensitivities, extraction responses;
    a few seconds); False gives only residual and own columns (for cross-validation)."""
    result = alternation_of(machine, measurements, result)
    ident = measurements.stage(*IDENTIFICATION_STAGES, camera=IDENTIFICATION_CAMERA)
    residual = np.asarray(result.pige.fit.residual, dtype=float)
    if residual.size != 6 * len(ident):
        raise ValueError(f"the fit has {residual.size // 6} images, the measurements {len(ident)} "
                         "identification images: diagnose the measurements the result was calibrated on")
    W = whitening(ident.cov)
    own, names = own_columns(result)
    lin = Linearisation(machine, measurements, result, ident, W, residual, own, names)
    if not candidates:
        return lin
    raw = residual_sensitivity(machine, result.model, ident)
    lin.sensitivity = Sensitivity({ch: np.einsum("nij,njk->nik", W, D) for ch, D in raw.blocks.items()})
    ext = result.extraction_model if result.extraction_model is not None else ErrorModel(
        effects=list(result.model.effects))
    corrected = imaging_corrected(machine, ext, measurements)
    q = machine.commands_to_internal(ident.commands)
    lin.sweeps = {}
    for axis, resp in axis_responses(machine, ext, corrected).items():
        sens = error_motion_sensitivity(machine, ext, resp.sweep, axis)
        lin.sweeps[axis] = SweepLink(resp, sens, resp.interpolation(q[:, AXIS_ORDER.index(axis)]))
    lin.images = measurements.stage(*IDENTIFICATION_STAGES, "pdge")
    where = pd.Series(np.arange(len(lin.images)), index=lin.images.table.image_id.to_numpy())
    lin.rows = {"ident": where[ident.table.image_id].to_numpy(),
                **{axis: where[link.response.sweep.table.image_id].to_numpy() for axis, link in lin.sweeps.items()}}
    return lin

"""How the extracted PDGE profiles respond, to first order, to a change of the sweeps' error motions.

The PDGE extraction (:mod:`tasks.identification.pdge_extraction`, eqs. 13–19) is, for a fixed
smoothing parameter, a chain of linear maps of the measured error motions E_j (N_j, 6) of axis
j's sweep:

    P_j(q) = I_j(q) · G_j · H_j · A_j · E_j

A_j (K, N_j): the mean over the repeats of each of the K sweep positions; H_j: per component c
the smoothing spline's hat matrix H_jc (K, K) at the roughness λ_jc that generalised
cross-validation chooses on the campaign's data; G_j (6K, 6K): the gauge (value at home removed,
then the least-squares line-error signatures); I_j(q) (·, K): the natural cubic spline that
interpolates the tabulated profile at any position q (held constant beyond the sweep).

When a candidate effect is put into the model, the extraction sees each sweep image's error
motion change by ΔE_j (the effect's share, with the sign the extraction gives it) and the
profile changes by ΔP_j = I_j G_j H_j A_j ΔE_j: this is how much of the effect the PDGE spline
swallows. A cyclic error whose period the sweep's steps resolve but the spline smooths keeps most
of its signature; a linear or slowly varying one is swallowed whole.

λ_jc is found as the extraction finds it (:meth:`tasks.identification.smoothing.SplineBasis.roughness`)
on the mean error motions of the extraction's model, so H_jc is the smoother the extraction used
(tests/analysis/test_diagnosis.py checks the profiles it gives against the extraction's).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks.identification.measurements import Measurements
from tasks.identification.pdge_extraction import (
    TabulatedProfile,
    line_error_signatures,
    measured_error_motions,
    pooled_variance,
    position_means,
    repeats_noise,
)
from tasks.identification.smoothing import MIN_POINTS, SplineBasis
from tasks.machine.description import AXIS_ORDER, Machine
from tasks.machine.error_model import COMPONENT_SCALE, ErrorModel


def gauge_operator(machine: Machine, axis: str, q: np.ndarray) -> np.ndarray:
    """(K·6, K·6) linear map of a tabulated profile (K, 6) (row-major flattening, mm / rad) to its
    gauge-referred form (:func:`tasks.identification.pdge_extraction.referred_to_home`)."""
    k = q.size
    home = TabulatedProfile(q, np.eye(k))(np.zeros(1))[0] if k >= 2 else np.ones(k)  # (K,) interpolation weights
    minus_home = np.eye(k) - np.outer(np.ones(k), home)  # (K, K)
    R = np.kron(minus_home, np.eye(6))  # (6K, 6K) on the flattened (K, 6)
    if k < 2:
        return R
    sig = line_error_signatures(machine, axis, q)  # (K, 6, m) internal units per unit screw
    A = (sig / COMPONENT_SCALE[None, :, None]).reshape(-1, sig.shape[2])  # file units, (6K, m)
    to_file = np.tile(1.0 / COMPONENT_SCALE, k)  # (6K,)
    coef = np.linalg.pinv(A) @ (to_file[:, None] * R)  # (m, 6K)
    return R - sig.reshape(-1, sig.shape[2]) @ coef


@dataclass
class AxisResponse:
    """The linear extraction map of one axis' sweep.

    sweep: the sweep's images (stage ``pdge``, group = axis). q: (K,) sweep positions (mm or rad).
    error_motions: (N_j, 6) what the extraction read from the sweep (mm, rad).
    average: (K, N_j) mean over repeats. hat: (6, K, K) per component. gauge: (6K, 6K).
    operator: (6K, 6N_j) the whole map G H A on row-major flattened (K, 6) and (N_j, 6) arrays.
    smoothing_cov: (6K, 6K) the smoothing bias allowance of the referred profile (see
    :func:`smoothing_bias_covariance`)."""

    axis: str
    sweep: Measurements
    q: np.ndarray
    average: np.ndarray
    hat: np.ndarray
    gauge: np.ndarray
    operator: np.ndarray | None = None
    smoothing_cov: np.ndarray | None = None
    error_motions: np.ndarray | None = None

    def __post_init__(self):
        if self.operator is None:
            k, n = self.average.shape
            HA = self.hat @ self.average  # (6, K, N_j): smoothing of the repeat means, per component
            full = np.zeros((k, 6, n, 6))
            for c in range(6):
                full[:, c, :, c] = HA[c]
            self.operator = self.gauge @ full.reshape(6 * k, 6 * n)

    def profile_change(self, dE: np.ndarray) -> np.ndarray:
        """(B, N_j, 6) changes of the sweep's error motions -> (B, K, 6) changes of the referred profile."""
        b = dE.shape[0]
        return (dE.reshape(b, -1) @ self.operator.T).reshape(b, -1, 6)

    def profile(self) -> TabulatedProfile:
        """The referred profile the extraction makes of ``error_motions`` (N_j, 6): the same as
        :func:`tasks.identification.pdge_extraction.extract_axis`'s, without its table."""
        k = self.q.size
        return TabulatedProfile(self.q, (self.operator @ self.error_motions.ravel()).reshape(k, 6))

    def interpolation(self, positions: np.ndarray) -> np.ndarray:
        """(N, K) weights of the tabulated profile's natural cubic spline at ``positions`` (mm or rad)."""
        return TabulatedProfile(self.q, np.eye(self.q.size))(np.asarray(positions, dtype=float))


def smoothing_bias_covariance(hat: np.ndarray, variance: np.ndarray, count: np.ndarray,
                              gauge: np.ndarray) -> np.ndarray:
    """(6K, 6K) what a smoothing spline's Bayesian posterior covariance adds to its sampling covariance.

    Wahba's Bayesian reading of the smoothing spline (the roughness penalty as a prior) gives the
    fitted values the covariance H C_y instead of the sampling one H C_y Hᵀ: the difference
    H C_y (I − Hᵀ) ⪰ 0 is an allowance for the smoothing bias (what the spline smooths away of the
    true profile, on average). Per component c with C_y = diag(variance_c / count) (the
    extraction's pooled within-position variance), then through the gauge."""
    k = hat.shape[1]
    blocks = np.zeros((k, 6, k, 6))
    for c in range(6):
        Cy = np.diag(variance[c] / count)
        HC = hat[c] @ Cy
        extra = HC - HC @ hat[c].T
        blocks[:, c, :, c] = 0.5 * (extra + extra.T)
    B = blocks.reshape(6 * k, 6 * k)
    return gauge @ B @ gauge.T


def axis_response(machine: Machine, model: ErrorModel, sweep: Measurements, axis: str) -> AxisResponse:
    """The extraction map of ``axis`` for its ``sweep``, with the roughness the extraction picks
    (:meth:`tasks.identification.smoothing.SplineBasis.roughness`) on the error motions that
    ``model`` (the extraction's model) leaves."""
    E = measured_error_motions(machine, model, sweep, axis)  # (N_j, 6)
    pos = sweep.table[axis].to_numpy(dtype=float)
    positions, inverse, count = np.unique(pos, return_inverse=True, return_counts=True)
    k = positions.size
    average = np.zeros((k, pos.size))
    average[inverse, np.arange(pos.size)] = 1.0
    average /= count[:, None]
    q = machine.axes[axis].to_internal(positions)
    hat = np.broadcast_to(np.eye(k), (6, k, k)).copy()
    mean = average @ E
    pooled = pooled_variance(E, inverse, position_means(E, inverse, count))
    if k >= MIN_POINTS:
        w = count / count.mean()  # the extraction's weights count/pooled, normalised: pooled cancels
        basis = SplineBasis.of(q, w)
        noise = repeats_noise(pooled, count)
        for c in range(6):
            hat[c] = basis.hat(basis.roughness(mean[:, c], None if noise is None else float(noise[c])))
    gauge = gauge_operator(machine, axis, q)
    bias = smoothing_bias_covariance(hat, pooled, count, gauge)
    return AxisResponse(axis, sweep, q, average, hat, gauge, smoothing_cov=bias, error_motions=E)


def axis_responses(machine: Machine, model: ErrorModel, measurements: Measurements) -> dict[str, AxisResponse]:
    """{axis: AxisResponse} for every axis with a sweep (stage ``pdge``, group = axis), as
    :func:`tasks.identification.pdge_extraction.extract_pdges` selects them."""
    sweeps = measurements.stage("pdge")
    out = {}
    for axis in AXIS_ORDER:
        sweep = sweeps.select(sweeps.table.group == axis)
        if len(sweep) >= 2:
            out[axis] = axis_response(machine, model, sweep, axis)
    return out

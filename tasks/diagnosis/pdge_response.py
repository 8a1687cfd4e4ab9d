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

λ_jc is found as scipy's ``make_smoothing_spline`` finds it (the same criterion,
GCV(λ) = n‖y − H_λ y‖² / (n − tr H_λ)², minimised by the same bounded search on [0, n]) on
the mean error motions of the extraction's model, so H_jc is the smoother the extraction used.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import make_smoothing_spline
from scipy.optimize import minimize_scalar

from tasks.error_model import COMPONENT_SCALE, ErrorModel
from tasks.identification.measurements import Measurements
from tasks.identification.pdge_extraction import TabulatedProfile, line_error_signatures, measured_error_motions
from tasks.machine import AXIS_ORDER, Machine

MIN_SMOOTHED = 5  # fewer positions: the extraction does not smooth (_smooth in pdge_extraction)


def hat_matrix(x: np.ndarray, w: np.ndarray, lam: float) -> np.ndarray:
    """(K, K) hat matrix of the weighted cubic smoothing spline through abscissas ``x`` at roughness ``lam``:
    fitted values = H @ y. w: (K,) weights (normalised to mean 1, as the extraction does)."""
    k = x.size
    return make_smoothing_spline(x, np.eye(k), w=w, lam=lam)(x)


def gcv_roughness(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> float:
    """λ minimising GCV(λ) = (1/n)‖y − H_λ y‖² / (1 − tr H_λ / n)² on [0, n] (scipy's criterion and search)."""
    n = x.size
    scale = np.max(np.abs(y)) or 1.0  # GCV is scale free in y; keep the numbers near 1

    def gcv(lam: float) -> float:
        H = hat_matrix(x, w, lam)
        res = y / scale - H @ (y / scale)
        return float(res @ res / n / (1.0 - np.trace(H) / n) ** 2)

    return float(minimize_scalar(gcv, bounds=(0, n), method="bounded").x)


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
    average: (K, N_j) mean over repeats. hat: (6, K, K) per component. gauge: (6K, 6K)."""

    axis: str
    sweep: Measurements
    q: np.ndarray
    average: np.ndarray
    hat: np.ndarray
    gauge: np.ndarray

    def profile_change(self, dE: np.ndarray) -> np.ndarray:
        """(B, N_j, 6) changes of the sweep's error motions -> (B, K, 6) changes of the referred profile."""
        mean = np.einsum("kn,bnc->bkc", self.average, dE)
        smooth = np.einsum("ckl,blc->bkc", self.hat, mean)
        b, k = smooth.shape[:2]
        return (smooth.reshape(b, k * 6) @ self.gauge.T).reshape(b, k, 6)

    def interpolation(self, positions: np.ndarray) -> np.ndarray:
        """(N, K) weights of the tabulated profile's natural cubic spline at ``positions`` (mm or rad)."""
        return TabulatedProfile(self.q, np.eye(self.q.size))(np.asarray(positions, dtype=float))


def axis_response(machine: Machine, model: ErrorModel, sweep: Measurements, axis: str) -> AxisResponse:
    """The extraction map of ``axis`` for its ``sweep``, with the roughness GCV picks on the error
    motions that ``model`` (the extraction's model) leaves."""
    E = measured_error_motions(machine, model, sweep, axis)  # (N_j, 6)
    pos = sweep.table[axis].to_numpy(dtype=float)
    positions, inverse, count = np.unique(pos, return_inverse=True, return_counts=True)
    k = positions.size
    average = np.zeros((k, pos.size))
    average[inverse, np.arange(pos.size)] = 1.0
    average /= count[:, None]
    q = machine.axes[axis].to_internal(positions)
    hat = np.broadcast_to(np.eye(k), (6, k, k)).copy()
    if k >= MIN_SMOOTHED:
        w = count / count.mean()  # the extraction's weights count/pooled, normalised: pooled cancels
        mean = average @ E
        for c in range(6):
            hat[c] = hat_matrix(q, w, gcv_roughness(q, mean[:, c], w))
    return AxisResponse(axis, sweep, q, average, hat, gauge_operator(machine, axis, q))


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

"""Cross-validated residual of a calibration, with or without extra candidate columns.

SYNOPSIS
    >>> linearised_cross_validated_rms(machine, measurements, result)      # whitened RMS over held-out poses

The fit's images (camera 1's sweeps and five-axis poses) are split into k folds deterministically
(image i of the fit's order goes to fold i mod k, so every fold holds every stage and time). For
each fold the model's parameters (and a candidate's amplitudes) are refitted without that fold's
images, by one Gauss–Newton step from the solution (the problem is linear far below the noise):

    δ_f = argmin ‖r_train + X_train δ‖²,   e_f = r_test + X_test δ_f                     (3)

with r the whitened residual and X = [J | G] the own (and candidate) columns. The PDGE profiles are
not re-extracted per fold (a held-out sweep image helped make its axis' profile, so its held-out
error is somewhat optimistic, alike with and without a candidate, whose columns carry the
extraction's response). cv_rms = √(Σ_f ‖e_f‖² / Σ_f |test_f|) is whitened: 1 is the noise the pose
covariances describe.

A candidate is confirmed when the held-out errors fall significantly: a one-sided paired t-test over
the held-out images of d = e²_without − e²_with (:func:`cv_improvement_p`).
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from tasks.analysis.diagnosis.linearisation import Linearisation, linearise
from tasks.identification.measurements import Measurements
from tasks.identification.pige_identification import CalibrationResult
from tasks.machine.description import Machine

FOLDS = 5


def fold_rows(lin: Linearisation, folds: int = FOLDS) -> list[np.ndarray]:
    """Residual row indices held out in each fold (six rows per image)."""
    images = np.arange(lin.n_images)
    return [(6 * images[f::folds, None] + np.arange(6)).ravel() for f in range(folds)]


def held_out_errors(residual: np.ndarray, X: np.ndarray, folds: list[np.ndarray]) -> np.ndarray:
    """Eq. (3): squared whitened held-out error of each held-out image, (n_images,) in fold order.
    residual (M,), X (M, P), folds: row indices (six per image)."""
    out = []
    scale = np.linalg.norm(X, axis=0)
    Xs = X / np.where(scale > 0, scale, 1.0)
    A, b = Xs.T @ Xs, Xs.T @ residual  # normal equations of all rows; each fold removes its own
    for test in folds:
        At = A - Xs[test].T @ Xs[test]
        bt = b - Xs[test].T @ residual[test]
        delta = -np.linalg.lstsq(At, bt, rcond=1e-12)[0]
        e = residual[test] + Xs[test] @ delta
        out.append((e.reshape(-1, 6) ** 2).sum(axis=1))
    return np.concatenate(out) if out else np.zeros(0)


def rms(held_out: np.ndarray) -> float:
    """Whitened RMS per component of held-out squared errors per image (n_images,)."""
    return float(np.sqrt(np.sum(held_out) / max(6 * np.size(held_out), 1)))


def cv_rms(residual: np.ndarray, X: np.ndarray, folds: list[np.ndarray]) -> float:
    """Eq. (3): whitened RMS of the held-out residuals (per component)."""
    return rms(held_out_errors(residual, X, folds))


def cv_improvement_p(without: np.ndarray, with_: np.ndarray) -> float:
    """One-sided paired t-test that adding the columns lowers the held-out error: per held-out image
    d = e²_without − e²_with. The images are independent samples of what the model predicts, so
    the test holds when the residual has structure that the F-test's white-noise assumption ignores."""
    d = np.asarray(without) - np.asarray(with_)
    if d.size < 3 or not np.any(d):
        return 1.0
    return float(stats.ttest_1samp(d, 0.0, alternative="greater").pvalue)


def linearised_cross_validated_rms(machine: Machine, measurements: Measurements, result: CalibrationResult,
                        folds: int = FOLDS) -> float:
    """Eq. (3) for ``result`` with its own parameters (effects included): whitened RMS over the
    held-out images of camera 1 (sweeps and five-axis poses)."""
    lin = linearise(machine, measurements, result, candidates=False)
    return cv_rms(lin.residual, lin.own, fold_rows(lin, folds))

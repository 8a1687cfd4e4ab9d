"""Weighted cubic smoothing splines with the roughness chosen by generalised cross-validation.

SYNOPSIS
    >>> fitted, lam = smooth(x, Y, w)            # GCV picks one λ per column of Y
    >>> again, _ = smooth(x, Y + dY, w, lam)     # the same linear smoother, λ held

The problem is scipy's ``make_smoothing_spline``: minimise Σ wᵢ (yᵢ − f(xᵢ))² + λ ∫ f''² over
natural cubic splines f with knots at x, and with λ unset choose it by minimising

    GCV(λ) = (1/n) Σ (yᵢ − f_λ(xᵢ))² / (1 − tr H(λ)/n)²,   λ ∈ (0, n)  (bounded Brent),

as scipy does. scipy evaluates GCV with a per-element Python loop (most of the time of a PDGE
extraction) and does not return the λ it chose; the uncertainty propagation
(:mod:`tasks.identification.uncertainty`) needs λ to hold the smoother fixed while it perturbs
the data. Here GCV is evaluated in the Demmler–Reinsch basis: with the penalty matrix
K = Q R⁻¹ Qᵀ of the natural cubic spline (Green & Silverman, *Nonparametric Regression and
Generalized Linear Models*, §2.1), B = W^-½ K W^-½ = U diag(d) Uᵀ gives

    H(λ) = W^-½ U diag(1 / (1 + λ d)) Uᵀ W^½,   tr H(λ) = Σ 1 / (1 + λ dᵢ),

so each evaluation is O(n), and the fitted values are H(λ) y (:class:`SplineBasis`, built once
per sweep). The result is scipy's up to the
tolerance of the λ search (tests/identification/test_identification.py compares them).

The bound (0, n) is in the units of x (mm, or rad for a rotary axis), so it caps the smoothing
differently per axis (a 50-position sweep keeps at least 7.6 effective degrees of freedom at
1 mm steps, 3.0 at 0.2 mm, 2.4 at 7.2° and 2.0 at 1°). Where it leaves more than
MIN_DEGREES_OF_FREEDOM (3: the X and Y sweeps) and the sweep's repeats give the noise of a
position's mean, the choice goes on beyond GCV's (:meth:`SplineBasis.roughness`): the smoothest
fit, down to 3 degrees of freedom, whose weighted residual sum of squares that noise explains
(below the 95 % point of χ² with n − tr H degrees of freedom: the discrepancy principle). On
white noise GCV's curve is flat enough there to pick 10–15 degrees of freedom by chance; on the
10-seed demo-size panel that left X's εx 3.4–4.2″ off the truth on two seeds, where the repeats'
scatter (independent between repeats on X and Y: the per-position means scatter as the repeats
over √n do) shows that 3 explain the data (``python bench/seed_panel.py --mode profiles``). The
Z, A and C sweeps keep GCV's choice: their bound leaves 3 or fewer, and Z's detector error, smooth
along Z and shared by the repeats, is not white (docs/history.md). A sweep without repeats keeps
GCV's choice too.
Why GCV rather than REML or a GCV that charges each degree of freedom more: docs/history.md
(2026-11-22, "The PDGE smoothers' roughness" and "Seed 11's σ² of 19").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq, minimize_scalar
from scipy.stats import chi2

MIN_POINTS = 5
"""Fewer points are returned unsmoothed (scipy needs at least 5)."""

MIN_DEGREES_OF_FREEDOM = 3.0
"""Where scipy's bound λ = n leaves more effective degrees of freedom than this and the sweep has
repeats, the smoother's choice may go on up to the λ that leaves this many (module docstring)."""

DISCREPANCY_GRID = 60
"""Roughnesses tried, log-spaced from the smoothest down to GCV's, by :meth:`SplineBasis.roughness`."""


def penalty_matrix(x: np.ndarray) -> np.ndarray:
    """(n, n) K with ∫ f''² = gᵀ K g for the natural cubic spline through the values g at the
    strictly increasing abscissas x (n,): Green & Silverman's Q R⁻¹ Qᵀ (units: 1 / x³)."""
    x = np.asarray(x, dtype=float)
    n = x.size
    h = np.diff(x)
    Q = np.zeros((n, n - 2))
    j = np.arange(n - 2)
    Q[j, j] = 1.0 / h[:-1]
    Q[j + 1, j] = -1.0 / h[:-1] - 1.0 / h[1:]
    Q[j + 2, j] = 1.0 / h[1:]
    R = np.diag((h[:-1] + h[1:]) / 3.0)
    R[j[:-1], j[:-1] + 1] = R[j[:-1] + 1, j[:-1]] = h[1:-1] / 6.0
    return Q @ np.linalg.solve(R, Q.T)


@dataclass(frozen=True)
class SplineBasis:
    """The Demmler–Reinsch basis of the smoothing spline through x (n,) with weights w (n,):
    sw = √w, and d (n,) ≥ 0, U (n, n) with W^-½ K W^-½ = U diag(d) Uᵀ. Built once per abscissas
    and weights, it gives the hat matrix and the GCV choice of every column without a solve."""

    sw: np.ndarray
    d: np.ndarray
    U: np.ndarray

    @classmethod
    def of(cls, x: np.ndarray, w: np.ndarray) -> SplineBasis:
        sw = np.sqrt(np.asarray(w, dtype=float))
        d, U = np.linalg.eigh(penalty_matrix(x) / np.outer(sw, sw))
        return cls(sw, np.clip(d, 0.0, None), U)  # the two zero eigenvalues come out at ±rounding

    def hat(self, lam: float) -> np.ndarray:
        """(n, n) hat matrix at roughness ``lam``: fitted values H @ y = (W + λ K)⁻¹ W y."""
        return (self.U / self.sw[:, None]) * (1.0 / (1.0 + lam * self.d)) @ (self.U.T * self.sw)

    def gcv_roughness(self, y: np.ndarray) -> float:
        """λ minimising GCV(λ) for the values y (n,), over (0, n) by scipy's bounded search; each
        evaluation is O(n) (module docstring)."""
        n, d, U, sw = self.d.size, self.d, self.U, self.sw
        z = U.T @ (sw * y / (np.max(np.abs(y)) or 1.0))  # GCV's minimiser is scale free in y

        def gcv(lam: float) -> float:
            shrink = lam * d / (1.0 + lam * d)  # 1 − the eigenvalues of H
            res = (U @ (shrink * z)) / sw
            return float(res @ res / n / (1.0 - np.sum(1.0 / (1.0 + lam * d)) / n) ** 2)

        est = minimize_scalar(gcv, bounds=(0, n), method="bounded")
        if not est.success:
            raise ValueError(f"no minimum of the GCV function: {est.message}")
        return float(est.x)

    def roughness(self, y: np.ndarray, noise_var: float | None = None) -> float:
        """The λ of the values y (n,): GCV's (:meth:`gcv_roughness`), except where scipy's bound λ = n
        leaves more than MIN_DEGREES_OF_FREEDOM and the repeats give the noise (``noise_var``: the
        variance of a point of unit weight): there the smoothest fit between GCV's and the λ that
        leaves MIN_DEGREES_OF_FREEDOM whose residuals the noise explains, Σ wᵢ rᵢ² / noise_var
        within the 95 % point of χ² with n − tr H(λ) degrees of freedom (module docstring)."""
        lam = self.gcv_roughness(y)
        lam_max = self.roughness_at(MIN_DEGREES_OF_FREEDOM)
        if noise_var is None or not noise_var > 0 or lam_max <= self.d.size or lam >= lam_max:
            return lam
        z = self.U.T @ (self.sw * y)
        n = self.d.size
        for candidate in np.exp(np.linspace(np.log(lam_max), np.log(lam), DISCREPANCY_GRID)):
            shrink = candidate * self.d / (1.0 + candidate * self.d)
            if np.sum((shrink * z) ** 2) / noise_var <= chi2.ppf(0.95, n - self.degrees_of_freedom(candidate)):
                return float(max(candidate, lam))
        return lam

    def degrees_of_freedom(self, lam: float) -> float:
        """tr H(λ): the effective degrees of freedom of the fit at roughness ``lam``."""
        return float(np.sum(1.0 / (1.0 + lam * self.d)))

    def roughness_at(self, dof: float) -> float:
        """The λ at which tr H(λ) = ``dof`` (> 2, the straight line's)."""
        lo, hi = 0.0, 1.0
        while self.degrees_of_freedom(hi) > dof:
            lo, hi = hi, hi * 10.0
        return float(brentq(lambda lam: self.degrees_of_freedom(lam) - dof, lo, hi))


def smooth(x: np.ndarray, Y: np.ndarray, w: np.ndarray, lam: np.ndarray | None = None,
           noise_var: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Smoothing spline of each column of Y (n, m) through x (n,), evaluated at x.

    w: (n,) weights (only their ratios matter; they are normalised to mean 1, which keeps the
    λ search well conditioned). lam: (m,) roughness per column; None chooses it
    (:meth:`SplineBasis.roughness`). noise_var: (m,) the variance of a point of weight mean(w) per
    column, from repeats (None: GCV alone).
    Returns (fitted (n, m), λ (m,)); with fewer than MIN_POINTS points, (Y, NaN)."""
    x, Y = np.asarray(x, float), np.asarray(Y, float)
    if x.size < MIN_POINTS:
        return Y.copy(), np.full(Y.shape[1], np.nan)
    basis = SplineBasis.of(x, np.asarray(w, float) / np.mean(w))
    if lam is None:
        noise = np.full(Y.shape[1], np.nan) if noise_var is None else np.asarray(noise_var, float)
        lam = np.array([basis.roughness(Y[:, k], None if np.isnan(noise[k]) else float(noise[k]))
                        for k in range(Y.shape[1])])
    fitted = np.column_stack([basis.hat(float(lam[k])) @ Y[:, k] for k in range(Y.shape[1])])
    return fitted, lam

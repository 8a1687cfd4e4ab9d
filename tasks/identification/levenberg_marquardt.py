"""Levenberg–Marquardt with the damping of eq. 22 and an SVD that names what the data cannot fix.

    Δδ = (JᵀJ + λ D)⁻¹ Jᵀ e,   D = diag(JᵀJ)                                     (eq. 22)

Parameters are handled in "natural" units (the ``steps``: 1 µm or 1″), where the Jacobian's SVD
is meaningful: a direction v with singular value s is known to ±sqrt(σ²)/s natural units. A
direction known no better than ``max_uncertainty`` (default 50 µm or 50″, more than any error it
could hold) is one the data do not excite. Steps are restricted to the identifiable subspace
(the unidentifiable combinations keep their starting value, zero), and a parameter is reported as
unidentifiable when a null direction loads on it. Standard uncertainties come from the truncated
pseudo-inverse of JᵀJ scaled by the residual variance.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from tasks.core.units import MAX_UNCERTAINTY


@dataclass
class FitResult:
    """x: (P,) solution. covariance: (P, P) (NaN rows/cols for unidentifiable parameters).
    identifiable: (P,) bool. null_space: (P, K) unit directions the data cannot fix.
    singular_values: (P,) of the Jacobian in natural units (per µm or arcsec). sigma2: residual variance factor.
    iterations, converged, cost (½‖e‖² at x), residual (M,) at x, jacobian (M, P) at x."""

    x: np.ndarray
    covariance: np.ndarray
    identifiable: np.ndarray
    null_space: np.ndarray
    singular_values: np.ndarray
    sigma2: float
    iterations: int
    converged: bool
    cost: float
    residual: np.ndarray
    jacobian: np.ndarray

    @property
    def uncertainty(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))


def right_singular(Jn: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Singular values (P,) (descending) and right singular vectors Vt (P, P) of Jn (M, P), from the
    eigen-decomposition of the small Gram matrix JnᵀJn. Cheaper than an SVD of the tall Jn and
    free of multi-threaded BLAS contention; accurate for the conditions met here (natural units,
    condition numbers ≲ 1e6)."""
    w, V = np.linalg.eigh(Jn.T @ Jn)
    order = np.argsort(w)[::-1]
    return np.sqrt(np.maximum(w[order], 0.0)), V[:, order].T


def numerical_jacobian(fun: Callable[[np.ndarray], np.ndarray], x: np.ndarray, steps: np.ndarray,
                       f0: np.ndarray | None = None) -> np.ndarray:
    """Central differences with one step per parameter (in its own units): (M, P)."""
    cols = []
    for j in range(x.size):
        dx = np.zeros_like(x)
        dx[j] = steps[j]
        cols.append((fun(x + dx) - fun(x - dx)) / (2 * steps[j]))
    return np.column_stack(cols)


def levenberg_marquardt(fun: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, steps: np.ndarray, *,
                        tau: float = 1e-5, max_iter: int = 50, max_uncertainty: float = MAX_UNCERTAINTY,
                        lam0: float = 1e-3) -> FitResult:
    """Minimise ½‖fun(x)‖² from x0. fun returns whitened residuals (M,). steps: (P,) difference steps.

    Convergence (τ of the paper): the step is below τ·(‖x‖ + τ) in scaled units, or the relative
    decrease of the cost is below τ."""
    x = np.asarray(x0, dtype=float).copy()
    e = fun(x)
    cost = 0.5 * e @ e
    lam, converged, iterations = lam0, False, 0
    J = numerical_jacobian(fun, x, steps, e)
    sigma = 1.0  # whitened residuals: unit variance if the covariances are right
    for it in range(1, max_iter + 1):
        iterations = it
        s, Vt = right_singular(J * steps)  # natural units
        keep = sigma / np.maximum(s, 1e-300) < max_uncertainty
        V = Vt[keep].T * steps[:, None]  # identifiable subspace, back in internal units (x = steps · x_natural)
        norms = np.linalg.norm(J @ V, axis=0)
        norms[norms == 0] = 1.0
        V = V / norms
        A = V.T @ (J.T @ J) @ V
        g = V.T @ (J.T @ e)
        D = np.diag(np.diag(A))
        accepted = False
        for _ in range(20):
            step_s = -np.linalg.solve(A + lam * D, g)  # eq. 22 in the identifiable subspace
            x_new = x + V @ step_s
            e_new = fun(x_new)
            cost_new = 0.5 * e_new @ e_new
            if cost_new <= cost:
                accepted = True
                break
            lam *= 10.0
        if not accepted:
            converged = True
            break
        rel = (cost - cost_new) / max(cost, 1e-300)
        small_step = np.linalg.norm((x_new - x) / steps) <= tau * (np.linalg.norm(x / steps) + tau)
        x, e, cost = x_new, e_new, cost_new
        sigma = np.sqrt(max(2 * cost / max(e.size - int(keep.sum()), 1), 1.0))
        lam = max(lam / 10.0, 1e-12)
        J = numerical_jacobian(fun, x, steps, e)
        if small_step or rel < tau:
            converged = True
            break
    s, Vt = right_singular(J * steps)
    dof = max(e.size - x.size, 1)
    sigma2 = float(e @ e / dof)
    keep = np.sqrt(max(sigma2, 1.0)) / np.maximum(s, 1e-300) < max_uncertainty
    null = Vt[~keep].T if (~keep).any() else np.zeros((x.size, 0))  # natural units, unit norm
    identifiable = ~(np.abs(null) > 0.1).any(axis=1) if null.size else np.ones(x.size, bool)
    Vk = Vt[keep].T
    cov_n = Vk @ np.diag(1.0 / s[keep] ** 2) @ Vk.T
    cov = sigma2 * cov_n * np.outer(steps, steps)
    cov[~identifiable, :] = np.nan
    cov[:, ~identifiable] = np.nan
    return FitResult(x, cov, identifiable, null, s, sigma2, iterations, converged, float(cost), e, J)

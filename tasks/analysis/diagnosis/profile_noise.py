"""The PDGE profiles' own uncertainty, propagated to the residual: the metric of the score test.

The profiles are smoothing splines through noisy sweeps. At a five-axis pose their error is not
pose noise: it is one error of the profile, shared by every pose at a similar position of that axis,
so the residual carries correlated structure along each axis even when the model lacks nothing.
A candidate that bends a profile (a camera 2 effect on the A sweep, a sag of A) can fit that
structure; the white-noise F-test would call it significant, and so would a cross-validation over
five-axis poses, which all share the same profiles.

Its covariance in the whitened residual space: each sweep image's pose noise n (covariance C_n plus
the fit's floor) moves the error motion the extraction reads by S_n n (S_n: the imaging channel of
:mod:`tasks.analysis.diagnosis.sensitivity`), the extraction maps that to the profile (operator O_j of
:mod:`tasks.identification.pdge_response`) and the profile to the residual (interpolation I_j and the
joint's sensitivity D_j):

    Σ = I + Σ_j L_j L_jᵀ,   L_j = W D_j I_j O_j blockdiag(S_n chol(C_n))                    (4)

plus, inside each L_j, the smoothing spline's bias allowance (its Bayesian posterior covariance
minus the sampling one, :func:`tasks.identification.pdge_response.smoothing_bias_covariance`): what the
spline smooths away of the true profile is another error shared by the poses near a position.

(the camera 1 sweep images' own rows are treated as if their noise were independent of the profile
they made: this overstates Σ along smooth directions there, which errs on the side of "not
significant"). The score test of :mod:`tasks.analysis.diagnosis.score` runs on Σ^(-1/2)-transformed residual and
columns (generalised least squares); Σ = I + U diag(s) Uᵀ with U orthonormal (M, r) keeps the
transform cheap: Σ^(-1/2) x = x − U ((1 − (1 + s)^(-1/2)) ⊙ Uᵀ x).
"""

from __future__ import annotations

import numpy as np

from tasks.analysis.diagnosis.linearisation import Linearisation
from tasks.analysis.diagnosis.sensitivity import IMAGING
from tasks.identification.pige_identification import COV_FLOOR

MIN_VARIANCE = 0.05  # directions of Σ − I below this (in units of the pose noise) are dropped: ≤ 2.5 % of a weight


def profile_noise(lin: Linearisation) -> tuple[np.ndarray, np.ndarray]:
    """(U (M, r), s (r,)) with Σ − I = U diag(s) Uᵀ, eq. (4), in the whitened residual space."""
    cols = []
    for axis, link in lin.sweeps.items():
        resp = link.response
        S = link.sensitivity.blocks.get(IMAGING)
        if S is None:
            continue
        B = S @ np.linalg.cholesky(resp.sweep.cov + COV_FLOOR)  # (N_j, 6, 6): error-motion noise factor
        k6 = resp.operator.shape[0]
        F = np.einsum("pnc,ncd->pnd", resp.operator.reshape(k6, -1, 6), B).reshape(k6, -1)  # (6K, 6N_j)
        cov = F @ F.T + (resp.smoothing_cov if resp.smoothing_cov is not None else 0.0)
        w, V = np.linalg.eigh(cov)  # profile covariance, (6K, 6K)
        keep = w > 1e-12 * max(w.max(), 1e-300)
        factor = V[:, keep] * np.sqrt(w[keep])  # (6K, r_j)
        dP = factor.T.reshape(-1, k6 // 6, 6)  # (r_j, K, 6)
        at = np.matmul(link.interpolation, dP)  # (r_j, N, 6)
        col = lin.sensitivity.apply({("joint", axis): at})
        if col is not None:
            cols.append(col.reshape(col.shape[0], -1).T)
    if not cols:
        return np.zeros((lin.residual.size, 0)), np.zeros(0)
    L = np.hstack(cols)
    w, V = np.linalg.eigh(L.T @ L)
    keep = w > MIN_VARIANCE
    return L @ (V[:, keep] / np.sqrt(w[keep])), w[keep]


def gls_transform(U: np.ndarray, s: np.ndarray):
    """x (M,) or (M, k) or (B, M, k) -> Σ^(-1/2) x along the M axis (the second to last for 3-D input)."""
    d = 1.0 - 1.0 / np.sqrt(1.0 + s)

    def transform(x: np.ndarray) -> np.ndarray:
        if U.shape[1] == 0:
            return x
        if x.ndim == 1:
            return x - U @ (d * (U.T @ x))
        if x.ndim == 2:
            return x - U @ (d[:, None] * (U.T @ x))
        b, m, k = x.shape  # one product for the whole batch: (M, B·k)
        flat = x.transpose(1, 0, 2).reshape(m, b * k)
        return (flat - U @ (d[:, None] * (U.T @ flat))).reshape(m, b, k).transpose(1, 0, 2)

    return transform

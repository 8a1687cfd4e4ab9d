"""Score test of candidate columns against the current whitened residual, the model's own columns
projected out.

With r (M,) the whitened residual at the fit's solution, J (M, P) the model's own columns and a
candidate's columns G (M, k) (:mod:`tasks.analysis.diagnosis.linearisation`), the candidate's new
directions are G⊥ = (I − Q Qᵀ) G, Q an orthonormal basis of J's range. Adding the candidate and
refitting (one Gauss–Newton step: the problem is linear to far below the noise) removes

    ΔRSS = rᵀ G⊥ (G⊥ᵀ G⊥)⁺ G⊥ᵀ r                                                       (2)

from RSS = rᵀr, at amplitudes a = −(G⊥ᵀ G⊥)⁺ G⊥ᵀ r (r changes by G a). Reported:

- score S = ΔRSS / σ̂², σ̂² = RSS / (M − P): the score (Lagrange-multiplier) statistic, χ²_k under
  "the candidate is absent" when the residual is noise;
- F = (ΔRSS / k) / ((RSS − ΔRSS) / (M − P − k)) and its p-value (F-test of nested least squares);
- ΔBIC = M ln((RSS − ΔRSS) / RSS) + k ln M (Gaussian likelihood, σ profiled out); negative favours
  the candidate, below −10 is "very strong";
- predicted RMS = √((RSS − ΔRSS) / M), whitened (1 = the pose noise the covariances describe);
- visible = max_a ‖G⊥ a‖ / ‖G_raw a‖: the largest fraction of the candidate's raw signature (without
  the PDGE splines' response and the projection) that the model cannot reproduce. Below 0.1 the
  candidate is *absorbed*; a zero raw column is *unseen* (no camera sees it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

RANK_TOL = 1e-9  # relative singular-value floor for ranks
ABSORBED = 0.1  # visible fraction below which a candidate is absorbed by the model


def orthonormal_basis(A: np.ndarray, tol: float = RANK_TOL) -> np.ndarray:
    """(M, r) orthonormal basis of the column space of A (M, P)."""
    if A.size == 0:
        return np.zeros((A.shape[0], 0))
    # from the small Gram matrix (a tall SVD is slow under multi-threaded BLAS on a busy machine);
    # columns scaled to unit norm first so that their units do not matter
    norms = np.linalg.norm(A, axis=0)
    As = A[:, norms > 0] / norms[norms > 0]
    if As.shape[1] == 0:
        return np.zeros((A.shape[0], 0))
    w, V = np.linalg.eigh(As.T @ As)
    keep = w > tol * max(w.max(), 1e-300)
    U = As @ (V[:, keep] / np.sqrt(w[keep]))
    # one re-orthogonalisation pass against the Gram route's loss of accuracy
    Q, _ = np.linalg.qr(U)
    return Q


def _pinv_psd(A: np.ndarray, tol: float = RANK_TOL) -> tuple[np.ndarray, np.ndarray]:
    """Pseudo-inverse of symmetric PSD matrices (B, k, k) and their ranks (B,)."""
    w, V = np.linalg.eigh(A)
    floor = tol * np.maximum(w.max(axis=-1, keepdims=True), 1e-300)
    keep = w > floor
    inv_w = np.where(keep, 1.0 / np.where(keep, w, 1.0), 0.0)
    return np.einsum("bij,bj,bkj->bik", V, inv_w, V), keep.sum(axis=-1)


@dataclass
class Scores:
    """Per candidate (B,): delta_rss, k (rank of G⊥), amplitude (B, k_max) in units of the columns,
    visible, raw_norm."""

    delta_rss: np.ndarray
    k: np.ndarray
    amplitude: np.ndarray
    visible: np.ndarray
    raw_norm: np.ndarray


class Scorer:
    """The current residual and the span of the model's columns (own plus accepted effects), in the
    metric ``transform`` (default: the whitened residual as it is; :mod:`tasks.analysis.diagnosis.profile_noise`
    gives the one that accounts for the PDGE profiles' uncertainty). Columns passed to the methods are
    untransformed whitened columns; the transform is applied here."""

    def __init__(self, residual: np.ndarray, own: np.ndarray, transform=None):
        self.transform = transform or (lambda x: x)
        self.r = self.transform(np.asarray(residual, dtype=float)).copy()
        self.Q = orthonormal_basis(self.transform(own))
        self.M = self.r.size

    @property
    def P(self) -> int:
        return self.Q.shape[1]

    @property
    def rss(self) -> float:
        return float(self.r @ self.r)

    def project(self, G: np.ndarray) -> np.ndarray:
        """(B, M, k) -> G⊥ = (I − Q Qᵀ) G."""
        return G - self.Q @ (self.Q.T @ G)

    def score(self, G: np.ndarray, raw: np.ndarray | None = None) -> Scores:
        """Eq. (2) for B candidates of k columns each: G (B, M, k), raw (B, M, k) (default G)."""
        G = self.transform(G)
        raw = None if raw is None else self.transform(raw)
        Gp = self.project(G)
        A = np.einsum("bmi,bmj->bij", Gp, Gp)
        g = np.einsum("bmi,m->bi", Gp, self.r)
        Ainv, k = _pinv_psd(A)
        c = np.einsum("bij,bj->bi", Ainv, g)
        delta = np.einsum("bi,bi->b", g, c)
        raw = G if raw is None else raw
        R = np.einsum("bmi,bmj->bij", raw, raw)
        raw_norm = np.sqrt(np.trace(R, axis1=1, axis2=2))
        # a signature seen only through the PDGE profiles (e.g. a camera 2 effect on the A sweep) is
        # measured against itself
        only_through_pdge = raw_norm == 0
        R[only_through_pdge] = np.einsum("bmi,bmj->bij", G[only_through_pdge], G[only_through_pdge])
        raw_norm = np.sqrt(np.trace(R, axis1=1, axis2=2))
        Rinv, _ = _pinv_psd(R)
        # largest generalised eigenvalue of (A, R): max ‖G⊥ a‖² / ‖G_raw a‖²
        visible = np.sqrt(np.clip([np.max(np.real(np.linalg.eigvals(Ri @ Ai))) if rn > 0 else 0.0
                                   for Ri, Ai, rn in zip(Rinv, A, raw_norm, strict=True)], 0.0, None))
        return Scores(delta, k, -c, visible, raw_norm)

    def statistics(self, delta_rss: np.ndarray, k: np.ndarray) -> dict[str, np.ndarray]:
        """score, F, p_value, delta_bic, predicted_rms, explained for ΔRSS (B,) with k (B,) columns."""
        delta_rss = np.clip(np.asarray(delta_rss, float), 0.0, self.rss)
        k = np.maximum(np.asarray(k, float), 1.0)
        dof0 = max(self.M - self.P, 1)
        dof1 = np.maximum(dof0 - k, 1.0)
        rss1 = np.maximum(self.rss - delta_rss, 1e-300)
        F = (delta_rss / k) / (rss1 / dof1)
        return {
            "score": delta_rss / (self.rss / dof0),
            "F": F,
            "p_value": stats.f.sf(F, k, dof1),
            "delta_bic": self.M * np.log(rss1 / self.rss) + k * np.log(self.M),
            "predicted_rms": np.sqrt(rss1 / self.M),
            "explained": delta_rss / max(self.rss, 1e-300),
        }

    def accept(self, G: np.ndarray) -> None:
        """Add the candidate's columns G (M, k) to the model: the residual loses what they explain."""
        Gp = orthonormal_basis(self.project(self.transform(G)[None])[0])
        self.r = self.r - Gp @ (Gp.T @ self.r)
        self.Q = np.hstack([self.Q, Gp])

    def conditional(self, G_a: np.ndarray, G_b: np.ndarray) -> tuple[float, float]:
        """(ΔRSS, p) of adding G_a (M, k_a) to a model that already holds G_b (M, k_b): can the data
        prefer a over b? F-test against the residual after both."""
        G_a, G_b = self.transform(G_a), self.transform(G_b)
        Qb = orthonormal_basis(np.hstack([self.Q, self.project(G_b[None])[0]]))
        rb = self.r - Qb @ (Qb.T @ self.r)
        Ga = G_a - Qb @ (Qb.T @ G_a)
        Qa = orthonormal_basis(Ga)
        delta = float(np.sum((Qa.T @ rb) ** 2))
        k = max(Qa.shape[1], 1)
        dof = max(self.M - Qb.shape[1] - k, 1)
        F = (delta / k) / (max(rb @ rb - delta, 1e-300) / dof)
        return delta, float(stats.f.sf(F, k, dof))

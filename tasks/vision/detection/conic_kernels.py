"""Compiled per-point loops of the batched conic tests (:mod:`tasks.vision.detection.conics`).

The Sampson distances of every point to its set's conic (or to each of a set's RANSAC
hypotheses) and the ellipse test, written as loops over the points instead of a dozen numpy
operations on (K, N) or (K, H, N) temporaries. Each value is computed with the same floating-point
operations in the same order as the numpy form (no fused multiply–adds; ``math.hypot`` is the C
library's, as numpy's), so the results are the same to every bit. Units: those of the points.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_COMPILED = {"cache": True, "nogil": True}


@njit(inline="always", **_COMPILED)
def _abs_sampson(c, x, y):  # pragma: no cover - compiled
    """|Q(x, y)| / max(|∇Q(x, y)|, 1e-12) for the conic c (6,) (NaN for a NaN conic)."""
    a, b, cc, d, e, f = c[0], c[1], c[2], c[3], c[4], c[5]
    q = a * x * x + b * x * y + cc * y * y + d * x + e * y + f
    qx = 2 * a * x + b * y + d
    qy = b * x + 2 * cc * y + e
    g = math.hypot(qx, qy)
    return abs(q / (1e-12 if g < 1e-12 else g))


@njit(inline="always", **_COMPILED)
def _is_ellipse(c):  # pragma: no cover - compiled
    """A real, non-degenerate ellipse with its centre inside (:func:`conics.is_ellipse`)."""
    a, b, cc, d, e, f = c[0], c[1], c[2], c[3], c[4], c[5]
    disc = b * b - 4 * a * cc
    det = 4 * a * cc - b * b
    if not (np.isfinite(disc) and disc < 0) or abs(det) < 1e-300:
        return False
    xc = (b * e - 2 * cc * d) / det
    yc = (b * d - 2 * a * e) / det
    q = a * xc * xc + b * xc * yc + cc * yc * yc + d * xc + e * yc + f
    return q * a < 0


@njit(**_COMPILED)
def abs_sampson_distances(conics, x, y):  # pragma: no cover - compiled
    """(K, N) |Sampson distance| of the points x, y (K, N) to their set's conic (K, 6)."""
    k_sets, n = x.shape
    out = np.empty((k_sets, n))
    for k in range(k_sets):
        c = conics[k]
        for i in range(n):
            out[k, i] = _abs_sampson(c, x[k, i], y[k, i])
    return out


@njit(**_COMPILED)
def best_hypothesis_inliers(conics, complete, x, y, valid, threshold):  # pragma: no cover - compiled
    """(K, N) inliers of each set's best RANSAC hypothesis: conics (K, H, 6), complete (K, H) its five
    points all valid, points x, y, valid (K, N), threshold (K,) Sampson distance. A hypothesis
    counts when complete and an ellipse; the first with the most inliers (valid points nearer
    than the threshold) wins; fewer than 5 inliers give an empty mask."""
    k_sets, n = x.shape
    mask = np.zeros((k_sets, n), np.bool_)
    for k in range(k_sets):
        best, best_h = -1, 0
        for h in range(conics.shape[1]):
            c = conics[k, h]
            if not (complete[k, h] and _is_ellipse(c)):
                continue
            score = 0
            for i in range(n):
                if _abs_sampson(c, x[k, i], y[k, i]) < threshold[k] and valid[k, i]:
                    score += 1
            if score > best:
                best, best_h = score, h
        if best >= 5:
            c = conics[k, best_h]
            for i in range(n):
                mask[k, i] = _abs_sampson(c, x[k, i], y[k, i]) < threshold[k] and valid[k, i]
    return mask


@njit(**_COMPILED)
def trace_constraint_rows(x, y):  # pragma: no cover - compiled
    """Rows (K, N, 5) [x² − y², xy, x, y, 1] and right-hand sides (K, N) −y² of the conic fit
    A (x² − y²) + B xy + D x + E y + F = −y², in the points' own precision."""
    k_sets, n = x.shape
    m = np.empty((k_sets, n, 5), x.dtype)
    rhs = np.empty((k_sets, n), x.dtype)
    for k in range(k_sets):
        for i in range(n):
            xi, yi = x[k, i], y[k, i]
            m[k, i, 0] = xi * xi - yi * yi
            m[k, i, 1] = xi * yi
            m[k, i, 2] = xi
            m[k, i, 3] = yi
            m[k, i, 4] = 1.0
            rhs[k, i] = -(yi * yi)
    return m, rhs


@njit(**_COMPILED)
def weighted_rows(m, w):  # pragma: no cover - compiled
    """(K, N, 5) float64 rows m (K, N, 5) times their weights w (K, N)."""
    k_sets, n, n_c = m.shape
    out = np.empty((k_sets, n, n_c))
    for k in range(k_sets):
        for i in range(n):
            wi = w[k, i]
            for c in range(n_c):
                out[k, i, c] = m[k, i, c] * wi
    return out


@njit(**_COMPILED)
def gradient_squared(conics, x, y):  # pragma: no cover - compiled
    """|∇Q|² (K, N) of each set's conic (K, 6) at its points x, y (K, N)."""
    k_sets, n = x.shape
    out = np.empty((k_sets, n))
    for k in range(k_sets):
        a, b, c, d, e = conics[k, 0], conics[k, 1], conics[k, 2], conics[k, 3], conics[k, 4]
        for i in range(n):
            xi, yi = x[k, i], y[k, i]
            qx = 2 * a * xi + b * yi + d
            qy = b * xi + 2 * c * yi + e
            out[k, i] = qx * qx + qy * qy
    return out

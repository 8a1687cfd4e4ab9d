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

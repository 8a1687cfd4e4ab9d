"""Batched conic (ellipse) fitting in pixel coordinates.

A conic is the 6-vector ``(A, B, C, D, E, F)`` of ``A x² + B xy + C y² + D x + E y + F = 0``.
Every function works on a batch of K point sets at once, each padded to the same length N with
a boolean ``valid`` mask, so that fitting all dots of a plate is one call (the per-point loops are
compiled, :mod:`tasks.vision.detection.conic_kernels`). Points are given in px; each set is
normalised internally (shifted by ``origin`` and divided by ``scale``) for conditioning, and
conics are returned in those normalised coordinates together with the ``origin`` (K, 2) px and
``scale`` (K,) px needed to map back (see :func:`ellipse_params`).
"""

from __future__ import annotations

import numpy as np

from tasks.vision.detection.conic_kernels import (
    abs_sampson_distances,
    best_hypothesis_inliers,
    gradient_squared,
    trace_constraint_rows,
    weighted_rows,
)


def _design(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(..., 6) monomials [x², xy, y², x, y, 1]."""
    return np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=-1)


def conic_value_and_grad(conic: np.ndarray, x: np.ndarray, y: np.ndarray):
    """Algebraic value Q(x, y) and gradient (Qx, Qy); conic (..., 6) broadcast against x, y."""
    a, b, c, d, e, f = (conic[..., i] for i in range(6))
    q = a * x * x + b * x * y + c * y * y + d * x + e * y + f
    qx = 2 * a * x + b * y + d
    qy = b * x + 2 * c * y + e
    return q, qx, qy


def sampson_distance(conic: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """First-order geometric (Sampson) distance of points to conics, same units as x, y."""
    q, qx, qy = conic_value_and_grad(conic, x, y)
    return q / np.maximum(np.hypot(qx, qy), 1e-12)


def abs_sampson_distance(conics: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """|:func:`sampson_distance`| (K, N) of K sets of points x, y (K, N) to their own conic (K, 6)."""
    return abs_sampson_distances(np.ascontiguousarray(conics, dtype=float), np.ascontiguousarray(x, dtype=float),
                                 np.ascontiguousarray(y, dtype=float))


def fit_conic_lsq(
    x: np.ndarray, y: np.ndarray, weights: np.ndarray, sampson_iterations: int = 2
) -> np.ndarray:
    """Least-squares conics through K weighted point sets, normalised by A + C = 1.

    x, y, weights: (K, N) in normalised coordinates (weights 0 drop a point). The trace
    constraint A + C = 1 is invariant to rotation and translation and never excludes an ellipse.
    Then ``sampson_iterations`` re-weightings by 1/|∇Q|² turn the algebraic residual into the
    first-order geometric one, which removes most of the algebraic fit's bias.
    Returns (K, 6) conics; rows with fewer than 5 weighted points come back as NaN.
    """
    w = np.asarray(weights, dtype=float)
    x, y = (np.ascontiguousarray(v, dtype=np.result_type(x, y)) for v in (x, y))
    m, rhs = trace_constraint_rows(x, y)  # A (x² − y²) + B xy + D x + E y + F = −y²: (K, N, 5), (K, N)
    enough = (w > 0).sum(axis=1) >= 5
    conic = np.full((*x.shape[:-1], 6), np.nan)
    ww = w.copy()
    for it in range(sampson_iterations + 1):
        mtw = np.swapaxes(weighted_rows(m, np.ascontiguousarray(ww)), 1, 2)  # (K, 5, N)
        ata = np.matmul(mtw, m)  # (K, 5, 5)
        atb = np.matmul(mtw, rhs[..., None])[..., 0]
        ridge = 1e-12 * np.trace(ata, axis1=1, axis2=2)[:, None, None] * np.eye(5)
        ata = ata + ridge
        ata[~enough] = np.eye(5)
        p = np.linalg.solve(ata, atb[..., None])[..., 0]  # (K, 5)
        conic = np.stack([p[:, 0], p[:, 1], 1.0 - p[:, 0], p[:, 2], p[:, 3], p[:, 4]], axis=-1)
        if it < sampson_iterations:
            g2 = gradient_squared(conic, x, y)
            ref = (w * g2).sum(axis=1, keepdims=True) / np.maximum(w.sum(axis=1, keepdims=True), 1e-12)
            ref = np.where(np.isfinite(ref) & (ref > 0), ref, 1.0)
            ww = w * (ref / np.maximum(g2, 1e-6 * ref))
    conic[~enough] = np.nan
    return conic


def conic_through_five(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Conics through 5 points each: x, y (..., 5) → (..., 6), unit norm.

    Solved with F = −1, i.e. for conics that do not pass through the origin: callers normalise
    points about the ellipse's own (approximate) centre, which lies inside it. Degenerate
    samples come back as NaN.
    """
    d = np.stack([x * x, x * y, y * y, x, y], axis=-1)  # (..., 5, 5)
    ok = np.abs(np.linalg.det(d)) > 1e-12
    d = np.where(ok[..., None, None], d, np.eye(5))
    p = np.linalg.solve(d, np.ones((*x.shape, 1)))[..., 0]  # (..., 5)
    conic = np.concatenate([p, -np.ones((*x.shape[:-1], 1))], axis=-1)
    conic /= np.linalg.norm(conic, axis=-1, keepdims=True)
    return np.where(ok[..., None], conic, np.nan)


def is_ellipse(conic: np.ndarray) -> np.ndarray:
    """True where the conic (..., 6) is a real, non-degenerate ellipse."""
    a, b, c = conic[..., 0], conic[..., 1], conic[..., 2]
    disc = b * b - 4 * a * c
    ok = np.isfinite(disc) & (disc < 0)
    xc, yc = _centre(conic)
    q, _, _ = conic_value_and_grad(conic, xc, yc)
    # the centre must lie inside: Q(centre) has the opposite sign of A (and C)
    return ok & (q * a < 0)


def _centre(conic: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b, c, d, e = (conic[..., i] for i in range(5))
    det = 4 * a * c - b * b
    det = np.where(np.abs(det) < 1e-300, np.nan, det)
    xc = (b * e - 2 * c * d) / det
    yc = (b * d - 2 * a * e) / det
    return xc, yc


def ellipse_params(conic: np.ndarray, origin: np.ndarray, scale: np.ndarray):
    """Centre (K, 2) px, semi-axes (K, 2) px (major, minor) and major-axis angle (K,) rad.

    ``conic`` (K, 6) in the coordinates ``(p - origin) / scale``.
    """
    conic = np.where((conic[..., 0] + conic[..., 2] < 0)[..., None], -conic, conic)
    a, b, c = conic[..., 0], conic[..., 1], conic[..., 2]
    xc, yc = _centre(conic)
    q0, _, _ = conic_value_and_grad(conic, xc, yc)  # value at the centre
    # quadratic part eigen-decomposition: [[a, b/2], [b/2, c]]
    tr = a + c
    diff = np.sqrt((a - c) ** 2 + b * b)
    lam1, lam2 = (tr + diff) / 2, (tr - diff) / 2
    with np.errstate(invalid="ignore", divide="ignore"):
        ax1 = np.sqrt(-q0 / lam1)
        ax2 = np.sqrt(-q0 / lam2)
    major = np.fmax(ax1, ax2)
    minor = np.fmin(ax1, ax2)
    # eigenvector of the smaller |lambda| (the major axis)
    theta = 0.5 * np.arctan2(b, a - c)  # direction of lam1's eigenvector
    theta = np.where(ax1 >= ax2, theta, theta + np.pi / 2)
    centre = np.stack([xc, yc], axis=-1) * scale[..., None] + origin
    axes = np.stack([major, minor], axis=-1) * scale[..., None]
    return centre, axes, theta


def conic_matrix(conic: np.ndarray) -> np.ndarray:
    """(..., 6) conic → (..., 3, 3) symmetric matrix in homogeneous coordinates."""
    a, b, c, d, e, f = (conic[..., i] for i in range(6))
    row0 = np.stack([a, b / 2, d / 2], axis=-1)
    row1 = np.stack([b / 2, c, e / 2], axis=-1)
    row2 = np.stack([d / 2, e / 2, f], axis=-1)
    return np.stack([row0, row1, row2], axis=-2)


def conic_centre_h(cm: np.ndarray) -> np.ndarray:
    """Centre (..., 2) of conics given as (..., 3, 3) matrices."""
    return -np.linalg.solve(cm[..., :2, :2], cm[..., :2, 2:3])[..., 0]


def ellipse_radius_along(
    centre: np.ndarray, axes: np.ndarray, theta: np.ndarray, angles: np.ndarray
) -> np.ndarray:
    """Distance (K, R) px from each ellipse centre to its boundary along ray ``angles`` (R,) rad."""
    phi = angles[None, :] - theta[:, None]
    a, b = axes[:, 0:1], axes[:, 1:2]
    return a * b / np.sqrt((b * np.cos(phi)) ** 2 + (a * np.sin(phi)) ** 2)


def ransac_samples(k: int, n: int, n_hypotheses: int, rng: np.random.Generator) -> np.ndarray:
    """Minimal samples for :func:`ransac_ellipse`: (K, H, 5) indices into K sets of n points ordered
    by angle around each set's centre (rays), 5 roughly equally spaced indices with a random start
    and jitter each, so that the samples are well spread. Drawn for all sets at once, so that any
    subset of the sets can then be fitted on its own with the same draws."""
    start = rng.integers(0, n, size=(k, n_hypotheses, 1))
    spacing = np.arange(5) * (n / 5.0)
    jitter = rng.uniform(-0.3, 0.3, size=(k, n_hypotheses, 5)) * (n / 5.0)
    return (start + np.round(spacing + jitter).astype(int)) % n


def ransac_ellipse(
    x: np.ndarray,
    y: np.ndarray,
    valid: np.ndarray,
    threshold: np.ndarray | float,
    samples: np.ndarray,
) -> np.ndarray:
    """RANSAC over minimal 5-point ellipses, all K sets at once.

    x, y, valid: (K, N) normalised points ordered by angle around each set's centre (rays).
    samples: (K, H, 5) indices of the H minimal samples per set (:func:`ransac_samples`).
    threshold: Sampson inlier distance in the same normalised units (scalar or (K,)). Returns the
    (K, N) inlier mask of the best hypothesis per set (all False if none).
    """
    k = x.shape[0]
    kk = np.arange(k)[:, None, None]
    xs, ys, vs = x[kk, samples], y[kk, samples], valid[kk, samples]
    xs = np.where(vs, xs, 0.0)
    ys = np.where(vs, ys, 0.0)
    conics = conic_through_five(xs, ys)  # (K, H, 6)
    thr = np.ascontiguousarray(np.broadcast_to(np.asarray(threshold, dtype=float), (k,)))
    return best_hypothesis_inliers(conics, vs.all(axis=-1), np.ascontiguousarray(x, dtype=float),
                                   np.ascontiguousarray(y, dtype=float), np.ascontiguousarray(valid, dtype=bool), thr)

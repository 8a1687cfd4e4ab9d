"""Edge map of the coarse image: Sobel gradients, Canny with automatic thresholds.

Gradients are Sobel 3×3 derivatives (grey levels per px, ×8 Sobel gain) in the coarse image
frame: gx along +u (columns), gy along +v (rows). Canny runs on these same derivatives, so the
edge pixels and the gradient directions used by the Hough sampling agree exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class EdgeMap:
    """Canny edges and the gradient field of one coarse image (all (H, W) arrays)."""

    edges: np.ndarray  # uint8, 255 on edge pixels
    gx: np.ndarray  # int16, d I / d u (Sobel)
    gy: np.ndarray  # int16, d I / d v
    low: float  # Canny hysteresis thresholds (gradient magnitude, L2)
    high: float


def canny_edges(image: np.ndarray, high_percentile: float = 99.0, high_fraction: float = 0.25,
                min_high: float = 24.0) -> EdgeMap:
    """Canny edges with thresholds derived from the gradient distribution.

    high = max(min_high, 6 × median |∇I|, high_fraction × percentile(|∇I|, high_percentile)),
    low = high / 2: noise sets the floor (median), the strongest edges the scale (percentile).
    """
    # both Sobel 3×3 derivatives (CV_16S, reflected border) in one pass: the integers of two cv2.Sobel calls
    dx, dy = cv2.spatialGradient(image, ksize=3)
    # percentile and median from a strided subsample: cheap and precise enough for thresholds; sorted
    # once, both are a lookup (numpy's selection on the unsorted array costs three times the sort)
    sub = np.sort(gradient_magnitude(dx[::2, ::2], dy[::2, ::2]).ravel())
    hi_p = float(np.percentile(sub, high_percentile)) if sub.size else 0.0
    med = float(np.median(sub)) if sub.size else 0.0
    high = max(min_high, 6.0 * med, high_fraction * hi_p)
    low = 0.5 * high
    edges = cv2.Canny(dx, dy, low, high, L2gradient=True)
    return EdgeMap(edges=edges, gx=dx, gy=dy, low=low, high=high)


def gradient_magnitude(gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """sqrt(gx² + gy²) (float32) of integer Sobel derivatives (|g| < 2¹¹: the squares and their sum
    are exact in float32), correctly rounded: the same bits wherever the arrays lie in memory.
    ``cv2.magnitude``'s is off by an ulp in about a quarter of the pixels, which ones depending on the
    arrays' alignment (the heap's state, so the threads that ran before): the Canny thresholds moved by
    an ulp, and a Hough seed whose gradient is exactly at the high threshold came and went."""
    fx, fy = gx.astype(np.float32), gy.astype(np.float32)
    fx *= fx
    fx += fy * fy
    return np.sqrt(fx, out=fx)


def pixels_where(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows v, columns u) of the non-zero pixels of a 2-D map, in row-major order: ``np.nonzero``'s
    result, through the flat indices (several times faster on a whole image)."""
    flat = np.flatnonzero(mask if mask.dtype == bool else mask != 0)
    return np.divmod(flat, mask.shape[1])


N_DIRECTIONS = 64  # gradient direction codes: code k ↔ angle 2πk/64 from +u towards +v


def direction_codes(em: EdgeMap, edges: np.ndarray) -> np.ndarray:
    """(H, W) uint8 map: quantised gradient direction on edge pixels, 255 elsewhere.

    One uint8 gather then answers both "is this an edge pixel" and "where does its gradient
    point", which is what the Hough sampling and the rim search ask millions of times.
    """
    vs, us = pixels_where(edges)
    phase = np.arctan2(em.gy[vs, us].astype(float), em.gx[vs, us].astype(float))  # rad in (−π, π]
    code = np.rint(phase * (N_DIRECTIONS / (2 * np.pi))).astype(np.int64) % N_DIRECTIONS
    out = np.full(edges.shape, 255, dtype=np.uint8)
    out[vs, us] = code
    return out


def direction_difference(a: np.ndarray, b: np.ndarray | int) -> np.ndarray:
    """Absolute circular difference of direction codes (0 … N_DIRECTIONS/2)."""
    d = (np.asarray(a, dtype=np.int16) - np.asarray(b, dtype=np.int16)) % N_DIRECTIONS
    return np.minimum(d, N_DIRECTIONS - d)

"""Dot candidates from region contours: the fallback when the Hough search finds no grid.

The RRHT needs rim edges; a rim that a shadow edge, JPEG blocks or a busy background break into
short pieces gives it few votes. A printed dot is also a region darker (or lighter) than its
surround: the coarse image is thresholded against its local mean over windows a few dot sizes
wide (one window per octave of dot size, so that a shadow or a light gradient does not move the
threshold across a dot), and each outer contour whose area, convexity and ellipse fit fit a dot
of d_min…d_max becomes a candidate ellipse. Units: px of the coarse image.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree

from tasks.vision.detection.parallel import map_kernel
from tasks.vision.detection.region_kernels import convex_contour_areas, darker_than_mean
from tasks.vision.detection.rrht import CoarseCircles


def contour_candidates(image: np.ndarray, dark_dots: bool, d_min: float, d_max: float,
                       offset_fraction: float = 0.08, min_convexity: float = 0.9,
                       max_fill_error: float = 0.12, contour_counts: list[int] | None = None,
                       means: dict | None = None) -> CoarseCircles:
    """Ellipses (coarse px) of the dot-like regions of ``image`` (uint8, preprocessed).

    offset_fraction: a pixel belongs to a region when it is darker (lighter) than its local mean
    by this fraction of the image's 1–99 % grey range; min_convexity: region area over its convex
    hull's; max_fill_error: |region area / fitted ellipse area − 1| allowed; contour_counts: when
    given, each window's number of regions (of any size and shape) is appended to it; means: when
    given, a store of this ``image``'s local means (float32, by polarity and window) that searches of
    the same image at other offsets fill and reuse (the same bits as made afresh: on a 12 MP image
    each window's mean costs about 20 ms; the caller keeps one store per image, and only where it
    searches the image again).
    """
    lo, hi = np.percentile(image[::4, ::4], (1, 99))
    offset = offset_fraction * max(float(hi - lo), 1.0)
    kept = {} if means is None else means  # without a store each window's mean is freed once used
    if (dark_dots, 0) not in kept:
        kept[dark_dots, 0] = (image if dark_dots else cv2.bitwise_not(image)).astype(np.float32)
    src = kept[dark_dots, 0]
    a_min, a_max = np.pi * (d_min / 2) ** 2 * 0.6, np.pi * (d_max / 2) ** 2 * 1.4
    blocks = []
    block = 2 * d_min
    while block <= 4 * d_max:
        blocks.append(int(block) | 1)
        block *= 2

    def regions(k: int) -> np.ndarray:  # (N, 6) cu, cv, a, b, θ, area of one window's dot-like regions
        mean = kept.get((dark_dots, k))
        if mean is None:
            mean = cv2.blur(src, (k, k), borderType=cv2.BORDER_REFLECT)
            if means is not None:
                kept[dark_dots, k] = mean
        mask = darker_than_mean(src, mean, np.float32(offset))  # findContours takes any non-zero
        del mean
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        if contour_counts is not None:
            contour_counts.append(len(contours))
        areas, convex = _convex_areas(contours, a_min, a_max, min_convexity)
        convex = np.flatnonzero(convex)
        ellipses = map(cv2.fitEllipse, (contours[i] for i in convex))
        fits = np.array([(cu, cv_, w, h, ang) for (cu, cv_), (w, h), ang in ellipses], dtype=float).reshape(-1, 5)
        w, h, area = fits[:, 2], fits[:, 3], areas[convex]
        a, b = np.maximum(w, h) / 2, np.minimum(w, h) / 2
        with np.errstate(divide="ignore", invalid="ignore"):
            ok = (b > 0) & ~(a / b > 4.0) & ~(np.abs(area / (np.pi * a * b) - 1.0) > max_fill_error)
        theta = np.radians(fits[:, 4]) + np.where(h > w, np.pi / 2, 0.0)  # angle of the major axis
        out = np.column_stack([fits[:, 0], fits[:, 1], a, b, (theta + np.pi / 2) % np.pi - np.pi / 2, area])
        return out[ok]

    found = np.concatenate(map_kernel(regions, blocks)) if blocks else np.empty((0, 6))
    if not len(found):
        return CoarseCircles.empty()
    # one candidate per dot: windows of several sizes find the same region
    f = found[np.argsort(-found[:, 5])]
    f = f[first_of_each_place(f[:, :2], 0.5 * f[:, 3])]
    return CoarseCircles(f[:, :2].copy(), f[:, 2:4].copy(), f[:, 4].copy(), f[:, 5].copy(), np.ones(len(f)))



def first_of_each_place(centres: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """(N,) bool: going through the N regions in order, each one kept unless an earlier kept one lies
    within its own ``reach`` (px) of it (distance ≤ reach, ``np.hypot`` of the centres' difference).
    Only the pairs a k-d tree finds within the largest reach are measured: a textured image gives
    thousands of regions, and a pass over all earlier ones per region cost tens of ms."""
    keep = np.ones(len(centres), bool)
    if len(centres) < 2:
        return keep
    near = cKDTree(centres).query_pairs(float(reach.max()) * (1.0 + 1e-9) + 1e-9, output_type="ndarray")
    i, j = np.sort(near, axis=1).T  # i < j: i comes first
    d = np.hypot(centres[j, 0] - centres[i, 0], centres[j, 1] - centres[i, 1])
    close = ~(d > reach[i])
    i, j = i[close], j[close]
    for k in np.lexsort((j, i)):  # by the earlier region, in order
        if keep[i[k]]:
            keep[j[k]] = False
    return keep


def _convex_areas(contours, a_min: float, a_max: float, min_convexity: float) -> tuple[np.ndarray, np.ndarray]:
    """(area px², convex) (N,) of the N contours: ``cv2.contourArea`` of the contour to every bit (NaN for
    contours of fewer than 6 points or an area outside a_min … a_max), and whether it is at least
    ``min_convexity`` of its ``cv2.convexHull``'s, in one compiled pass
    (:func:`region_kernels.convex_contour_areas`) over the contours :func:`can_enclose` lets through."""
    area, convex = np.full(len(contours), np.nan), np.zeros(len(contours), bool)
    if not contours:
        return area, convex
    lens = np.fromiter(map(len, contours), np.int64, len(contours))
    some = np.flatnonzero(can_enclose(lens, a_min))
    if not len(some):
        return area, convex
    lens = lens[some]
    starts = np.concatenate([[0], np.cumsum(lens)[:-1]])
    points = np.concatenate([contours[i] for i in some]).reshape(-1, 2).astype(np.float64)
    area[some], convex[some] = convex_contour_areas(points, starts, lens, a_min, a_max, min_convexity)
    return area, convex


def can_enclose(lens: np.ndarray, a_min: float) -> np.ndarray:
    """(N,) bool: the closed contours of ``lens`` (N,) points (``cv2.CHAIN_APPROX_NONE``: each step to one of
    the 8 neighbouring pixels, the last back to the first) that may enclose ``a_min`` px² or more. n steps
    of at most √2 px are at most n √2 px long, and a closed curve of length L encloses at most L² / 4π
    (the isoperimetric inequality, which bounds the shoelace sum of a self-crossing curve too): n² / 2π.
    A textured image's thousands of specks of a few pixels are dropped before their points are gathered."""
    n = lens.astype(np.float64)
    return n * n >= 2.0 * np.pi * a_min * (1.0 - 1e-9)

"""Areas of many region contours at once, compiled: the candidate search's filters before ``cv2.fitEllipse``.

A textured 12 MP photograph thresholded against its local mean gives tens of thousands of
contours per window (:mod:`tasks.vision.detection.blobs`); a Python call of ``cv2.contourArea`` and
``cv2.convexHull`` for each cost more than OpenCV's own work. Here all contours of a window are one
array of integer points (concatenated, as ``cv2.findContours`` gives them) and one compiled pass
gives each contour's enclosed area and its convex hull's area. Both are shoelace sums of integer
coordinates, exact in float64 whatever the order of summation, and the convex hull of a point set
is unique: the areas equal ``cv2.contourArea(c)`` and ``cv2.contourArea(cv2.convexHull(c))`` to
every bit (tests/vision/test_detection_kernels.py). Units: px², the contour's pixel grid.
"""

from __future__ import annotations

import numpy as np
from numba import njit

_COMPILED = {"cache": True, "nogil": True}


@njit(**_COMPILED)
def _shoelace(x, y):  # pragma: no cover - compiled
    """|Σ (x_{i−1} y_i − y_{i−1} x_i)| / 2 of the closed polygon (x, y) (float64 of integers: exact)."""
    n = x.shape[0]
    s = 0.0
    px, py = x[n - 1], y[n - 1]
    for i in range(n):
        s += px * y[i] - py * x[i]
        px, py = x[i], y[i]
    return abs(0.5 * s)


@njit(**_COMPILED)
def _cross(ox, oy, ax, ay, bx, by):  # pragma: no cover - compiled
    return (ax - ox) * (by - oy) - (ay - oy) * (bx - ox)


@njit(**_COMPILED)
def _hull_area(x, y):  # pragma: no cover - compiled
    """Area of the convex hull of the points (x, y) (Andrew's monotone chain; collinear points
    dropped, which leaves the area unchanged)."""
    n = x.shape[0]
    if n < 3:
        return 0.0
    order = np.argsort(x * 4294967296.0 + y)  # by x, then y (coordinates below 2³¹: exact keys)
    hx = np.empty(2 * n)
    hy = np.empty(2 * n)
    k = 0
    for j in range(n):  # lower hull
        i = order[j]
        while k >= 2 and _cross(hx[k - 2], hy[k - 2], hx[k - 1], hy[k - 1], x[i], y[i]) <= 0.0:
            k -= 1
        hx[k], hy[k] = x[i], y[i]
        k += 1
    lower = k + 1
    for j in range(n - 2, -1, -1):  # upper hull
        i = order[j]
        while k >= lower and _cross(hx[k - 2], hy[k - 2], hx[k - 1], hy[k - 1], x[i], y[i]) <= 0.0:
            k -= 1
        hx[k], hy[k] = x[i], y[i]
        k += 1
    return _shoelace(hx[: k - 1], hy[: k - 1])  # the last point repeats the first


@njit(inline="always", **_COMPILED)
def _sized_contour(points, start, length, a_min, a_max):  # pragma: no cover - compiled
    """(u, v, area) of the closed contour points[start:start + length]; area NaN where it has fewer than
    6 points or its area lies outside a_min … a_max."""
    x = points[start : start + length, 0]
    y = points[start : start + length, 1]
    if length < 6:
        return x, y, np.nan
    a = _shoelace(x, y)
    return x, y, (a if a_min <= a <= a_max else np.nan)


@njit(**_COMPILED)
def contour_areas(points, starts, lens, a_min, a_max):  # pragma: no cover - compiled
    """(area, hull area) (N,) of N closed contours, contour j being points[starts[j]:starts[j] + lens[j]]
    ((P, 2) float64 integer u, v); a contour whose area lies outside a_min … a_max, or with fewer than
    6 points, gets NaN for both (not computed). The exact form :func:`convex_contour_areas` answers
    from (its test compares the two); the detector calls that one."""
    n = starts.shape[0]
    area = np.full(n, np.nan)
    hull = np.full(n, np.nan)
    for j in range(n):
        x, y, a = _sized_contour(points, starts[j], lens[j], a_min, a_max)
        if np.isnan(a):
            continue
        area[j] = a
        hull[j] = _hull_area(x, y)
    return area, hull


@njit(**_COMPILED)
def _octagon_and_box(x, y):  # pragma: no cover - compiled
    """(octagon, box) areas of the points (x, y). The octagon: the polygon through the points furthest
    along +u, +u+v, +v, −u+v, −u, −u−v, −v and +u−v, in that order (of points equally far, the first):
    each lies on the convex hull, in the hull's order, so the polygon lies inside the hull and its area
    is at most the hull's (exact for integer coordinates). The box: their bounding box's,
    (max u − min u)(max v − min v), at least the hull's. Eight running maxima in scalars: called once
    per contour, no arrays made."""
    b0 = b1 = b2 = b3 = b4 = b5 = b6 = b7 = -np.inf
    x0 = y0 = x1 = y1 = x2 = y2 = x3 = y3 = x4 = y4 = x5 = y5 = x6 = y6 = x7 = y7 = 0.0
    for i in range(x.shape[0]):
        u, v = x[i], y[i]
        if u > b0:
            b0, x0, y0 = u, u, v
        if u + v > b1:
            b1, x1, y1 = u + v, u, v
        if v > b2:
            b2, x2, y2 = v, u, v
        if v - u > b3:
            b3, x3, y3 = v - u, u, v
        if -u > b4:
            b4, x4, y4 = -u, u, v
        if -u - v > b5:
            b5, x5, y5 = -u - v, u, v
        if -v > b6:
            b6, x6, y6 = -v, u, v
        if u - v > b7:
            b7, x7, y7 = u - v, u, v
    # the shoelace sum of the eight points (integers: exact in any order)
    s = (x7 * y0 - y7 * x0) + (x0 * y1 - y0 * x1) + (x1 * y2 - y1 * x2) + (x2 * y3 - y2 * x3) \
        + (x3 * y4 - y3 * x4) + (x4 * y5 - y4 * x5) + (x5 * y6 - y5 * x6) + (x6 * y7 - y6 * x7)
    return abs(0.5 * s), (b0 + b4) * (b2 + b6)


@njit(**_COMPILED)
def convex_contour_areas(points, starts, lens, a_min, a_max, min_convexity):  # pragma: no cover - compiled
    """(area (N,), convex (N,) bool) of N closed contours as in :func:`contour_areas` (``a_min`` > 0):
    ``convex`` is ``(hull > 0) & (area / hull >= min_convexity)`` with the hull area of
    :func:`contour_areas`, to the same bit, the hull computed only where cheaper bounds leave the
    answer open: the hull holds the polygon of the extreme points along eight directions
    (:func:`_octagon_and_box`'s octagon ≤ hull) and lies within the points' bounding box (hull ≤ box),
    and IEEE division is monotonic, so area / octagon < min_convexity means not convex and area / box ≥
    min_convexity (octagon > 0) convex. A textured photograph's thousands of ragged regions are
    refused by the first bound without sorting their points."""
    n = starts.shape[0]
    area = np.full(n, np.nan)
    convex = np.zeros(n, np.bool_)
    for j in range(n):
        x, y, a = _sized_contour(points, starts[j], lens[j], a_min, a_max)
        if np.isnan(a):
            continue
        area[j] = a
        low, box = _octagon_and_box(x, y)
        if low > 0.0 and a / low < min_convexity:
            continue
        if low > 0.0 and a / box >= min_convexity:
            convex[j] = True
            continue
        hull = _hull_area(x, y)
        convex[j] = hull > 0.0 and a / hull >= min_convexity
    return area, convex


@njit(**_COMPILED)
def darker_than_mean(src, mean, offset):  # pragma: no cover - compiled
    """(H, W) uint8 mask, 255 where ``src[i, j] < mean[i, j] − offset`` ((H, W) float32 each, ``offset``
    float32; the difference rounded to float32 as numpy's ``mean - offset`` is), else 0: the regions'
    threshold in one pass, without the (H, W) float32 threshold image."""
    h, w = src.shape
    out = np.empty((h, w), np.uint8)
    for i in range(h):
        for j in range(w):
            out[i, j] = 255 if src[i, j] < np.float32(mean[i, j] - offset) else 0
    return out

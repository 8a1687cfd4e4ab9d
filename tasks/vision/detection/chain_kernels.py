"""Chain-code screening of many edge contours at once, compiled (:mod:`tasks.vision.detection.chaincode`).

A 12 MP photograph's edge map gives tens of thousands of contours and a million contour points; the
per-point arrays of the numpy form (steps, codes, a histogram over all contours) and the redrawing
of the kept contours cost more than OpenCV's tracing. Here one pass over each contour's points
gives its bounding box and code histogram and, for a kept contour whose every step is a unit
8-neighbour move, writes its points into the output map, which is what ``cv2.drawContours`` with
thickness 1 draws for such a contour (each line segment joins two neighbouring pixels). Units: px
of the edge map.
"""

from __future__ import annotations

import numpy as np
from numba import njit

_COMPILED = {"cache": True, "nogil": True}


@njit(**_COMPILED)
def screen_contours(u, v, starts, lens, lo, hi, max_aspect, min_distinct, max_code_fraction, code_of,
                    out):  # pragma: no cover - compiled
    """(keep (M,) bool, drawn (M,) bool) of M closed contours, contour j being the int64 pixels
    (u, v)[starts[j]:starts[j] + lens[j]]: kept when its bounding box's longer side B (px) satisfies
    lo ≤ B ≤ hi and B ≤ max_aspect × shorter side + 2, its Freeman codes (``code_of`` (3, 3), indexed
    [dv + 1, du + 1], −1 for no move; a step that is not an 8-neighbour move has no code) take at least
    ``min_distinct`` directions and none more than ``max_code_fraction`` of the coded steps. A kept
    contour whose steps all move to an 8-neighbour (or stay) is written into ``out`` ((H, W) uint8,
    255) and ``drawn``; the others are left to ``cv2.drawContours``."""
    m = starts.shape[0]
    w = out.shape[1]
    flat = out.reshape(-1)
    keep = np.zeros(m, np.bool_)
    drawn = np.zeros(m, np.bool_)
    hist = np.zeros(8, np.int64)
    for j in range(m):
        s, n = starts[j], lens[j]
        umin, umax, vmin, vmax = u[s], u[s], v[s], v[s]
        hist[:] = 0
        adjacent = True
        for i in range(s, s + n):
            nx = i + 1 if i + 1 < s + n else s  # closed: the last point steps to the first
            du, dv = u[nx] - u[i], v[nx] - v[i]
            umin, umax = min(umin, u[i]), max(umax, u[i])
            vmin, vmax = min(vmin, v[i]), max(vmax, v[i])
            if abs(du) <= 1 and abs(dv) <= 1:
                c = code_of[dv + 1, du + 1]
                if c >= 0:
                    hist[c] += 1
            else:
                adjacent = False
        big = max(umax - umin + 1, vmax - vmin + 1)
        small = min(umax - umin + 1, vmax - vmin + 1)
        if not (big >= lo and big <= hi and big <= max_aspect * small + 2):
            continue
        total, distinct, most = 0, 0, 0
        for c in range(8):
            total += hist[c]
            distinct += hist[c] > 0
            most = max(most, hist[c])
        if distinct < min_distinct or most / max(total, 1) > max_code_fraction:
            continue
        keep[j] = True
        if adjacent:
            drawn[j] = True
            for i in range(s, s + n):
                flat[v[i] * w + u[i]] = 255
    return keep, drawn

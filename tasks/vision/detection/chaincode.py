"""Freeman chain-code screening of edge contours: keep only edges that could be a dot's rim.

Each 8-connected edge contour (traced by ``cv2.findContours``) is encoded as its Freeman chain
code: the direction 0..7 (0 = +u, counting towards −v, 45° steps) from each contour pixel to the
next. A dot's rim, closed or broken into arcs, turns steadily through many directions with no
direction dominating; a straight line uses one or two codes, text strokes and boxes are too long
or too thin for a dot, specks too short. All contours are scored together (vectorised over the
concatenated points), not one by one.
"""

from __future__ import annotations

import cv2
import numpy as np

from tasks.vision.detection.chain_kernels import screen_contours

# code for step (du, dv), indexed [dv + 1, du + 1]; v points down, so code 2 is a step up (−v)
FREEMAN_CODE = np.array([[3, 2, 1], [4, -1, 0], [5, 6, 7]], dtype=np.int64)


def chain_codes(points: np.ndarray, seg_start: np.ndarray, seg_len: np.ndarray) -> np.ndarray:
    """Freeman codes of closed contours stored back to back.

    points: (P, 2) int pixel (u, v) of all contours concatenated; seg_start, seg_len: (M,) start
    index and length of each contour. Returns (P,) codes (step from each point to the next one of
    its own contour, wrapping around); -1 where a step is not a unit 8-neighbour move.
    """
    nxt = np.arange(points.shape[0]) + 1
    last = seg_start + seg_len - 1
    nxt[last] = seg_start  # close each contour
    d = points[nxt] - points
    ok = (np.abs(d) <= 1).all(axis=1)
    codes = np.full(points.shape[0], -1, dtype=np.int64)
    codes[ok] = FREEMAN_CODE[d[ok, 1] + 1, d[ok, 0] + 1]
    return codes


def filter_edges(edges: np.ndarray, d_min_px: float, d_max_px: float, min_distinct: int = 6,
                 max_code_fraction: float = 0.4, max_aspect: float = 4.0) -> tuple[np.ndarray, dict]:
    """Remove edge contours whose size or chain code cannot be a dot rim of diameter d_min..d_max px.

    Returns (filtered edge map uint8, stats dict with the contour counts before and after).
    """
    contours, _ = cv2.findContours(edges, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return np.zeros_like(edges), {"contours": 0, "kept": 0}
    lens = np.fromiter((len(c) for c in contours), dtype=np.int64, count=len(contours))
    pts = np.concatenate(contours, axis=0)[:, 0, :].astype(np.int64)
    starts = np.concatenate([[0], np.cumsum(lens)[:-1]])
    out = np.zeros_like(edges)
    # the size test on the bounding box, the chain-code histogram and the drawing of the kept contours
    # in one compiled pass (chain_kernels.screen_contours; a contour with a jump is drawn by OpenCV)
    keep, drawn = screen_contours(pts[:, 0].copy(), pts[:, 1].copy(), starts, lens, 0.45 * d_min_px,
                                  1.3 * d_max_px + 3, float(max_aspect), min_distinct, max_code_fraction,
                                  FREEMAN_CODE, out)
    kept = np.flatnonzero(keep)
    jumps = [contours[i] for i in np.flatnonzero(keep & ~drawn)]
    if jumps:
        cv2.drawContours(out, jumps, -1, 255, 1)
    if len(kept):
        out &= edges
    return out, {"contours": len(contours), "kept": len(kept)}

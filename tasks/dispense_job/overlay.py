"""An overlay of what the location found: boards (green accepted, red rejected, with the reason), the
accepted dispensing areas (yellow rectangle and centre) and the rejected candidates (grey)."""

from __future__ import annotations

import cv2
import numpy as np

from tasks.dispense_job.locate import Located


def draw_overlay(bgr: np.ndarray, found: Located) -> np.ndarray:
    """A copy of the BGR image (H, W, 3) uint8 with ``found`` drawn on it."""
    out = bgr.copy()
    for a in found.areas:
        if not a.accepted:
            cv2.polylines(out, [np.rint(a.rect.corners).astype(np.int32)], True, (140, 140, 140), 1, cv2.LINE_AA)
    for i, b in enumerate(found.boards):
        colour = (0, 200, 0) if b.ok else (0, 0, 230)
        cv2.polylines(out, [np.rint(b.board.rect.corners).astype(np.int32)], True, colour, 3, cv2.LINE_AA)
        label = f"b{i:02d}" + ("" if b.ok else f": {b.reason.split(':')[0]}")
        org = tuple(int(v) for v in np.rint(b.board.rect.corners.min(axis=0)))
        cv2.putText(out, label, org, cv2.FONT_HERSHEY_SIMPLEX, 0.9, colour, 2, cv2.LINE_AA)
        if b.area is not None:
            r = b.area.rect
            cv2.polylines(out, [np.rint(r.corners).astype(np.int32)], True, (0, 230, 255), 2, cv2.LINE_AA)
            cv2.drawMarker(out, (round(r.u), round(r.v)), (0, 230, 255), cv2.MARKER_CROSS, 20, 2)
    return out

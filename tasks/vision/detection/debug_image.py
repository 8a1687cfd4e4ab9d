"""A picture of what the detector saw: candidates, the grid found, or why it was refused.

:func:`draw_detection` returns a BGR copy of the image (scaled so that its longer side is at most
``max_side_px``) with every coarse candidate circle (thin, orange), each found dot's ellipse centre
and its (row, col) label (green), the grid's rows joined by lines (row 0 red, the others green:
the labelling's orientation at a glance), and a banner with "ok" or the rejection reason; on a
refusal, the lattice grown through the candidates (cyan: its neighbours joined, each point's
lattice coordinates), so that the dots it missed or the strays it took show.
Units: px of the input image; the drawing is scaled by one factor.
"""

from __future__ import annotations

import cv2
import numpy as np

from tasks.machine.plate import DotPlate
from tasks.vision.detection.result import GridDetection

CANDIDATE = (0, 140, 255)  # BGR
FOUND = (0, 200, 0)
FIRST_ROW = (0, 0, 230)
LATTICE = (230, 200, 0)
BANNER_OK = (0, 120, 0)
BANNER_FAIL = (0, 0, 180)


def _wrap(text: str, width: int) -> list[str]:
    words, lines, line = text.split(), [], ""
    for w in words:
        if line and len(line) + 1 + len(w) > width:
            lines.append(line)
            line = w
        else:
            line = f"{line} {w}".strip()
    return [*lines, line] if line else lines


def draw_detection(image: np.ndarray, det: GridDetection, plate: DotPlate, max_side_px: int = 1600) -> np.ndarray:
    """(H', W', 3) uint8 BGR drawing of ``det`` on ``image`` (grey (H, W) or BGR (H, W, 3)),
    scaled so that its longer side is between 800 px (or ``max_side_px`` if smaller) and ``max_side_px``."""
    bgr = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR) if image.ndim == 2 else image.copy()
    side = max(bgr.shape[:2])
    s = float(np.clip(side, min(800, max_side_px), max_side_px)) / side  # small images are enlarged to read
    if s != 1.0:
        bgr = cv2.resize(bgr, None, fx=s, fy=s, interpolation=cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR)
    h, w = bgr.shape[:2]
    lw = max(1, round(max(h, w) / 800))

    def pt(uv) -> tuple[int, int]:
        return round((uv[0] + 0.5) * s - 0.5), round((uv[1] + 0.5) * s - 0.5)

    if det.candidates_px is not None:
        diam = det.candidate_diameters_px
        if diam is None:
            diam = np.full(len(det.candidates_px), 10.0)
        for uv, d in zip(det.candidates_px, diam, strict=True):
            cv2.circle(bgr, pt(uv), max(2, round(d * s / 2)), CANDIDATE, lw, cv2.LINE_AA)
    if not det.ok and det.lattice_px is not None:
        _draw_lattice(bgr, det.lattice_px, det.lattice_coords, pt, lw)
    found = det.found
    if det.ok and found.any():
        uv = det.ellipse_centres if det.ellipse_centres is not None else det.centres
        grid = uv.reshape(plate.rows, plate.cols, 2)
        ok = found.reshape(plate.rows, plate.cols)
        for r in range(plate.rows):
            for c in range(plate.cols - 1):
                if ok[r, c] and ok[r, c + 1]:
                    cv2.line(bgr, pt(grid[r, c]), pt(grid[r, c + 1]), FIRST_ROW if r == 0 else FOUND, lw, cv2.LINE_AA)
        for (r, c), p, f in zip(plate.row_col(), uv, found, strict=True):
            if not f:
                continue
            cv2.drawMarker(bgr, pt(p), FOUND, cv2.MARKER_CROSS, 6 * lw, lw)
            cv2.putText(bgr, f"{r},{c}", (pt(p)[0] + 3 * lw, pt(p)[1] - 3 * lw), cv2.FONT_HERSHEY_SIMPLEX,
                        0.35 * lw, FOUND, lw, cv2.LINE_AA)
    text = (f"ok: {int(found.sum())} dots, {det.n_candidates} candidates, rotation {det.rotation_deg:.1f} deg"
            if det.ok else f"REFUSED: {det.reason}")
    lines = _wrap(f"{det.detector} {plate.rows}x{plate.cols}: {text}", max(20, w // (9 * lw)))
    line_h = 16 * lw
    cv2.rectangle(bgr, (0, 0), (w, line_h * len(lines) + 6 * lw), BANNER_OK if det.ok else BANNER_FAIL, -1)
    for i, line in enumerate(lines):
        cv2.putText(bgr, line, (4 * lw, line_h * (i + 1)), cv2.FONT_HERSHEY_SIMPLEX, 0.45 * lw, (255, 255, 255),
                    lw, cv2.LINE_AA)
    return bgr


MAX_LATTICE_LABELS = 60
"""A lattice of more points is drawn without its coordinates (they would cover it)."""


def _draw_lattice(bgr: np.ndarray, uv: np.ndarray, coords: np.ndarray, pt, lw: int) -> None:
    """Join the lattice points ``uv`` (L, 2) px whose coordinates ``coords`` (L, 2) are one step apart,
    and label each with its coordinates up to :data:`MAX_LATTICE_LABELS` points (``pt``: image px →
    drawing px)."""
    at = {tuple(c): k for k, c in enumerate(np.asarray(coords).tolist())}
    for (a, b), k in at.items():
        for nb in ((a + 1, b), (a, b + 1)):
            if nb in at:
                cv2.line(bgr, pt(uv[k]), pt(uv[at[nb]]), LATTICE, lw, cv2.LINE_AA)
        if len(at) <= MAX_LATTICE_LABELS:
                cv2.putText(bgr, f"{a},{b}", (pt(uv[k])[0] + 3 * lw, pt(uv[k])[1] + 12 * lw),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.35 * lw, LATTICE, lw, cv2.LINE_AA)

"""What the detector skips once the answer is settled (tasks/vision/detection/framework.py): the searches
for fainter or shadowed dots (the blur fallback, looking again, the log scale) on a lattice that holds a
bigger grid than the plate, which more candidates cannot make one window. On a large photograph of a big
grid they cost more than the rest of the detection ("Speed", docs/detector-comparison.md)."""

from __future__ import annotations

import cv2
import numpy as np

from tasks.machine.plate import DotPlate
from tasks.vision.detection import framework
from tasks.vision.detection.framework import detect_rrht

PLATE = DotPlate(rows=4, cols=3, pitch_mm=6.0, dot_diameter_mm=4.0)


def _sheet(rows: int, cols: int, dot_px: float = 14.0, size=(480, 640)) -> np.ndarray:
    """A light sheet with a rows × cols grid of dark dots (pitch 1.5 diameters), a little blurred and noisy."""
    img = np.full(size, 200, np.uint8)
    pitch = 1.5 * dot_px
    c0 = np.array([size[1] / 2 - (cols - 1) * pitch / 2, size[0] / 2 - (rows - 1) * pitch / 2])
    for r in range(rows):
        for c in range(cols):
            u, v = c0 + pitch * np.array([c, r])
            cv2.circle(img, (round(u * 16), round(v * 16)), int(dot_px / 2 * 16), 40, -1, cv2.LINE_AA, 4)
    img = cv2.GaussianBlur(img, (0, 0), 1.0)
    noise = np.random.default_rng(3).normal(0, 3, size)
    return np.clip(img + noise, 0, 255).astype(np.uint8)


def test_a_bigger_grid_is_refused_without_searching_for_faint_or_shadowed_dots(monkeypatch):
    """An 8 × 6 grid asked for as 4 × 3: every band's lattice holds many complete windows ("extra dots");
    the blur fallback's faint regions and the log-scale search are not made for it (both ran before)."""
    offsets, logged = [], []
    search, log_search = framework.contour_candidates, framework.on_log_scale

    def recorded(img, dark, d_min, d_max, offset=0.08, **kw):
        offsets.append(offset)
        return search(img, dark, d_min, d_max, offset, **kw)

    def recorded_log(*args, **kw):
        logged.append(True)
        return log_search(*args, **kw)

    monkeypatch.setattr(framework, "contour_candidates", recorded)
    monkeypatch.setattr(framework, "on_log_scale", recorded_log)
    det = detect_rrht(_sheet(8, 6), PLATE)
    assert not det.ok and det.reason.startswith("extra dots: 8x6 lattice holds")
    assert "complete 4x3 windows" in det.reason
    assert set(offsets) <= {0.08} and not logged
    det = detect_rrht(_sheet(4, 3), PLATE)  # the plate alone is found
    assert det.ok

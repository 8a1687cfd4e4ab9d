"""Public entry point: ``detect_grid(image, plate, detector)`` and the ``DETECTORS`` registry.

SYNOPSIS

    >>> from tasks.vision.detection import detect_grid
    >>> det = detect_grid(image, plate, "rrht", expected_rotation_deg=0.0)   # doctest: +SKIP
    >>> if det.ok: uv = det.centres          # (rows*cols, 2) px, row-major like plate.dot_centres_mm()
    ... else: print(det.reason)

Every detector takes an (H, W) uint8 grayscale image and a :class:`tasks.machine.plate.DotPlate` and
returns a :class:`tasks.vision.detection.result.GridDetection`; it never raises on image *content*
(blank, saturated, noise, a plate partly out of view without a prediction of its dots come back
with ``ok=False`` and a reason), only on a wrong input type (ValueError).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from tasks.machine.plate import DotPlate
from tasks.vision.detection.baselines import detect_blob, detect_hough
from tasks.vision.detection.framework import detect_rrht
from tasks.vision.detection.result import GridDetection

DETECTORS: dict[str, Callable[..., GridDetection]] = {
    "rrht": detect_rrht,
    "blob": detect_blob,
    "hough": detect_hough,
}


def detect_grid(image: np.ndarray, plate: DotPlate, detector: str = "rrht", *,
                expected_rotation_deg: float | None = None, px_per_mm_hint: float | None = None,
                mirrored: bool = False, expected_centres_px: np.ndarray | None = None) -> GridDetection:
    """Find the plate's rows × cols dots in ``image`` and order them like ``plate.dot_centres_mm()``.

    detector: "rrht" (the paper's framework, sub-pixel and perspective-corrected), "blob"
    (cv2.findCirclesGrid) or "hough" (cv2.HoughCircles).
    expected_rotation_deg: expected in-plane angle of the plate's +X (column) axis in the image,
    counter-clockwise on screen from +u (deg), e.g. from the commanded rotary-axis angle; it
    resolves the 90°/180° symmetry of the grid. Without it the orientation closest to 0° is
    taken and ``orientation_ambiguous`` is set for symmetric grids.
    px_per_mm_hint: approximate image scale on the plate (px per mm), optional.
    mirrored: the plate is seen from its back (handedness flipped).
    expected_centres_px: (rows*cols, 2) predicted dot positions (px), e.g. from the commanded axes
    through the nominal kinematics; with them "rrht" measures a plate partly out of the image on
    the dots wholly inside it (the others NaN; :mod:`tasks.vision.detection.partial_view`). The
    baselines need the whole grid.
    """
    try:
        fn = DETECTORS[detector]
    except KeyError:
        raise ValueError(f"unknown detector {detector!r}; choose one of {sorted(DETECTORS)}") from None
    return fn(image, plate, expected_rotation_deg=expected_rotation_deg, px_per_mm_hint=px_per_mm_hint,
              mirrored=mirrored, expected_centres_px=expected_centres_px)

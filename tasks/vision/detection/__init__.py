"""Dot-grid detection: the seed paper's RRHT framework (§4.1) and two OpenCV baselines.

No Prefect import. Public API: :func:`detect_grid`, :data:`DETECTORS`, :class:`GridDetection`.
Modules, one job each: ``preprocess`` (downsampling, median, gamma), ``edges`` (Canny),
``chaincode`` (Freeman chain-code contour filter), ``rrht`` (random Hough circles),
``blobs`` (region-contour candidates), ``verify`` (candidate appearance test),
``conics`` (batched ellipse fits, RANSAC), ``subpixel`` and ``edge_fit`` (full-resolution rim
fits), ``grid`` (lattice ordering), ``perspective`` (homographies, centre bias), ``framework``
(the RRHT pipeline), ``baselines`` (blob / Hough), ``debug_image`` (what the detector saw),
``synthetic`` (quick test images), ``stress`` (the renderer's photograph-like stress set)."""

from tasks.vision.detection.api import DETECTORS, detect_grid
from tasks.vision.detection.result import GridDetection

__all__ = ["DETECTORS", "GridDetection", "detect_grid"]

"""Baseline detectors in the same framework (same inputs, same GridDetection output).

* "blob": ``cv2.findCirclesGrid`` (symmetric grid) with a ``cv2.SimpleBlobDetector`` tuned to
  the plate's polarity and, given a scale hint, to the dot area. Its grid order is re-indexed
  to the plate's rows/cols with the same orientation rules as the RRHT framework.
* "hough": ``cv2.HoughCircles`` (gradient method) on a median-filtered image, then the same
  lattice ordering as the RRHT framework.

Both return raw centres (blob centroids / Hough centres): no sub-pixel rim fit and no
perspective-bias correction, and both need the whole grid in view: they take the predicted dot
positions (``expected_centres_px``) for a common signature but do not measure partial views.
Units: px.
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from tasks.machine.plate import DotPlate
from tasks.vision.detection.framework import search_scale
from tasks.vision.detection.grid import order_grid
from tasks.vision.detection.perspective import fit_homography
from tasks.vision.detection.preprocess import check_image
from tasks.vision.detection.result import GridDetection


def blob_detector(plate: DotPlate, d_min_px: float, d_max_px: float) -> cv2.SimpleBlobDetector:
    """SimpleBlobDetector for dots of diameter d_min..d_max px and the plate's polarity."""
    p = cv2.SimpleBlobDetector_Params()
    p.filterByColor = True
    p.blobColor = 0 if plate.dark_dots else 255
    p.filterByArea = True
    p.minArea = float(np.pi * (d_min_px / 2) ** 2 * 0.8)
    p.maxArea = float(np.pi * (d_max_px / 2) ** 2 * 1.2)
    p.filterByCircularity = True
    p.minCircularity = 0.6
    p.filterByConvexity = True
    p.minConvexity = 0.85
    p.filterByInertia = True
    p.minInertiaRatio = 0.3
    p.minDistBetweenBlobs = float(max(2.0, 0.5 * d_min_px))
    return cv2.SimpleBlobDetector_create(p)


def _finish(name: str, plate: DotPlate, centres_found: np.ndarray, order, t0: float, tm: dict,
            n_cand: int, sizes: np.ndarray | None = None) -> GridDetection:
    n = plate.rows * plate.cols
    if not order.ok:
        return GridDetection.failure(n, name, order.reason, elapsed_s=time.perf_counter() - t0,
                                     timings_s=tm, n_candidates=n_cand)
    c = centres_found[order.index]
    xy = plate.dot_centres_mm()[:, :2]
    axes = np.full((n, 2), np.nan) if sizes is None else np.repeat(sizes[order.index, None] / 2, 2, axis=1)
    return GridDetection(
        ok=True, reason="", detector=name, centres=c, residual_rms_px=np.full(n, np.nan),
        support_ratio=np.full(n, np.nan), elapsed_s=time.perf_counter() - t0, ellipse_centres=c.copy(),
        axes_px=axes, rotation_deg=order.rotation_deg, orientation_ambiguous=order.ambiguous,
        homography=fit_homography(xy, c), n_candidates=n_cand, timings_s=tm,
    )


def detect_blob(image: np.ndarray, plate: DotPlate, *, expected_rotation_deg: float | None = None,
                px_per_mm_hint: float | None = None, mirrored: bool = False,
                expected_centres_px: np.ndarray | None = None) -> GridDetection:
    """``cv2.findCirclesGrid`` baseline; see the module docstring."""
    t0 = time.perf_counter()
    image = check_image(image)
    n = plate.rows * plate.cols
    _, d_min, d_max = search_scale(image.shape, plate, px_per_mm_hint, 12.0, 768)
    det = blob_detector(plate, d_min, d_max)
    t1 = time.perf_counter()
    found, c = cv2.findCirclesGrid(image, (plate.cols, plate.rows), flags=cv2.CALIB_CB_SYMMETRIC_GRID,
                                   blobDetector=det)
    tm = {"find_circles_grid": time.perf_counter() - t1}
    if not found or c is None or len(c) != n:
        return GridDetection.failure(n, "blob", "cv2.findCirclesGrid found no complete "
                                     f"{plate.rows}x{plate.cols} grid", elapsed_s=time.perf_counter() - t0,
                                     timings_s=tm)
    pts = c.reshape(-1, 2).astype(float)
    k = np.arange(n)
    mn = np.stack([k // plate.cols, k % plate.cols], axis=1)
    t2 = time.perf_counter()
    order = order_grid(pts, plate, expected_rotation_deg=expected_rotation_deg, mirrored=mirrored,
                       lattice=(mn, np.ones(n, bool)))
    tm["ordering"] = time.perf_counter() - t2
    return _finish("blob", plate, pts, order, t0, tm, n)


def detect_hough(image: np.ndarray, plate: DotPlate, *, expected_rotation_deg: float | None = None,
                 px_per_mm_hint: float | None = None, mirrored: bool = False,
                 expected_centres_px: np.ndarray | None = None, max_edge_density: float = 0.05) -> GridDetection:
    """``cv2.HoughCircles`` baseline; see the module docstring.

    Images where more than ``max_edge_density`` of the pixels are Canny edges are refused.
    """
    t0 = time.perf_counter()
    image = check_image(image)
    _, d_min, d_max = search_scale(image.shape, plate, px_per_mm_hint, 12.0, 768)
    t1 = time.perf_counter()
    med = cv2.medianBlur(image, 5)
    density = float(np.count_nonzero(cv2.Canny(med, 50, 100))) / med.size
    if density > max_edge_density:  # HoughCircles' run time explodes on noise (minutes per image)
        return GridDetection.failure(plate.rows * plate.cols, "hough", f"{100 * density:.0f}% of the pixels "
                                     "are edges: noise or texture, no Hough search",
                                     elapsed_s=time.perf_counter() - t0, timings_s={})
    spacing_min = d_min * plate.pitch_range_mm[0] / plate.dot_diameter_mm * 0.6
    circles = cv2.HoughCircles(med, cv2.HOUGH_GRADIENT, dp=1, minDist=max(spacing_min, 2.0), param1=100,
                               param2=max(10.0, 0.3 * np.pi * d_min / 2), minRadius=int(d_min / 2),
                               maxRadius=int(np.ceil(d_max / 2)))
    tm = {"hough_circles": time.perf_counter() - t1}
    if circles is None or len(circles[0]) == 0:
        return GridDetection.failure(plate.rows * plate.cols, "hough", "cv2.HoughCircles found no circles",
                                     elapsed_s=time.perf_counter() - t0, timings_s=tm)
    cir = circles[0].astype(float)
    pts, sizes = cir[:, :2], 2 * cir[:, 2]
    t2 = time.perf_counter()
    order = order_grid(pts, plate, sizes=sizes, image_shape=image.shape,
                       expected_rotation_deg=expected_rotation_deg, mirrored=mirrored)
    tm["ordering"] = time.perf_counter() - t2
    return _finish("hough", plate, pts, order, t0, tm, len(pts), sizes)

"""The RRHT-based dot-grid detection framework (seed paper §4.1, adapted to dot grids).

    image ─ downsample ─ median + gamma ─ Canny ─ chain-code filter ─ RRHT circles (coarse)
          ─ grid ordering ─ sub-pixel ellipses in circular ROIs at full size (RANSAC + LSQ)
          ─ homography + perspective-bias correction ─ GridDetection

SYNOPSIS

    >>> from tasks.detection.framework import detect_rrht
    >>> det = detect_rrht(image, plate, px_per_mm_hint=60.0)   # doctest: +SKIP
    >>> det.ok, det.centres.shape                                # (True, (49, 2))  # doctest: +SKIP

Units: px of the input image unless a name says otherwise; frames as in :mod:`tasks.detection.result`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from tasks.detection.chaincode import filter_edges
from tasks.detection.edges import canny_edges
from tasks.detection.grid import order_grid
from tasks.detection.partial_view import too_few_dots
from tasks.detection.perspective import correct_bias, fit_homography
from tasks.detection.preprocess import auto_gamma, check_image, coarse_to_full, downsample, full_to_coarse
from tasks.detection.result import GridDetection
from tasks.detection.rrht import RRHTParams, rrht_circles
from tasks.detection.subpixel import SubpixelParams, refine_ellipses, rim_reach_px
from tasks.plate import DotPlate


@dataclass
class FrameworkParams:
    coarse_target_diameter_px: float = 12.0  # dot diameter aimed at on the coarse image
    coarse_width_px: int = 768  # without a scale hint: coarse image about this wide
    median_ksize: int = 3
    min_support: float = 0.5  # per-dot fraction of the rim that must give inlier points
    bias_iterations: int = 2
    seed: int = 0
    rrht: RRHTParams = field(default_factory=RRHTParams)
    subpixel: SubpixelParams = field(default_factory=SubpixelParams)


def cut_by_border(centres_px: np.ndarray, major_semi_axes_px: np.ndarray, gap_ratio: float,
                  image_shape: tuple[int, int]) -> np.ndarray:
    """(K,) bool: dots (centres (K, 2) px, major semi-axes (K,) px) whose rim rays
    (:func:`tasks.detection.subpixel.rim_reach_px`), plus 2 px, would leave an image of
    ``image_shape`` (H, W): the border cuts what their rim fit needs."""
    h, w = image_shape
    reach = rim_reach_px(major_semi_axes_px, gap_ratio) + 2.0
    u, v = centres_px[:, 0], centres_px[:, 1]
    return (u < reach) | (u > w - 1 - reach) | (v < reach) | (v > h - 1 - reach)


def search_scale(shape: tuple[int, int], plate: DotPlate, px_per_mm_hint: float | None,
                 target_d: float, coarse_width: int) -> tuple[int, float, float]:
    """(downsampling factor, min and max dot diameter in full-size px) for the coarse search.

    With a hint the diameter is known to within perspective foreshortening and focus changes
    (×0.55…1.5); without one, dots from 1/128 to 1/14 of the longer image side are searched.
    """
    big = max(shape)
    if px_per_mm_hint is not None and px_per_mm_hint > 0:
        d = px_per_mm_hint * plate.dot_diameter_mm
        factor = int(np.clip(np.floor(d / target_d), 1, 8))
        return factor, 0.55 * d, 1.5 * d
    factor = max(1, round(big / coarse_width))
    return factor, big / 128.0, big / 14.0


def detect_rrht(image: np.ndarray, plate: DotPlate, *, expected_rotation_deg: float | None = None,
                px_per_mm_hint: float | None = None, correct_perspective: bool = True,
                mirrored: bool = False, expected_centres_px: np.ndarray | None = None,
                params: FrameworkParams | None = None) -> GridDetection:
    """Detect and order the plate's dots with the RRHT framework (see module docstring).

    image: (H, W) uint8 grayscale. plate: the expected plate (rows, cols, pitch, diameter,
    polarity). expected_rotation_deg: prior on the in-plane angle of the plate +X axis (ccw on
    screen, deg) that resolves the grid's rotational symmetry. px_per_mm_hint: approximate scale
    on the plate (px/mm); speeds up and hardens the search. correct_perspective: subtract the
    perspective bias of circle centres. mirrored: the plate is seen from its back.
    expected_centres_px: (rows*cols, 2) predicted dot positions (full-size px); with them a plate
    partly out of the image is measured on the dots inside it (:mod:`tasks.detection.partial_view`),
    and a dot whose rim rays the image border would cut (:func:`cut_by_border`) is left out.
    Without them the whole grid must be found and a dot at the border is fitted on the rays
    inside the image (calibration views, where the target fills the field).
    """
    p = params or FrameworkParams()
    t_start = time.perf_counter()
    n = plate.rows * plate.cols
    tm: dict[str, float] = {}

    def fail(reason: str, **kw) -> GridDetection:
        return GridDetection.failure(n, "rrht", reason, elapsed_s=time.perf_counter() - t_start,
                                     timings_s=tm, **kw)

    image = check_image(image)
    factor, d_min, d_max = search_scale(image.shape, plate, px_per_mm_hint, p.coarse_target_diameter_px,
                                        p.coarse_width_px)
    t0 = time.perf_counter()
    small = downsample(image, factor)
    pre, _ = auto_gamma(small, p.median_ksize)
    t1 = time.perf_counter()
    tm["preprocess"] = t1 - t0
    em = canny_edges(pre)
    edges, _ = filter_edges(em.edges, d_min / factor, d_max / factor)
    t2 = time.perf_counter()
    tm["edges"] = t2 - t1
    if not edges.any():
        return fail("no edges that could be dot rims (blank, saturated or featureless image)")
    circles = rrht_circles(em, edges, plate.dark_dots, d_min / factor / 2, d_max / factor / 2,
                           p.rrht, seed=p.seed, timings=tm)
    if len(circles) < 4:
        return fail(f"found {len(circles)} circular targets, not a {plate.rows}x{plate.cols} dot grid",
                    n_candidates=len(circles))
    t3 = time.perf_counter()
    prior = None if expected_centres_px is None else full_to_coarse(expected_centres_px, factor)
    order = order_grid(circles.centres, plate, sizes=2 * circles.axes[:, 0], image_shape=small.shape,
                       expected_rotation_deg=expected_rotation_deg, mirrored=mirrored, expected_centres=prior)
    tm["ordering"] = time.perf_counter() - t3
    if not order.ok:
        return fail(order.reason, n_candidates=len(circles))
    rc = plate.row_col()
    found = order.index >= 0
    gap_ratio = plate.pitch_range_mm[0] / plate.dot_diameter_mm - 1.0
    if prior is not None:  # a view that may be partial leaves out the dots the border cuts
        found[found] = ~cut_by_border(coarse_to_full(circles.centres[order.index[found]], factor),
                                      circles.axes[order.index[found], 0] * factor, gap_ratio, image.shape)
    too_few = too_few_dots(int(found.sum()), n)
    if too_few:
        return fail(too_few, n_candidates=len(circles))
    idx = order.index[found]
    c0 = coarse_to_full(circles.centres[idx], factor)
    fits = refine_ellipses(image, c0, circles.axes[idx] * factor, circles.theta[idx], plate.dark_dots,
                           gap_ratio, factor, p.subpixel, seed=p.seed, timings=tm)
    bad = ~fits.ok | (fits.support < p.min_support)
    moved = np.linalg.norm(fits.centres - c0, axis=1) > np.maximum(0.5 * fits.axes[:, 1], 2.0 * factor)
    bad |= moved
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        r, c = rc[found][k]
        return fail(f"rim fit failed for {int(bad.sum())} dot(s), first at row {r} col {c} "
                    f"(support {fits.support[k]:.2f})", n_candidates=len(circles))
    t5 = time.perf_counter()
    xy = plate.dot_centres_mm()[found, :2]
    if correct_perspective:
        centres, hom = correct_bias(fits.centres, xy, plate.dot_diameter_mm / 2, p.bias_iterations)
    else:
        centres, hom = fits.centres.copy(), fit_homography(xy, fits.centres)
    tm["perspective"] = time.perf_counter() - t5

    def per_dot(values: np.ndarray) -> np.ndarray:  # found dots' values → (rows*cols, ...), NaN for the rest
        out = np.full((n, *values.shape[1:]), np.nan)
        out[found] = values
        return out

    return GridDetection(
        ok=True, reason="", detector="rrht", centres=per_dot(centres), residual_rms_px=per_dot(fits.residual_rms_px),
        support_ratio=per_dot(fits.support), elapsed_s=time.perf_counter() - t_start,
        ellipse_centres=per_dot(fits.centres), axes_px=per_dot(fits.axes), edge_sigma_px=per_dot(fits.edge_sigma_px),
        rotation_deg=order.rotation_deg,
        orientation_ambiguous=order.ambiguous, homography=hom, n_candidates=len(circles), timings_s=tm,
    )
